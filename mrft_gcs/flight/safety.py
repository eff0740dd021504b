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
"""

from __future__ import annotations

import math

from mrft_gcs.errors import IdentificationError, SafetyAbort
from mrft_gcs.flight.controllers import FlightState
from mrft_gcs.profiles import SafetyLimits

__all__ = ["LimitExceeded", "RelayTooLarge", "SafetyMonitor", "RELAY_GUARD_FRACTION"]

#: share of the tilt limit at which a relay test is stopped (the limit itself aborts): room
#: for the swing that follows the stop, yet above the largest relay swings of completed
#: tunes (about 31 deg of the 35 deg limit)
RELAY_GUARD_FRACTION = 0.9


class LimitExceeded(SafetyAbort):
    """A safety limit was crossed during the test."""


class RelayTooLarge(IdentificationError):
    """A relay test swung towards the tilt limit and was stopped before it."""


class SafetyMonitor:
    """Check a :class:`FlightState` against :class:`~mrft_gcs.profiles.SafetyLimits`.

    Parameters
    ----------
    limits : SafetyLimits
    origin : (x_m, y_m, z_up_m)
        Take-off point.
    t_start_s : float
        Vehicle time of the take-off command (the duration limit counts from it).

    Examples
    --------
    >>> m = SafetyMonitor(SafetyLimits(max_tilt_deg=30), (0.0, 0.0, 0.0), 0.0)
    >>> s = FlightState(1, 0.7, 0, 0, 0, 0, 0, 1, 0, 0, 1, 0, 0, 0)
    >>> m.violation(s)
    'tilt 40.1 deg over the 30 deg limit'
    """

    def __init__(self, limits: SafetyLimits, origin: tuple[float, float, float],
                 t_start_s: float) -> None:
        self.limits = limits
        self.origin = origin
        self.t_start_s = t_start_s
        self.max_tilt_seen_deg = 0.0

    def reset(self, origin: tuple[float, float, float], t_start_s: float) -> None:
        self.origin, self.t_start_s, self.max_tilt_seen_deg = origin, t_start_s, 0.0

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

    def relay_guard(self, s: FlightState, what: str) -> None:
        """Raise :class:`RelayTooLarge` where ``s`` tilts past :data:`RELAY_GUARD_FRACTION`
        of the tilt limit (``what``: the tests running, for the message)."""
        tilt = math.degrees(s.tilt_rad)
        lim = self.limits.max_tilt_deg
        if tilt > RELAY_GUARD_FRACTION * lim:
            raise RelayTooLarge(
                f"{what}: tilt {tilt:.1f} deg, past {RELAY_GUARD_FRACTION:.0%} of the {lim:g} "
                f"deg limit: test stopped before the limit, landing commanded; check for a busy "
                f"computer or a lossy link (see the notes), and that the airframe is sound "
                f"(--max-tilt raises the limit where it can take more)")
