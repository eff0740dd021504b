"""GCS-side loops used during and after the tests: the PD, a conservative yaw hold, the state.

Once a loop is identified its relay is replaced at once by the deployed PD
``u = trim + Kc e - Kd dy/dt`` (derivative on the measurement, docs/method.md). ``trim``
is the mean relay output over the identified cycles: over a steady cycle of an
integrating plant the mean rate is zero, so the mean input is what balances the
constant load (hover thrust for altitude, the torque bias for roll and pitch).

Yaw is not tuned (the paper assumes it is easy); it is held by a deliberately
soft PD, the same on every vehicle, which the report states.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["FlightState", "PDLoop", "YawHold", "wrap_pi", "catch_pd"]


@dataclass(frozen=True, slots=True)
class FlightState:
    """The latest telemetry, in the loops' own axes.

    Times are the vehicle's boot clock (s): ``t_att_s`` of the last ATTITUDE,
    ``t_pos_s`` of the last LOCAL_POSITION_NED. Angles in rad, rates in rad/s
    (body), ``x_m`` north, ``y_m`` east, ``z_up_m`` up (m); velocities in m/s
    along the same axes.
    """

    t_att_s: float
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    p_rad_s: float
    q_rad_s: float
    r_rad_s: float
    t_pos_s: float
    x_m: float
    y_m: float
    z_up_m: float
    vx_m_s: float
    vy_m_s: float
    vz_up_m_s: float

    @property
    def tilt_rad(self) -> float:
        """Angle between body z and vertical."""
        c = math.cos(self.roll_rad) * math.cos(self.pitch_rad)
        return math.acos(max(-1.0, min(1.0, c)))


def catch_pd(h: float, period_s: float, amplitude: float) -> tuple[float, float]:
    """A damping PD ``(Kc, Kd)`` that brings a relay loop back to its set point.

    From the relay's own steady cycle (amplitude ``h``, period, amplitude of the
    measured variable): by the describing function the plant's gain at the cycle
    frequency ``w0`` is ``pi a / (4 h)``; the derivative term is sized for half of
    unit loop gain there (``Kd = 0.5 * 4h / (pi a w0)``) and the proportional term
    puts the PD's corner at a quarter of the period (``Kc = 4 Kd / T``), so the loop
    crosses over well below the cycle frequency with the PD's lead. About half the
    optimal gains on the bundled airframes: meant to damp, not to perform.

    >>> kc, kd = catch_pd(0.12, 0.22, 0.05)
    >>> round(kc, 2), round(kd, 3)
    (0.97, 0.053)
    """
    w0 = 2 * math.pi / period_s
    kd = 0.5 * 4 * h / (math.pi * amplitude * w0)
    return 4 * kd / period_s, kd


def wrap_pi(a: float) -> float:
    """Angle wrapped to [-pi, pi)."""
    return (a + math.pi) % (2 * math.pi) - math.pi


class PDLoop:
    """``u = clip(trim + Kc (ref - y) - Kd dy/dt, lo, hi)``.

    Parameters
    ----------
    Kc, Kd : float
        Gains in SI units of the loop.
    trim : float
        Constant output (hover thrust, torque bias), loop input units.
    lo, hi : float
        Output limits.

    Examples
    --------
    >>> PDLoop(2.0, 0.5).step(ref=1.0, y=0.5, dy=0.2)
    0.9
    """

    def __init__(self, Kc: float, Kd: float, trim: float = 0.0, lo: float = -math.inf,
                 hi: float = math.inf) -> None:
        self.Kc, self.Kd, self.trim, self.lo, self.hi = Kc, Kd, trim, lo, hi

    def reset(self) -> None:  # stateless: kept for the controller protocol
        pass

    def step(self, ref: float, y: float, dy: float) -> float:
        u = self.trim + self.Kc * (ref - y) - self.Kd * dy
        return min(self.hi, max(self.lo, u))


class YawHold(PDLoop):
    """Conservative yaw hold on normalised yaw torque: soft enough for any bundled airframe.

    ``Kc = 0.2`` per rad and ``Kd = 0.08`` per rad/s, output within +-0.3.
    """

    def __init__(self, Kc: float = 0.2, Kd: float = 0.08, limit: float = 0.3) -> None:
        super().__init__(Kc, Kd, 0.0, -limit, limit)

    def step(self, ref: float, y: float, dy: float, t_s: float = math.nan) -> float:
        # ``t_s`` (the sample's time) is for yaw controllers that record, e.g. a yaw relay
        return super().step(0.0, -wrap_pi(ref - y), dy)
