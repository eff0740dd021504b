"""Lift-off as the attitude sees it: when the roll and pitch relays may start.

The climb is flown by the take-off controller (:mod:`mrft_gcs.flight.takeoff`); the attitude
relays start once the vehicle leaves the ground: above ``airborne_m``, the altitude relay
running, or (with enough thrust to leave the ground) roll, pitch or their rates off their
ground values by more than the noise measured on the ground. The delayed altitude alone
would give a CoM offset time to tilt the vehicle first.

:class:`FirstSwingBrake` keeps the first swings of those relays, which start on no knowledge of
the axis, well inside the tilt limit: a light vehicle with a high thrust-to-weight swings at
the starting h far further than the cycle it is sized for, and a centre-of-mass torque weakens
the push that brakes every other swing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from mrft_gcs.flight.controllers import FlightState
from mrft_gcs.flight.phases.shared import Shared
from mrft_gcs.flight.phases.state import LoopTest
from mrft_gcs.loops import Loop

__all__ = ["FirstSwingBrake", "LiftoffDetector", "swing_stop"]


class LiftoffDetector:
    """Sees the vehicle leave the ground; its rate threshold also tells a turn of an axis.

    Parameters
    ----------
    shared : Shared
        The sequence's shared state (settings, noise measured on the ground, loops).
    """

    def __init__(self, shared: Shared) -> None:
        self.sh = shared
        self.lifted = False  # the attitude relays run (lift-off seen)
        #: ground roll, pitch (rad); angle thresholds roll, pitch (rad); rate thresholds
        #: p, q (rad/s); None before the take-off command
        self.thresholds: tuple[float, ...] | None = None

    def arm(self, s: FlightState) -> None:
        """At the take-off command: thresholds from the noise measured on the ground."""
        cfg = self.sh.config
        sig = self.sh.att_noise.sigma()
        if self.sh.att_noise.samples >= 8:
            r0, p0 = np.mean(np.asarray(self.sh.att_noise.v)[:, :2], axis=0)
        else:
            r0, p0 = s.roll_rad, s.pitch_rad
        rates = [max(cfg.liftoff_rate_floor_rad_s, cfg.liftoff_rate_sigmas * x)
                 if np.isfinite(x) else cfg.liftoff_rate_floor_rad_s for x in sig[2:]]
        self.thresholds = (float(r0), float(p0), self.sh.noise_band(Loop.ROLL),
                           self.sh.noise_band(Loop.PITCH), *rates)

    def step(self, s: FlightState, z: float) -> bool:
        """Whether the vehicle has left the ground (``z``: height over take-off, m); once
        seen, it stays so."""
        self.lifted = self._lifted_off(s, z)
        return self.lifted

    def _lifted_off(self, s: FlightState, z: float) -> bool:
        """The vehicle has left the ground: altitude, or roll/pitch off their ground values."""
        cfg = self.sh.config
        if self.lifted or z > cfg.airborne_m or self.sh.takeoff.switched:
            return True

        guess = cfg.hover_thrust_guess
        if self.thresholds is None or self.sh.loops[Loop.ALTITUDE].u < (
                cfg.liftoff_thrust_share * guess if guess else 0.1):
            return False  # no thrust to leave the ground with: vibration, not lift-off
        r0, p0, br, bp, wp, wq = self.thresholds
        return (abs(s.roll_rad - r0) > br or abs(s.pitch_rad - p0) > bp
                or abs(s.p_rad_s) > wp or abs(s.q_rad_s) > wq)

    def turn_rate(self, loop: Loop) -> float:
        """Rate (rad/s) the axis must pass the other way for a turn: the lift-off threshold."""
        if self.thresholds is None:
            return self.sh.config.liftoff_rate_floor_rad_s
        return self.thresholds[4 if loop is Loop.ROLL else 5]


def swing_stop(e: float, rate: float, decel: float) -> float:
    """How far from its set point (``|e|``, as ``e``) a swing moving out at ``rate`` (the
    error's rate) stops under a constant deceleration ``decel`` (> 0, same units per s):
    ``|e| + rate^2 / (2 decel)``; inf where it is not braked.

    Examples
    --------
    >>> swing_stop(0.1, 2.0, 20.0)
    0.2
    >>> swing_stop(0.1, 2.0, 0.0)
    inf
    """
    if not decel > 0:
        return math.inf
    return abs(e) + rate * rate / (2.0 * decel)


@dataclass
class _HalfSwing:
    """What the brake knows of one relay half-swing (from a switch to the next)."""

    switches: int = -1
    t_switch_s: float = math.nan
    rate_ext: float = 0.0  # largest outward rate since the switch (rad/s)
    t_ext_s: float = math.nan
    braked: bool = False
    done: bool = False
    lead_s: float = 0.0
    recent: list = field(default_factory=list)  # (t, outward rate) over the last window


class FirstSwingBrake:
    """Roll/pitch before the relay is sized: a swing the relay's push-back will not stop
    inside ``att_brake_amp_rad`` is braked harder until the axis turns.

    The half-swing's own shape tells where it stops before it gets there: once the push
    that brakes it acts (the outward rate past its peak), the rate's slope over the last
    ``att_brake_window_s`` is the deceleration, and ``|e| + rate^2 / 2 a`` the stop
    (:func:`swing_stop`). Nothing about the vehicle is assumed: its gain, delay, motor lag
    and a centre-of-mass torque (which weakens every other push-back) all show in that
    slope. Where the stop lies past the limit, the push is raised (up to ``h_goal``) by the
    share of deceleration the rest of the way needs, counting the time a raise takes to act
    (the switch-to-peak time just seen), and set back to the relay's h a delay before the
    axis is predicted to turn: the relay's own h is left to the sizing on the first period
    (a smaller h taken here lost to a centre-of-mass torque, and the swing that followed
    ran away). Each half-swing is braked once.
    """

    def __init__(self, shared: Shared) -> None:
        self.sh = shared
        self.swings: dict[Loop, _HalfSwing] = {}

    def step(self, t: LoopTest, t_s: float, e: float, e_rate: float) -> bool:
        """On a new attitude sample of ``t`` (error ``e``, rad, and its rate, rad/s): True
        where the relay's h changed now (the tick's output changes)."""
        cfg, r = self.sh.config, t.relay
        lim = cfg.att_brake_amp_rad
        if not lim or r is None:
            return False
        hs = self.swings.setdefault(t.loop, _HalfSwing())
        n = int(r.switches[0])
        out = e_rate * math.copysign(1.0, e) if e else 0.0  # rate away from the set point
        if hs.braked:
            decel = self._decel(hs, t_s, out, cfg.att_brake_window_s)
            # released once the raised push, still acting for a lead, would stop the rest of
            # the swing at half the deceleration seen now (which still grows through the
            # motors' lag): held longer it throws the axis back as hard
            if (n != hs.switches or t.sized or t.catch is not None or out <= 0
                    or out <= 2.0 * decel * hs.lead_s):
                hs.braked, hs.done = False, True
                changed = float(r.h[0]) != t.h
                r.h[:] = t.h
                return changed
            return False
        if t.sized or t.catch is not None:
            return False
        if n != hs.switches:  # a new half-swing: the push now acting is the new one
            self.swings[t.loop] = hs = _HalfSwing(switches=n, t_switch_s=t_s)
        st = float(r.state[0])
        if n == 0 or hs.braked or hs.done or not (st * e > 0 and out > 0):
            hs.recent.clear()
            return False
        if out > hs.rate_ext:
            hs.rate_ext, hs.t_ext_s = out, t_s
        decel = self._decel(hs, t_s, out, cfg.att_brake_window_s)
        band = t.band if math.isfinite(t.band) else 0.0
        # past its peak rate (the push-back acts), and out a quarter of the limit already: a
        # slope taken just past a small swing's peak (a hop off the ground) says little
        if out > 0.9 * hs.rate_ext or abs(e) < max(2 * band, 0.25 * lim):
            return False
        if not decel > 0:
            return False  # not yet braking: no stop to predict
        stop = swing_stop(e, out, decel)
        if not stop > lim:
            return False
        h = float(r.h[0])
        # a raise acts only a lead later (the switch-to-peak time just seen): where the swing
        # is then, and how fast, at the deceleration it has now
        lead = max(hs.t_ext_s - hs.t_switch_s, 0.0)
        w_lead = out - decel * lead
        if not w_lead > 0:
            return False  # it turns before a raise could act
        room = lim - abs(e) - out * lead + 0.5 * decel * lead * lead
        need = w_lead * w_lead / (2.0 * room) if room > 0 else math.inf
        h_b = min(max(t.h_goal, h), h * need / decel)
        if not h_b > h:
            return False
        hs.braked, hs.lead_s = True, lead
        r.h[:] = h_b
        self.sh.events.append(
            f"{t.loop.value}: a first swing heads for {stop:.3g} rad at h {h:.3g} "
            f"(limit {lim:.3g} rad): braked at h {h_b:.3g} until it turns")
        return True

    @staticmethod
    def _decel(hs: _HalfSwing, t_s: float, out: float, window_s: float) -> float:
        """Deceleration of the outward rate (rad/s^2): its slope over the last ``window_s``
        (nan with under 3 samples or half the window)."""
        hs.recent.append((t_s, out))
        while hs.recent and hs.recent[0][0] < t_s - window_s:
            hs.recent.pop(0)
        if len(hs.recent) < 3 or hs.recent[-1][0] - hs.recent[0][0] < 0.5 * window_s:
            return math.nan
        tt, ww = np.array(hs.recent).T
        tc = tt - tt.mean()
        return -float(tc @ (ww - ww.mean()) / (tc @ tc))
