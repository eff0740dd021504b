"""Safety limits (README, safety): tilt, altitude, distance from take-off, test duration.

:class:`SafetyMonitor` is checked on every setpoint tick. A limit crossed raises
:class:`LimitExceeded` (a :class:`~mrft_gcs.errors.SafetyAbort`, exit code 5) from
the setpoint callback, which stops the stream and commands a landing
(:class:`~mrft_gcs.link.SetpointStreamer` does both). Telemetry loss is the
streamer's watchdog; Ctrl-C is handled by the tuning API. Limits come from the
autopilot profile and are overridden from the command line.

While a relay test runs, :meth:`SafetyMonitor.relay_guard` stops it a little before the tilt
limit (:data:`RELAY_GUARD_FRACTION` of it) with :class:`RelayTooLarge`, an explained refusal
rather than an abort over the limit; the vehicle lands as on any stop.
:meth:`SafetyMonitor.drift_guard` does the same for the distance from the take-off point
(:class:`DriftTooLarge`): a relay test that the side hold cannot keep near the take-off point
(a roll or pitch trim the relays do not cancel, wind) is stopped well before the distance limit.
"""

from __future__ import annotations

import math

from mrft_gcs.errors import IdentificationError, SafetyAbort
from mrft_gcs.flight.controllers import FlightState
from mrft_gcs.profiles import SafetyLimits

__all__ = ["DriftTooLarge", "LimitExceeded", "RelayTooLarge", "SafetyMonitor",
           "DRIFT_GUARD_FRACTION", "DRIFT_GUARD_LEAD_S", "RELAY_GUARD_FRACTION",
           "RELAY_GUARD_LEAD_S", "predicted_tilt_rad"]

#: share of the tilt limit at which a relay test is stopped (the limit itself aborts): room
#: for the swing that follows the stop, yet above the largest relay swings of completed
#: tunes (about 31 deg of the 35 deg limit)
RELAY_GUARD_FRACTION = 0.9

#: how far ahead (s) the relay guard looks where the link's round trip is not known: the
#: measured tilt is a telemetry trip old and a stop acts a command trip later, so the guard
#: acts on the tilt extrapolated over the round trip (a loopback or Wi-Fi link: a few ms to
#: 20 ms; a telemetry period more)
RELAY_GUARD_LEAD_S = 0.02


#: share of the distance limit at which a relay test is stopped: the vehicle still moving
#: outwards needs room to brake and land (with the lead below, a drift at 0.6 m/s stops
#: near 3.7 m of 5); lower, it stopped vehicles that wander 3-4 m and come back
DRIFT_GUARD_FRACTION = 0.8

#: how far ahead (s) the drift guard carries the outward speed on
DRIFT_GUARD_LEAD_S = 0.5


def predicted_tilt_rad(s: FlightState, lead_s: float,
                       accel_rad_s2: tuple[float, float] = (0.0, 0.0)) -> float:
    """Tilt (rad) ``lead_s`` seconds after ``s``: roll and pitch carried on at their rates
    and angular accelerations (``accel_rad_s2``: roll, pitch).

    Body rates stand in for the angles' rates (within a few per cent below 20 deg of tilt
    and a slow yaw). Never less than the measured tilt.

    Examples
    --------
    >>> s = FlightState(1, 0.5, 0, 0, 2.0, 0, 0, 1, 0, 0, 1, 0, 0, 0)
    >>> round(math.degrees(predicted_tilt_rad(s, 0.05)), 1)
    34.4
    >>> round(math.degrees(predicted_tilt_rad(s, 0.05, (-40.0, 0.0))), 1)  # braking
    31.5
    """
    r = s.roll_rad + s.p_rad_s * lead_s + 0.5 * accel_rad_s2[0] * lead_s ** 2
    p = s.pitch_rad + s.q_rad_s * lead_s + 0.5 * accel_rad_s2[1] * lead_s ** 2
    c = math.cos(r) * math.cos(p)
    return max(s.tilt_rad, math.acos(max(-1.0, min(1.0, c))))


class LimitExceeded(SafetyAbort):
    """A safety limit was crossed during the test."""


class RelayTooLarge(IdentificationError):
    """A relay test swung towards the tilt limit and was stopped before it."""


class DriftTooLarge(IdentificationError):
    """A relay test drifted away from the take-off point and was stopped before the limit."""


class SafetyMonitor:
    """Check a :class:`FlightState` against :class:`~mrft_gcs.profiles.SafetyLimits`.

    Parameters
    ----------
    limits : SafetyLimits
    origin : (x_m, y_m, z_up_m)
        Take-off point.
    t_start_s : float
        Vehicle time of the take-off command (the duration limit counts from it).
    lead_s : float
        The relay guard acts on the tilt this far ahead (s): the link's round trip and a
        telemetry period (:data:`RELAY_GUARD_LEAD_S` where it is not known).

    Examples
    --------
    >>> m = SafetyMonitor(SafetyLimits(max_tilt_deg=30), (0.0, 0.0, 0.0), 0.0)
    >>> s = FlightState(1, 0.7, 0, 0, 0, 0, 0, 1, 0, 0, 1, 0, 0, 0)
    >>> m.violation(s)
    'tilt 40.1 deg over the 30 deg limit'
    """

    def __init__(self, limits: SafetyLimits, origin: tuple[float, float, float],
                 t_start_s: float, lead_s: float = RELAY_GUARD_LEAD_S) -> None:
        self.limits = limits
        self.lead_s = lead_s
        #: (t_att_s, p, q) of the last attitude sample the relay guard saw, and the angular
        #: accelerations (roll, pitch; rad/s^2) from it to the one before
        self._last: tuple[float, float, float] | None = None
        self._accel = (0.0, 0.0)
        self.origin = origin
        self.t_start_s = t_start_s
        self.max_tilt_seen_deg = 0.0

    def reset(self, origin: tuple[float, float, float], t_start_s: float) -> None:
        self.origin, self.t_start_s, self.max_tilt_seen_deg = origin, t_start_s, 0.0
        self._last, self._accel = None, (0.0, 0.0)

    def violation(self, s: FlightState, duration: bool = True) -> str | None:
        """A one-line reason if ``s`` is beyond a limit, else None (``duration``: check it too)."""
        lim = self.limits
        tilt = math.degrees(s.tilt_rad)
        self.max_tilt_seen_deg = max(self.max_tilt_seen_deg, tilt)
        if tilt > lim.max_tilt_deg:
            return f"tilt {tilt:.1f} deg over the {lim.max_tilt_deg:g} deg limit"
        alt = s.z_up_m - self.origin[2]
        if alt > lim.max_altitude_m:
            return f"altitude {alt:.2f} m over the {lim.max_altitude_m:g} m limit"
        dist = math.hypot(s.x_m - self.origin[0], s.y_m - self.origin[1])
        if dist > lim.max_distance_m:
            return f"{dist:.2f} m from take-off, over the {lim.max_distance_m:g} m limit"
        elapsed = max(s.t_att_s, s.t_pos_s) - self.t_start_s
        if duration and elapsed > lim.max_test_duration_s:
            return (f"test running for {elapsed:.1f} s, over the "
                    f"{lim.max_test_duration_s:g} s limit")
        return None

    def check(self, s: FlightState) -> None:
        """Raise :class:`LimitExceeded` if ``s`` is beyond a limit."""
        reason = self.violation(s)
        if reason is not None:
            raise LimitExceeded(f"safety limit: {reason}: test aborted, landing commanded")

    def drift_guard(self, s: FlightState, what: str) -> None:
        """Raise :class:`DriftTooLarge` where ``s``, its horizontal velocity carried on for
        :data:`DRIFT_GUARD_LEAD_S`, lies past :data:`DRIFT_GUARD_FRACTION` of the distance
        limit from the take-off point (``what``: the tests running, for the message).

        The distance limit aborts; this stops the test earlier, with the reason."""
        dx, dy = s.x_m - self.origin[0], s.y_m - self.origin[1]
        dist = math.hypot(dx, dy)
        lim = self.limits.max_distance_m
        if dist <= 0.0:
            return
        out = (dx * s.vx_m_s + dy * s.vy_m_s) / dist  # outward speed (m/s)
        ahead = dist + max(0.0, out) * DRIFT_GUARD_LEAD_S
        if ahead > DRIFT_GUARD_FRACTION * lim:
            raise DriftTooLarge(
                f"{what}: drifted {dist:.2f} m from the take-off point ({dx:+.2f} m x, "
                f"{dy:+.2f} m y, moving out at {max(0.0, out):.2f} m/s), past "
                f"{DRIFT_GUARD_FRACTION:.0%} of the {lim:g} m limit: the side hold could not "
                f"keep it near while the relays ran (a roll or pitch trim, a centre of mass "
                f"off the middle, or wind); test stopped before the limit, landing commanded; "
                f"balance the vehicle or fly in calm air (--max-distance raises the limit where "
                f"there is room)")

    def relay_guard(self, s: FlightState, what: str) -> None:
        """Raise :class:`RelayTooLarge` where ``s`` tilts, or is about to tilt (its rates
        carried on for ``lead_s``), past :data:`RELAY_GUARD_FRACTION` of the tilt limit
        (``what``: the tests running, for the message).

        The measured tilt trails the vehicle's by the telemetry's trip down, and a stop
        acts only after the command's trip up: a guard on the measured tilt alone stopped
        a swing that went on past the limit."""
        last = self._last
        if last is None or s.t_att_s > last[0]:
            if last is not None and s.t_att_s - last[0] < 0.1:  # a braking swing peaks sooner
                dt = s.t_att_s - last[0]
                self._accel = ((s.p_rad_s - last[1]) / dt, (s.q_rad_s - last[2]) / dt)
            self._last = (s.t_att_s, s.p_rad_s, s.q_rad_s)
        tilt = math.degrees(s.tilt_rad)
        ahead = math.degrees(predicted_tilt_rad(s, self.lead_s, self._accel))
        lim = self.limits.max_tilt_deg
        if ahead > RELAY_GUARD_FRACTION * lim:
            heading = f" heading for {ahead:.1f} deg" if ahead > tilt + 0.05 else ""
            raise RelayTooLarge(
                f"{what}: tilt {tilt:.1f} deg{heading}, past {RELAY_GUARD_FRACTION:.0%} of the "
                f"{lim:g} deg limit: test stopped before the limit, landing commanded; check "
                f"for a busy computer or a lossy link (see the notes), and that the airframe is "
                f"sound (--max-tilt raises the limit where it can take more)")
