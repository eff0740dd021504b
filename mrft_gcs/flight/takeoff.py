"""Take-off controller (paper eq. 21, Table V): PI on altitude, then MRFT around hover.

The vehicle starts on the ground with no knowledge of its hover thrust. A PI on
the altitude error lifts it; once the measured altitude passes ``delta_p``
(the position form of the switching condition ``C``) the controller switches,
for good, to the MRFT with the last PI output ``u_z0`` as the relay's bias:
``u = u_z0 +- h_alt``. With ``u_z0`` close to hover the oscillation is nearly
symmetric, which is what the altitude classifier was trained on.

With a known hover thrust (``relay_bias``: the autopilot's own estimate, the
"prior knowledge" the paper allows for a faster, smoother take-off) the climb is
instead a PD on altitude around that hover thrust (``u = hover (1 + a/g)``,
``a = kp e - kd v``), and the relay starts, with that hover thrust as its bias,
only once the vehicle holds the set point (within ``settle_m`` and
``settle_speed_m_s``, or after ``settle_max_s``), about the altitude it holds
then. A climb creeping up its last ``brake_m`` on the vehicle's drag is held where
it is about to be instead, and its relay starts only once the thrust that held the
vehicle there is that bias (``TakeoffSettings.brake_m``, ``hover_check_tol``).
Started from a climb 0.9 m below the set point, as eq. 21 does, the altitude
MRFT at the distinguishing phase (beta -0.7) overshoots into a slow, lopsided cycle
(about twice the period) that the classifier misreads with full confidence.

Table V values are the defaults. They were optimised by the paper for a take-off
that always succeeds across the whole parameter domain, which can be slow (the
integrator winds up from zero); ``u_init`` preloads the integrator with a
fraction of a known hover thrust (the autopilot's own estimate, e.g.
``MPC_THR_HOVER``), the "prior knowledge" shortcut the paper suggests.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from mrft_gcs.profiles import G_M_S2
from mrft_gcs.relay import MRFT

__all__ = ["TakeoffSettings", "TakeoffController", "TABLE_V"]


@dataclass(frozen=True)
class TakeoffSettings:
    """Take-off and relay amplitudes; units in the names (thrust is normalised, [0, 1]).

    Defaults are the paper's Table V (``h_alt`` 10.746 % ESC, ``h_att`` 5 % ESC,
    bounding relay ``h_o1 = h_o2 = 0.05`` rad, ``eps1, eps2 = 1, 2`` m).
    """

    kc_tf: float = 9.4969e-2  # thrust per m
    ki_tf: float = 9.8754e-3  # thrust per (m s)
    delta_p_m: float = 0.11984
    h_alt: float = 0.10746
    h_att: float = 0.05
    h_o1_rad: float = 0.05
    h_o2_rad: float = 0.05
    eps1_m: float = 1.0
    eps2_m: float = 2.0
    climb_pd: tuple[float, float] = (6.0, 4.0)  # (1/s^2, 1/s): climb with a known hover thrust
    #: integral gain of that climb (1/s^3; with climb_pd the poles are -2 and -1 +- 1j),
    #: integrating only near the set point and nearly at rest (the offset a wrong guess
    #: leaves, not the climb's own transient): it learns the hover thrust the guess got
    #: wrong, where the PD alone holds the vehicle under the set point and a relay biased
    #: at the guess sinks into a lopsided cycle
    climb_ki: float = 4.0
    climb_int_band_m: float = 0.3
    climb_int_speed_m_s: float = 0.1
    #: at rest off the set point (climb rate within ``rest_speed_m_s`` for ``rest_s``) the
    #: thrust that holds the vehicle *is* the hover thrust: the PD's steady effort is
    #: folded into the integral at once (once per climb), rather than integrated over
    #: seconds: a climb resting just outside the integral's band would creep for seconds
    rest_speed_m_s: float = 0.05
    rest_s: float = 0.5
    #: a climb creeping up its last ``brake_m`` slower than this (over all of the last
    #: ``hover_check_s``) is held by the thrust it gets: where that (force balance) is off
    #: the hover thrust by more than ``hover_check_tol`` the guess is wrong and is corrected
    #: at once (once per climb, as the fold at rest): the PD's steady effort against a wrong
    #: guess otherwise ebbs only as fast as the integral learns, a creep of 2-3 s at 0.1
    #: m/s; the drag at that speed is 1-3 % of hover, the brake's check of the thrust held
    #: and the integral mop up. Only where the climb may be braked (``no_brake`` off): the
    #: fold overstates hover by that drag, which a relay started unbraked does not check.
    #: 0: off
    creep_speed_m_s: float = 0.15
    #: a creep read further off the guess than this share is not taken: the hover parameter
    #: is rarely that wrong, a climb still settling after a relay's run-away can read so
    #: (0.34 against 0.49 on PX4 SITL), and the integral still learns a real error
    creep_max_share: float = 0.26
    settle_m: float = 0.05
    settle_speed_m_s: float = 0.05
    settle_max_s: float = 8.0
    #: the climb's last stretch: rising within ``brake_m`` under the set point at less than
    #: ``brake_speed_m_s`` (but faster than ``settle_speed_m_s``), the climb holds where the
    #: vehicle will be ``brake_lead_s`` later instead (once per climb), and the relay starts
    #: about that altitude: vertical drag (the altitude model's T1) over-damps the PD, which
    #: then creeps its last stretch for a second or more
    brake_m: float = 0.3
    brake_speed_m_s: float = 0.2
    brake_lead_s: float = 0.3
    #: a braked climb's relay starts only once the thrust that held the vehicle over the
    #: last ``hover_check_s`` (its mean command over ``1 + a/g``, ``a`` the climb rate's
    #: slope) is within ``hover_check_tol`` of the relay's bias: a wrong hover guess passes
    #: slowly near the hold at the top of a swing, and a relay started there would be
    #: biased at the wrong guess (and go lopsided)
    hover_check_s: float = 0.3
    hover_check_tol: float = 0.02


#: The paper's Table V.
TABLE_V = TakeoffSettings()


class TakeoffController:
    """Eq. 21 as a streaming controller: ``reset()``, ``step(t_s, z_up_m) -> thrust``.

    Parameters
    ----------
    z_ref_m : float
        Altitude set point above the take-off point (m, up).
    settings : TakeoffSettings
        Gains, switching altitude and relay amplitude (Table V by default).
    beta : float
        MRFT parameter of the altitude relay (the altitude domain's distinguishing phase).
    u_init : float
        Initial integrator value (normalised thrust); 0 is the paper's cold start.
    band_m : float
        Noise band of the relay (m).
    relay_bias : float, optional
        Bias of the relay (normalised thrust) instead of the last PI output.

    Examples
    --------
    >>> c = TakeoffController(z_ref_m=1.0, u_init=0.4)
    >>> round(c.step(0.0, 0.0), 4)   # PI: 0.4 + kc * 1 m
    0.495
    >>> c.switched
    False
    >>> _ = c.step(0.1, 0.2)          # passed delta_p: MRFT from now on
    >>> c.switched, round(c.u_z0, 4)
    (True, 0.495)
    """

    def __init__(self, z_ref_m: float = 1.0, settings: TakeoffSettings = TABLE_V,
                 beta: float = 0.0, u_init: float = 0.0, band_m: float = 0.0,
                 h_alt: float | None = None, relay_bias: float | None = None) -> None:
        if not (math.isfinite(z_ref_m) and z_ref_m > settings.delta_p_m):
            raise ValueError("z_ref_m must lie above the switching altitude delta_p")
        self.z_ref_m = z_ref_m
        self.settings = settings
        self.h = settings.h_alt if h_alt is None else h_alt
        self.beta = beta
        self.u_init = u_init
        self.band_m = band_m
        self.relay_bias = relay_bias
        self.reset()

    def reset(self) -> None:
        self.integral = self.u_init
        self.a_int = 0.0  # the climb's integral term (m/s^2)
        self.t_rest: float | None = None  # since when the climb is at rest off its set point
        self.folded = False
        self.creep_folded = False
        self.creep_hover = math.nan  # the hover thrust the creep read (normalised thrust)
        self.t_prev: float | None = None
        self.t_climb: float | None = None
        self.z_hold_m = self.z_ref_m  # where the climb brings the vehicle to rest
        self.braked = False
        self.recent: deque[tuple[float, float, float]] = deque()  # (t, thrust, climb rate)
        self.no_brake = False  # set by the caller: the climb may not be braked now
        self.switched = False
        self.u_z0 = math.nan
        self.t_switch = math.nan
        self.relay: MRFT | None = None
        self.u = 0.0
        self.z_relay_m = self.z_ref_m  # the altitude the relay oscillates about

    def resettle(self, hover: float | None = None) -> bool:
        """Stop the relay and climb back: the PD about the hover thrust holds the set point,
        and the relay starts again, as after the first climb, once the vehicle holds it.

        A relay restarted away from its set point (after a run-away, or on a lopsided
        cycle) can lock into the slow, lopsided cycle described above, about twice the
        period of the one started at rest, again and again. The hover thrust is ``hover``
        when given (the mean thrust of the relay's own cycles: over a periodic cycle the
        mean vertical acceleration is zero, so a wrong first guess is corrected), else the
        relay's bias ``u_z0``. False, and nothing changed, before the first switch.
        """
        if not self.switched or not math.isfinite(self.u_z0):
            return False
        ok = hover is not None and math.isfinite(hover) and 0.0 < hover < 1.0
        self.relay_bias = float(hover) if ok and hover is not None else self.u_z0
        self.switched = False
        self.relay = None
        self.t_prev = self.t_climb = self.t_rest = None
        self.z_hold_m, self.braked = self.z_ref_m, False
        self.recent.clear()
        self.a_int = 0.0
        self.folded = self.creep_folded = False
        return True

    def step(self, t_s: float, z_up_m: float, vz_up_m_s: float | None = None) -> float:
        """Thrust command (normalised, clipped to [0, 1]) for the altitude sample at ``t_s``.

        ``vz_up_m_s`` (climb rate) is needed for the known-hover climb.
        """
        e = self.z_ref_m - z_up_m
        if not self.switched and self.relay_bias is not None and vz_up_m_s is not None:
            return self._climb(t_s, e, vz_up_m_s)
        if self.switched:
            e = self.z_relay_m - z_up_m
        if not self.switched:
            dt = 0.0 if self.t_prev is None else max(t_s - self.t_prev, 0.0)
            self.t_prev = t_s
            self.integral += self.settings.ki_tf * e * dt
            u = self.settings.kc_tf * e + self.integral
            if z_up_m >= self.settings.delta_p_m:
                self.switched = True
                last = self.u if self.relay_bias is None else self.relay_bias
                self.u_z0 = float(np.clip(last, 0.0, 1.0))  # the last PI output
                self.t_switch = t_s
                self.relay = MRFT(self.beta, self.h, bias=self.u_z0, band=self.band_m)
            else:
                self.u = float(np.clip(u, 0.0, 1.0))
                return self.u
        assert self.relay is not None
        self.u = float(np.clip(self.relay.step(e)[0], 0.0, 1.0))
        return self.u

    def _climb(self, t_s: float, e: float, vz: float) -> float:
        st, guess = self.settings, float(self.relay_bias)  # type: ignore[arg-type]
        g = G_M_S2
        if self.t_climb is None:
            self.t_climb = self.t_prev = t_s
        t0 = self.t_climb
        dt = max(t_s - (self.t_prev if self.t_prev is not None else t_s), 0.0)
        self.t_prev = t_s
        z = self.z_ref_m - e
        airborne = z >= st.delta_p_m
        if (not self.braked and not self.no_brake and airborne and 0 < e < st.brake_m
                and (self.a_int == 0.0 or self.folded or self.creep_folded)
                and st.settle_speed_m_s < vz < st.brake_speed_m_s):
            # creeping up the last stretch: hold where it is about to be (settings), unless
            # the integral has begun to learn a wrong guess; a fold at rest measured the
            # guess's error at once, and the climb after it creeps the same way
            self.z_hold_m, self.braked = z + st.brake_lead_s * vz, True
        e = self.z_hold_m - z
        if airborne and abs(e) < st.climb_int_band_m and abs(vz) < st.climb_int_speed_m_s:
            self.a_int = float(np.clip(self.a_int + st.climb_ki * e * dt, -0.3 * g, 0.3 * g))
        resting = airborne and abs(e) >= st.settle_m and abs(vz) < st.rest_speed_m_s and \
            not self.folded
        self.t_rest = (self.t_rest if self.t_rest is not None else t_s) if resting else None
        if self.t_rest is not None and t_s - self.t_rest >= st.rest_s:
            # what the PD adds to hold it here is what the guess got wrong
            self.a_int = float(np.clip(self.a_int + st.climb_pd[0] * e - st.climb_pd[1] * vz,
                                       -0.3 * g, 0.3 * g))
            self.folded, self.t_rest = True, None
        hover = float(np.clip(guess * (1.0 + self.a_int / g), 0.0, 1.0))  # what holds it
        if (airborne and not (self.folded or self.creep_folded or self.no_brake)
                and 0.0 < e < st.brake_m and self.recent and all(0.0 <= r[2] < st.creep_speed_m_s
                                        for r in self.recent)):
            held = self._thrust_held()
            if math.isfinite(held) and guess > 0 and \
                    st.hover_check_tol < abs(held / hover - 1.0) <= st.creep_max_share:
                self.a_int = float(np.clip(g * (held / guess - 1.0), -0.3 * g, 0.3 * g))
                self.creep_folded = True
                hover = float(np.clip(guess * (1.0 + self.a_int / g), 0.0, 1.0))
                self.creep_hover = hover
        at_rest = abs(e) < st.settle_m and abs(vz) < st.settle_speed_m_s
        if at_rest and self.braked:  # and not at the top of a swing on a wrong guess
            held = self._thrust_held()
            at_rest = math.isfinite(held) and abs(held / hover - 1.0) < st.hover_check_tol
        if airborne and (at_rest or t_s - t0 > st.settle_max_s):
            self.switched = True
            self.u_z0 = hover
            self.t_switch = t_s
            self.z_relay_m = z
            self.relay = MRFT(self.beta, self.h, bias=hover, band=self.band_m)
            self.u = float(np.clip(self.relay.step(0.0)[0], 0.0, 1.0))
            return self.u
        a = float(np.clip(st.climb_pd[0] * e - st.climb_pd[1] * vz + self.a_int,
                          -0.3 * g, 0.3 * g))
        self.u = float(np.clip(guess * (1.0 + a / g), 0.0, 1.0))
        self.recent.append((t_s, self.u, vz))
        while self.recent[0][0] < t_s - st.hover_check_s:
            self.recent.popleft()
        return self.u

    def _thrust_held(self) -> float:
        """The thrust that held the vehicle over the last ``hover_check_s`` (force balance:
        mean command / (1 + a/g), ``a`` the least-squares slope of the climb rate; drag at
        the near-rest speeds where this is asked is a percent or two); nan while that is
        not yet covered."""
        recent = self.recent
        if len(recent) < 5 or recent[-1][0] - recent[0][0] < 0.8 * self.settings.hover_check_s:
            return math.nan
        t, u, v = np.array(recent).T
        tc = t - t.mean()
        a = float(tc @ (v - v.mean()) / (tc @ tc))
        return float(np.clip(u.mean() / (1.0 + a / G_M_S2), 0.0, 1.0))
