"""Lift-off as the attitude sees it: when the roll and pitch relays may start.

The climb is flown by the take-off controller (:mod:`mrft_gcs.flight.takeoff`); the attitude
relays start once the vehicle leaves the ground: above ``airborne_m``, the altitude relay
running, or (with enough thrust to leave the ground) roll, pitch or their rates off their
ground values by more than the noise measured on the ground. The delayed altitude alone
would give a CoM offset time to tilt the vehicle first.
"""

from __future__ import annotations

import numpy as np

from mrft_gcs.flight.controllers import FlightState
from mrft_gcs.flight.phases.shared import Shared
from mrft_gcs.loops import Loop

__all__ = ["LiftoffDetector"]


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
