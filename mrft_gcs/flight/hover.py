"""Is the vehicle airborne and steady on the written gains? (README's report schema ``status``.)

After the gains are written the ground station hands the vehicle to the autopilot's
position mode and watches a short window. A tune's status is ``ok`` only when, over that
whole window, the vehicle stayed above the take-off point by a margin with a small climb
rate (airborne, not sitting or bouncing on the ground), and stayed near the point where
position mode took over, with small tilt (steady). One number alone does not tell: a
vehicle that hit the ground during the hand-over holds "still" too.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from mrft_gcs.flight.controllers import FlightState

__all__ = ["HoverLimits", "HoverCheck", "check_hover", "check_hover_states"]


@dataclass(frozen=True)
class HoverLimits:
    """Bounds of an airborne, steady hover.

    The defaults leave room for a position-mode hover on fresh gains (the bundled SITL
    holds within a few cm and a few degrees) and fail a vehicle on the ground or one
    swinging about.
    """

    min_height_m: float = 0.3  # above the take-off point, every sample
    max_climb_m_s: float = 0.5  # |vertical speed|, every sample
    max_error_m: float = 0.5  # from where position mode took over
    max_tilt_deg: float = 15.0
    min_samples: int = 5


@dataclass(frozen=True)
class HoverCheck:
    """What the check window showed; ``reason`` says why it failed ('' when passed)."""

    airborne: bool
    steady: bool
    samples: int
    duration_s: float
    min_height_m: float  # lowest height above the take-off point (m)
    max_climb_m_s: float  # largest |vertical speed| (m/s)
    max_error_m: float  # largest distance from the first sample (m)
    max_tilt_deg: float
    reason: str

    @property
    def passed(self) -> bool:
        return self.airborne and self.steady

    def as_dict(self) -> dict[str, object]:
        return {"passed": self.passed, "airborne": self.airborne, "steady": self.steady,
                "samples": self.samples, "duration_s": self.duration_s,
                "min_height_m": self.min_height_m, "max_climb_m_s": self.max_climb_m_s,
                "max_error_m": self.max_error_m, "max_tilt_deg": self.max_tilt_deg,
                "reason": self.reason or None}


def check_hover(t_s: np.ndarray, xyz_up_m: np.ndarray, vz_up_m_s: np.ndarray,
                roll_rad: np.ndarray, pitch_rad: np.ndarray, ground_z_up_m: float,
                limits: HoverLimits = HoverLimits()) -> HoverCheck:
    """Judge a hover window.

    Parameters
    ----------
    t_s : (n,) array
        Sample times (s).
    xyz_up_m : (n, 3) array
        Position, z up (m); the first row is where position mode took over.
    vz_up_m_s : (n,) array
        Vertical speed, up positive (m/s).
    roll_rad, pitch_rad : (n,) arrays
        Attitude (rad).
    ground_z_up_m : float
        Height of the take-off point on the same axis (m).

    Examples
    --------
    >>> n = 50
    >>> on_ground = check_hover(np.arange(n) * 0.02, np.zeros((n, 3)), np.zeros(n),
    ...                         np.zeros(n), np.zeros(n), 0.0)
    >>> on_ground.passed, on_ground.reason.split(":")[0]
    (False, 'not airborne')
    """
    t = np.asarray(t_s, float)
    p = np.asarray(xyz_up_m, float).reshape(-1, 3)
    n = len(t)
    if n < limits.min_samples:
        return HoverCheck(False, False, n, 0.0, math.nan, math.nan, math.nan, math.nan,
                          f"only {n} samples in the hover window (needs {limits.min_samples}): "
                          f"telemetry too sparse to tell whether it hovers")
    height = p[:, 2] - ground_z_up_m
    climb = np.abs(np.asarray(vz_up_m_s, float))
    error = np.linalg.norm(p - p[0], axis=1)
    tilt = np.degrees(np.arccos(np.clip(np.cos(roll_rad) * np.cos(pitch_rad), -1.0, 1.0)))
    low, fast = float(height.min()), float(climb.max())
    err, tmax = float(error.max()), float(tilt.max())
    problems = []
    airborne = low >= limits.min_height_m and fast <= limits.max_climb_m_s
    if low < limits.min_height_m:
        problems.append(f"not airborne: {low:.2f} m above the take-off point "
                        f"(needs >= {limits.min_height_m:g} m)")
    if fast > limits.max_climb_m_s:
        problems.append(f"not holding its height: vertical speed reached "
                        f"{fast:.2f} m/s (needs <= {limits.max_climb_m_s:g} m/s)")
    steady = err <= limits.max_error_m and tmax <= limits.max_tilt_deg
    if err > limits.max_error_m:
        problems.append(f"not steady: {err:.2f} m from where position mode took over "
                        f"(needs <= {limits.max_error_m:g} m)")
    if tmax > limits.max_tilt_deg:
        problems.append(f"not steady: tilt reached {tmax:.1f} deg "
                        f"(needs <= {limits.max_tilt_deg:g} deg)")
    return HoverCheck(airborne, steady, n, float(t[-1] - t[0]), low, fast, err, tmax,
                      "; ".join(problems))


def check_hover_states(states: Sequence[FlightState], ground_z_up_m: float,
                       limits: HoverLimits = HoverLimits()) -> HoverCheck:
    """:func:`check_hover` on the flight states polled during the window."""
    n = len(states)
    return check_hover(
        np.array([s.t_att_s for s in states], float),
        np.array([(s.x_m, s.y_m, s.z_up_m) for s in states], float).reshape(n, 3),
        np.array([s.vz_up_m_s for s in states], float),
        np.array([s.roll_rad for s in states], float),
        np.array([s.pitch_rad for s in states], float), ground_z_up_m, limits)
