"""The simulated vehicle's onboard flight software: PX4-style modes, parameters and cascades.

The structures are exactly those the tuner's gains are written for (docs/writing-gains.md), so a PD
``u = Kc e - Kd w`` written as ``MC_ROLL_P = Kc/Kd``, ``MC_ROLLRATE_P = Kd``
(``I = D = 0``, ``K = 1``) flies as that PD:

Attitude (roll shown; pitch and yaw alike)::

    rate_sp    = MC_ROLL_P * angle_error                       (rad/s; |rate_sp| <= 220 deg/s)
    torque_cmd = MC_ROLLRATE_K * (MC_ROLLRATE_P * (rate_sp - rate) + I_int
                                  - MC_ROLLRATE_D * d(rate)/dt) + MC_ROLLRATE_FF * rate_sp
                                    (normalised, clipped to [-1, 1])
    I_int     += MC_ROLLRATE_I * (rate_sp - rate) dt            (|I_int| <= MC_RR_INT_LIM)

The angle error is the body-frame rotation vector of ``q_meas^-1 q_sp`` (equal to the Euler
angle differences for small angles); ``d(rate)/dt`` is low-passed at ``IMU_DGYRO_CUTOFF``.

The structure's own filters and rates are parameters under the firmware's names
(:func:`structure_specs`), as a ground station reads them from real firmware: PX4-like
vehicles ``IMU_DGYRO_CUTOFF`` (Hz), ``IMU_GYRO_RATEMAX`` (the rate loop's rate, Hz) and
``IMU_INTEG_RATE`` (Hz) with ``EKF2_PREDICT_US`` (us), which set the position loop's rate as
on PX4 (docs/onboard-rates.md); ArduPilot-like ones ``ATC_RAT_RLL_FLTT`` / ``ATC_RAT_PIT_FLTT``
(rate target low-pass, Hz), ``ATC_RAT_RLL_FLTD`` / ``ATC_RAT_PIT_FLTD`` (D low-pass, Hz) and
``SCHED_LOOP_RATE`` (Hz: the rate loop's and, as on ArduCopter, the position loop's).
A filter written takes effect at once; a loop rate, as on the firmware, only after a reboot
(never, in the simulator).

Position (north/east; altitude alike with the MPC_Z_* names, up positive)::

    vel_sp = MPC_XY_P * pos_error                               (|vel_sp| <= MPC_XY_VEL_MAX)
    acc_sp = MPC_XY_VEL_P_ACC * (vel_sp - vel) + I_int - MPC_XY_VEL_D_ACC * d(vel)/dt
    tilt   = acc_sp / g, rotated by yaw: roll_sp = acc_right / g, pitch_sp = -acc_forward / g
                                                                (|tilt| <= MPC_TILTMAX_AIR)
    thrust = MPC_THR_HOVER * (1 + acc_up_sp / g)                (clipped to [0, 1])

Modes (PX4 custom_mode: main mode in bits 16-23, sub mode in bits 24-31): MANUAL, STABILIZED
and ACRO are accepted only on the ground (there is no RC); ALTCTL holds altitude with a level
attitude; POSCTL holds the position and altitude where it was entered; OFFBOARD follows
SET_ACTUATOR_CONTROL_TARGET (torque path, straight to the mixer) or SET_ATTITUDE_TARGET
(through the attitude cascade above); AUTO.LOITER (MAVSDK's "hold") behaves as POSCTL;
AUTO.LAND holds x/y and descends at MPC_LAND_SPEED, then
disarms 2 s after touchdown. Offboard loss (no valid setpoint for COM_OF_LOSS_T, default 0.5 s)
switches to AUTO.LAND with a STATUSTEXT.

Default gains are PX4 v1.13's shipped defaults, as on a fresh build: generic, untuned for this
airframe but flyable on the bundled profiles (POSCTL and LAND work out of the box).
``MPC_THR_HOVER`` starts at the airframe's true hover throttle (rounded to 0.01), as if PX4's
hover-thrust estimator had converged; ``COM_OF_LOSS_T`` defaults to 0.5 s (PX4: 1 s).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

from mrft_gcs.sitl.airframe import GRAVITY_M_S2, OnboardSpec
from mrft_gcs.telemetry import quat_from_euler

__all__ = [
    "FlightMode",
    "CommandResult",
    "ParamSpec",
    "PARAM_SPECS",
    "ParamStore",
    "Autopilot",
    "StatusEvent",
    "sqrt_controller",
    "structure_specs",
]


class FlightMode(enum.Enum):
    """PX4 flight modes as ``(main_mode, sub_mode)``."""

    MANUAL = (1, 0)
    ALTCTL = (2, 0)
    POSCTL = (3, 0)
    AUTO_LOITER = (4, 3)
    AUTO_LAND = (4, 6)
    ACRO = (5, 0)
    OFFBOARD = (6, 0)
    STABILIZED = (7, 0)

    @property
    def custom_mode(self) -> int:
        """The HEARTBEAT ``custom_mode`` word (main in bits 16-23, sub in bits 24-31)."""
        main, sub = self.value
        return (main << 16) | (sub << 24)

    @classmethod
    def from_px4(cls, main: int, sub: int = 0) -> FlightMode | None:
        """The mode for a DO_SET_MODE request, or None if not supported."""
        for mode in cls:
            m, s = mode.value
            if m == main and s == sub:
                return mode
        return None


class CommandResult(enum.IntEnum):
    """Outcome of a command, numerically equal to MAV_RESULT."""

    ACCEPTED = 0
    TEMPORARILY_REJECTED = 1
    DENIED = 2
    UNSUPPORTED = 3
    FAILED = 4


@dataclass(frozen=True)
class StatusEvent:
    """A message for the ground station (becomes STATUSTEXT). Severity as MAV_SEVERITY."""

    severity: int
    text: str


@dataclass(frozen=True)
class ParamSpec:
    """A float parameter: default, allowed range, unit."""

    default: float
    low: float
    high: float
    unit: str = ""


_DEG = math.pi / 180.0

#: Parameters served over MAVLink (all MAV_PARAM_TYPE_REAL32), PX4 v1.13 defaults.
PARAM_SPECS: dict[str, ParamSpec] = {
    "MC_ROLL_P": ParamSpec(6.5, 0.0, 50.0, "1/s"),
    "MC_PITCH_P": ParamSpec(6.5, 0.0, 50.0, "1/s"),
    "MC_YAW_P": ParamSpec(2.8, 0.0, 50.0, "1/s"),
    "MC_ROLLRATE_P": ParamSpec(0.15, 0.0, 5.0, "1/(rad/s)"),
    "MC_ROLLRATE_I": ParamSpec(0.2, 0.0, 10.0, "1/rad"),
    "MC_ROLLRATE_D": ParamSpec(0.003, 0.0, 1.0, "s/rad"),
    "MC_ROLLRATE_K": ParamSpec(1.0, 0.0, 5.0, ""),
    "MC_ROLLRATE_FF": ParamSpec(0.0, 0.0, 5.0, ""),
    "MC_PITCHRATE_P": ParamSpec(0.15, 0.0, 5.0, "1/(rad/s)"),
    "MC_PITCHRATE_I": ParamSpec(0.2, 0.0, 10.0, "1/rad"),
    "MC_PITCHRATE_D": ParamSpec(0.003, 0.0, 1.0, "s/rad"),
    "MC_PITCHRATE_K": ParamSpec(1.0, 0.0, 5.0, ""),
    "MC_PITCHRATE_FF": ParamSpec(0.0, 0.0, 5.0, ""),
    "MC_YAWRATE_P": ParamSpec(0.2, 0.0, 5.0, "1/(rad/s)"),
    "MC_YAWRATE_I": ParamSpec(0.1, 0.0, 10.0, "1/rad"),
    "MC_YAWRATE_D": ParamSpec(0.0, 0.0, 1.0, "s/rad"),
    "MC_YAWRATE_K": ParamSpec(1.0, 0.0, 5.0, ""),
    "MC_YAWRATE_FF": ParamSpec(0.0, 0.0, 5.0, ""),
    "MC_RR_INT_LIM": ParamSpec(0.3, 0.0, 1.0, ""),
    "MC_ROLLRATE_MAX": ParamSpec(220.0, 0.0, 1800.0, "deg/s"),
    "MC_PITCHRATE_MAX": ParamSpec(220.0, 0.0, 1800.0, "deg/s"),
    "MC_YAWRATE_MAX": ParamSpec(200.0, 0.0, 1800.0, "deg/s"),
    "MPC_XY_P": ParamSpec(0.95, 0.0, 10.0, "1/s"),
    "MPC_XY_VEL_P_ACC": ParamSpec(1.8, 0.0, 30.0, "1/s"),
    "MPC_XY_VEL_I_ACC": ParamSpec(0.4, 0.0, 60.0, "1/s^2"),
    "MPC_XY_VEL_D_ACC": ParamSpec(0.2, 0.0, 10.0, ""),
    "MPC_XY_VEL_MAX": ParamSpec(12.0, 0.0, 20.0, "m/s"),
    "MPC_Z_P": ParamSpec(1.0, 0.0, 10.0, "1/s"),
    "MPC_Z_VEL_P_ACC": ParamSpec(4.0, 0.0, 60.0, "1/s"),
    "MPC_Z_VEL_I_ACC": ParamSpec(2.0, 0.0, 60.0, "1/s^2"),
    "MPC_Z_VEL_D_ACC": ParamSpec(0.0, 0.0, 10.0, ""),
    "MPC_Z_VEL_MAX_UP": ParamSpec(3.0, 0.5, 8.0, "m/s"),
    "MPC_Z_VEL_MAX_DN": ParamSpec(1.0, 0.5, 4.0, "m/s"),
    "MPC_THR_HOVER": ParamSpec(0.5, 0.1, 0.8, ""),
    "MPC_TILTMAX_AIR": ParamSpec(45.0, 20.0, 89.0, "deg"),
    "MPC_LAND_SPEED": ParamSpec(0.7, 0.2, 3.0, "m/s"),
    "COM_OF_LOSS_T": ParamSpec(0.5, 0.0, 60.0, "s"),
    "COM_DISARM_LAND": ParamSpec(2.0, -1.0, 20.0, "s"),
}


def structure_specs(spec: OnboardSpec | None = None) -> dict[str, ParamSpec]:
    """The onboard structure's filter and loop-rate parameters, under the firmware's names,
    with ``spec``'s values as defaults (ranges as the firmware's).

    >>> sorted(structure_specs(OnboardSpec()))
    ['EKF2_PREDICT_US', 'IMU_DGYRO_CUTOFF', 'IMU_GYRO_RATEMAX', 'IMU_INTEG_RATE']
    >>> structure_specs(OnboardSpec(loop_hz=500.0, position_loop_hz=125.0))["EKF2_PREDICT_US"]
    ParamSpec(default=8000.0, low=1000.0, high=20000.0, unit='us')
    >>> structure_specs(OnboardSpec(style="ardupilot", target_cutoff_hz=15.0))["ATC_RAT_RLL_FLTT"]
    ParamSpec(default=15.0, low=0.0, high=500.0, unit='Hz')
    """
    sp = spec or OnboardSpec()
    if sp.style == "ardupilot":
        return {"ATC_RAT_RLL_FLTT": ParamSpec(sp.target_cutoff_hz, 0.0, 500.0, "Hz"),
                "ATC_RAT_PIT_FLTT": ParamSpec(sp.target_cutoff_hz, 0.0, 500.0, "Hz"),
                "ATC_RAT_RLL_FLTD": ParamSpec(sp.dgyro_cutoff_hz, 0.0, 500.0, "Hz"),
                "ATC_RAT_PIT_FLTD": ParamSpec(sp.dgyro_cutoff_hz, 0.0, 500.0, "Hz"),
                "SCHED_LOOP_RATE": ParamSpec(sp.loop_hz, 50.0, 2000.0, "Hz")}
    # the position loop runs on each EKF2 update: every round(EKF2_PREDICT_US / IMU period)
    # samples of vehicle_imu, published at IMU_INTEG_RATE (here the rate loop's rate)
    every = max(1, round(sp.loop_hz / sp.position_loop_hz))
    return {"IMU_DGYRO_CUTOFF": ParamSpec(sp.dgyro_cutoff_hz, 0.0, 1000.0, "Hz"),
            "IMU_GYRO_RATEMAX": ParamSpec(sp.loop_hz, 100.0, 2000.0, "Hz"),
            "IMU_INTEG_RATE": ParamSpec(sp.loop_hz, 100.0, 1000.0, "Hz"),
            "EKF2_PREDICT_US": ParamSpec(float(round(1e6 * every / sp.loop_hz)), 1000.0,
                                         20000.0, "us")}


class ParamStore:
    """The vehicle's float parameters, in a stable order (the MAVLink param_index):
    :data:`PARAM_SPECS`, then the structure's (:func:`structure_specs` of ``spec``)."""

    def __init__(self, hover_thrust: float | None = None,
                 spec: OnboardSpec | None = None) -> None:
        self.specs: dict[str, ParamSpec] = {**PARAM_SPECS, **structure_specs(spec)}
        self.names: tuple[str, ...] = tuple(self.specs)
        self.values: dict[str, float] = {n: s.default for n, s in self.specs.items()}
        if hover_thrust is not None:
            # as if PX4's hover-thrust estimator (MPC_USE_HTE) had converged
            self.values["MPC_THR_HOVER"] = round(_clip(hover_thrust, 0.1, 0.8), 2)

    def __getitem__(self, name: str) -> float:
        return self.values[name]

    def __contains__(self, name: object) -> bool:
        return name in self.values

    def index(self, name: str) -> int:
        return self.names.index(name)

    def set(self, name: str, value: float) -> bool:
        """Set ``name``; False (and no change) for unknown names, NaN/inf or out of range."""
        spec = self.specs.get(name)
        if spec is None or not math.isfinite(value) or not spec.low <= value <= spec.high:
            return False
        self.values[name] = float(value)
        return True


def _clip(v: float, lo: float, hi: float) -> float:
    return lo if v < lo else hi if v > hi else v


class _RateAxis:
    """One axis of the rate controller.

    PX4: ``K (P e + I - D d(rate)/dt) + FF rate_sp``, D on the measured rate, low-passed.
    ArduPilot (AC_PID): the target low-passed (FLTT), ``P e + I + D de/dt + FF target`` with D
    on the error, low-passed (FLTD); ``MC_*RATE_K`` is not used (ArduPilot has none).
    """

    #: the firmware's filter parameters of each axis: (D low-pass, target low-pass)
    _FILTERS: dict[tuple[str, str], tuple[str | None, str | None]] = {
                ("px4", "MC_ROLLRATE"): ("IMU_DGYRO_CUTOFF", None),
                ("px4", "MC_PITCHRATE"): ("IMU_DGYRO_CUTOFF", None),
                ("px4", "MC_YAWRATE"): ("IMU_DGYRO_CUTOFF", None),
                ("ardupilot", "MC_ROLLRATE"): ("ATC_RAT_RLL_FLTD", "ATC_RAT_RLL_FLTT"),
                ("ardupilot", "MC_PITCHRATE"): ("ATC_RAT_PIT_FLTD", "ATC_RAT_PIT_FLTT")}

    def __init__(self, prefix: str, dt: float, spec: OnboardSpec | None = None) -> None:
        spec = spec or OnboardSpec()
        self.p, self.i, self.d = f"{prefix}_P", f"{prefix}_I", f"{prefix}_D"
        self.k, self.ff = f"{prefix}_K", f"{prefix}_FF"
        self.dt = dt
        self.ardupilot = spec.style == "ardupilot"
        self.fd_name, self.ft_name = self._FILTERS.get((spec.style, prefix), (None, None))
        self._names = tuple(n for n in (self.fd_name, self.ft_name) if n)
        self._cutoffs = (spec.dgyro_cutoff_hz, spec.target_cutoff_hz)
        self._set_filters(*self._cutoffs)
        self.reset()

    def _set_filters(self, d_hz: float, target_hz: float) -> None:
        self._cutoffs = (d_hz, target_hz)
        self.alpha = 1.0 - math.exp(-2 * math.pi * d_hz * self.dt) if d_hz > 0 else 1.0
        self.alpha_t = (1.0 - math.exp(-2 * math.pi * target_hz * self.dt)
                        if target_hz > 0 else 1.0)

    def _follow_params(self, prm: ParamStore) -> None:
        """A filter parameter written takes effect at once (as on the firmware)."""
        if not self._names:
            return
        d_hz = prm.values.get(self.fd_name or "", self._cutoffs[0])
        t_hz = prm.values.get(self.ft_name or "", self._cutoffs[1])
        if (d_hz, t_hz) != self._cutoffs:
            self._set_filters(d_hz, t_hz)

    def reset(self) -> None:
        self.integral = 0.0
        self.prev_rate: float | None = None
        self.rate_dot = 0.0
        self.target: float | None = None

    def update(self, prm: ParamStore, rate_sp: float, rate: float, integrate: bool) -> float:
        self._follow_params(prm)
        if self.ardupilot:
            return self._update_ardupilot(prm, rate_sp, rate, integrate)
        if self.prev_rate is not None:
            self.rate_dot += self.alpha * ((rate - self.prev_rate) / self.dt - self.rate_dot)
        self.prev_rate = rate
        err = rate_sp - rate
        if integrate:
            lim = prm["MC_RR_INT_LIM"]
            self.integral = _clip(self.integral + prm[self.i] * err * self.dt, -lim, lim)
        out = prm[self.k] * (prm[self.p] * err + self.integral - prm[self.d] * self.rate_dot)
        return out + prm[self.ff] * rate_sp

    def _update_ardupilot(self, prm: ParamStore, rate_sp: float, rate: float,
                          integrate: bool) -> float:
        tgt = rate_sp if self.target is None else self.target + self.alpha_t * (
            rate_sp - self.target)
        self.target = tgt
        err = tgt - rate
        if self.prev_rate is not None:  # prev_rate holds the previous error here
            self.rate_dot += self.alpha * ((err - self.prev_rate) / self.dt - self.rate_dot)
        self.prev_rate = err
        if integrate:
            lim = prm["MC_RR_INT_LIM"]
            self.integral = _clip(self.integral + prm[self.i] * err * self.dt, -lim, lim)
        return (prm[self.p] * err + self.integral + prm[self.d] * self.rate_dot
                + prm[self.ff] * tgt)


def sqrt_controller(error: float, p: float, accel_max: float, dt: float) -> float:
    """ArduPilot's square-root controller (AP_Math ``sqrt_controller``), rad/s.

    Linear (``p error``) for ``|error| <= accel_max / p^2``, beyond that the rate that
    stops at the target under ``accel_max``; never more than ``|error| / dt``.

    >>> sqrt_controller(0.01, 10.0, 20.0, 0.0025)
    0.1
    >>> round(sqrt_controller(0.5, 10.0, 20.0, 0.0025), 3)  # sqrt(2 * 20 * (0.5 - 0.1))
    4.0
    """
    if accel_max <= 0.0:
        rate = p * error
    elif p == 0.0:
        rate = math.copysign(math.sqrt(2.0 * accel_max * abs(error)), error)
    else:
        lin = accel_max / (p * p)
        if abs(error) > lin:
            rate = math.copysign(math.sqrt(2.0 * accel_max * (abs(error) - 0.5 * lin)), error)
        else:
            rate = p * error
    if dt > 0.0:
        rate = _clip(rate, -abs(error) / dt, abs(error) / dt)
    return rate


class _VelAxis:
    """One axis of the PX4 velocity controller, output an acceleration setpoint in m/s^2."""

    def __init__(self, prefix: str, dt: float) -> None:
        self.p, self.i, self.d = f"{prefix}_P_ACC", f"{prefix}_I_ACC", f"{prefix}_D_ACC"
        self.dt = dt
        self.alpha = 1.0 - math.exp(-2 * math.pi * 5.0 * dt)  # MPC_VELD_LP = 5 Hz
        self.reset()

    def reset(self) -> None:
        self.integral = 0.0
        self.prev_vel: float | None = None
        self.vel_dot = 0.0

    def update(self, prm: ParamStore, vel_sp: float, vel: float, integrate: bool) -> float:
        if self.prev_vel is not None:
            self.vel_dot += self.alpha * ((vel - self.prev_vel) / self.dt - self.vel_dot)
        self.prev_vel = vel
        err = vel_sp - vel
        if integrate:
            self.integral = _clip(self.integral + prm[self.i] * err * self.dt,
                                  -GRAVITY_M_S2, GRAVITY_M_S2)
        return prm[self.p] * err + self.integral - prm[self.d] * self.vel_dot


def _quat_mul(a: tuple[float, ...], b: tuple[float, ...]) -> tuple[float, float, float, float]:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw)


class Autopilot:
    """Modes, arming, setpoints, failsafes and the control cascades.

    Call :meth:`update` once per physics step with the latest measurement; it returns the
    normalised ``(roll, pitch, yaw, thrust)`` command for the mixer.
    """

    def __init__(self, dt_s: float, hover_thrust: float | None = None,
                 spec: OnboardSpec | None = None, position_every: int = 1) -> None:
        self.dt = dt_s
        self.spec = spec or OnboardSpec()
        #: the position loop runs on every ``position_every``-th update (its set points held)
        self.position_every = max(1, int(position_every))
        self.params = ParamStore(hover_thrust, self.spec)
        sp = self.spec
        self._rate = [_RateAxis("MC_ROLLRATE", dt_s, sp), _RateAxis("MC_PITCHRATE", dt_s, sp),
                      _RateAxis("MC_YAWRATE", dt_s, sp)]
        pdt = dt_s * self.position_every
        self._vel = [_VelAxis("MPC_XY_VEL", pdt), _VelAxis("MPC_XY_VEL", pdt),
                     _VelAxis("MPC_Z_VEL", pdt)]
        self._axes: tuple[_RateAxis | _VelAxis, ...] = (*self._rate, *self._vel)
        self.reset()

    def reset(self) -> None:
        self.armed = False
        self.mode = FlightMode.MANUAL
        self.events: list[StatusEvent] = []
        self.t = 0.0
        self.landed = True
        self._landed_since = 0.0
        self._sp_time = -math.inf
        self._sp_kind: str | None = None  # "actuator" | "attitude"
        self._sp_actuator = (0.0, 0.0, 0.0, 0.0)
        self._sp_att = ((1.0, 0.0, 0.0, 0.0), 0.0)
        #: the attitude set point the attitude loop last tracked (w, x, y, z)
        self.attitude_sp: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0)
        self._hold_pos = (0.0, 0.0, 0.0)  # north, east, up
        self._hold_yaw = 0.0
        self._last_meas: tuple[tuple[float, ...], tuple[float, ...]] | None = None
        self._pos_count = 0
        self._pos_out: tuple[float, float, float] | None = None  # roll_sp, pitch_sp, thrust
        for ax in self._axes:
            ax.reset()

    # ----------------------------------------------------------- commands
    def _event(self, severity: int, text: str) -> None:
        self.events.append(StatusEvent(severity, text))

    def drain_events(self) -> list[StatusEvent]:
        out, self.events = self.events, []
        return out

    def arm(self, arm: bool, force: bool = False) -> CommandResult:
        if arm == self.armed:
            return CommandResult.ACCEPTED
        if arm:
            if self.mode is FlightMode.OFFBOARD and not self._offboard_fresh():
                self._event(4, "Arming denied: no offboard setpoints")
                return CommandResult.DENIED
            self.armed = True
            for ax in self._axes:
                ax.reset()
            self._capture_hold()
            self._event(6, "Armed")
            return CommandResult.ACCEPTED
        if not self.landed and not force:
            self._event(4, "Disarming denied: not landed")
            return CommandResult.DENIED
        self.armed = False
        self._event(6, "Disarmed")
        return CommandResult.ACCEPTED

    def set_mode(self, mode: FlightMode) -> CommandResult:
        if mode is self.mode:
            return CommandResult.ACCEPTED
        if mode in (FlightMode.MANUAL, FlightMode.STABILIZED, FlightMode.ACRO) and not (
                self.landed or not self.armed):
            self._event(4, f"Switching to {mode.name} denied: no RC input in the simulator")
            return CommandResult.DENIED
        if mode is FlightMode.OFFBOARD and not self._offboard_fresh():
            self._event(4, "Switching to OFFBOARD denied: stream setpoints first")
            return CommandResult.DENIED
        self._enter(mode)
        return CommandResult.ACCEPTED

    def _enter(self, mode: FlightMode) -> None:
        self.mode = mode
        self._capture_hold()
        for ax in self._vel:
            ax.reset()
        self._pos_out = None
        name = {FlightMode.AUTO_LAND: "LAND"}.get(mode, mode.name)
        self._event(6, f"Mode changed to {name}")

    def land(self) -> CommandResult:
        if self.mode is not FlightMode.AUTO_LAND:
            self._enter(FlightMode.AUTO_LAND)
        return CommandResult.ACCEPTED

    def set_actuator_controls(self, roll: float, pitch: float, yaw: float,
                              thrust: float) -> bool:
        """Torque-path setpoint; False (ignored) if not finite or out of range."""
        vals = (roll, pitch, yaw, thrust)
        if not all(math.isfinite(v) for v in vals) or not (
                all(-1.0 <= v <= 1.0 for v in vals[:3]) and 0.0 <= thrust <= 1.0):
            return False
        self._sp_actuator = (float(roll), float(pitch), float(yaw), float(thrust))
        self._sp_kind, self._sp_time = "actuator", self.t
        return True

    def set_attitude_target(self, q: tuple[float, float, float, float], thrust: float) -> bool:
        """Attitude-path setpoint; False (ignored) if not finite, |q| != 1 or thrust off [0, 1]."""
        if not all(math.isfinite(v) for v in (*q, thrust)) or not 0.0 <= thrust <= 1.0:
            return False
        norm = math.sqrt(sum(v * v for v in q))
        if abs(norm - 1.0) > 1e-2:
            return False
        self._sp_att = (tuple(v / norm for v in q), float(thrust))  # type: ignore[assignment]
        self._sp_kind, self._sp_time = "attitude", self.t
        return True

    # ------------------------------------------------------------- update
    def _offboard_fresh(self) -> bool:
        return self.t - self._sp_time <= max(self.params["COM_OF_LOSS_T"], 0.0) + 1e-9

    def _capture_hold(self) -> None:
        if self._last_meas is None:
            return
        att, posv = self._last_meas
        self._hold_pos = (posv[0], posv[1], -posv[2])
        self._hold_yaw = att[2]

    def update(self, t: float, att: tuple[float, ...], posv: tuple[float, ...],
               on_ground: bool) -> tuple[float, float, float, float]:
        """One control step. ``att``/``posv`` as :attr:`Multirotor.meas_att`/``meas_posv``."""
        self.t = t
        self._last_meas = (att, posv)
        self._update_landed(on_ground)
        if not self.armed:
            return (0.0, 0.0, 0.0, 0.0)
        if self.mode is FlightMode.OFFBOARD and not self._offboard_fresh():
            self._event(2, "Failsafe enabled: no offboard setpoints, landing")
            self._enter(FlightMode.AUTO_LAND)
        mode = self.mode
        if mode is FlightMode.OFFBOARD and self._sp_kind == "actuator":
            return self._sp_actuator
        if mode is FlightMode.OFFBOARD:
            q_sp, thrust = self._sp_att
            return (*self._attitude(q_sp, att), thrust)
        if mode in (FlightMode.POSCTL, FlightMode.ALTCTL, FlightMode.AUTO_LAND,
                    FlightMode.AUTO_LOITER):
            return self._position(mode, att, posv)
        # MANUAL / STABILIZED / ACRO on the ground: nothing to fly
        return (0.0, 0.0, 0.0, 0.0)

    def _update_landed(self, on_ground: bool) -> None:
        # Land detector: the physics' ground contact (PX4 infers it from thrust and motion).
        if on_ground and not self.landed:
            self.landed, self._landed_since = True, self.t
            if self.armed:
                self._event(6, "Landing detected")
        elif not on_ground:
            self.landed = False
        delay = self.params["COM_DISARM_LAND"]
        if (self.armed and self.landed and self.mode is FlightMode.AUTO_LAND and delay >= 0
                and self.t - self._landed_since >= delay):
            self.armed = False
            self._event(6, "Disarmed by auto disarm on land")

    def _attitude(self, q_sp: tuple[float, ...],
                  att: tuple[float, ...]) -> tuple[float, float, float]:
        prm = self.params
        self.attitude_sp = tuple(q_sp)  # what ATTITUDE_TARGET reports
        q = quat_from_euler(att[0], att[1], att[2])
        qe = _quat_mul((q[0], -q[1], -q[2], -q[3]), q_sp)
        # rotation vector of the error (exactly the angle error for a single-axis error)
        vn = math.sqrt(qe[1] * qe[1] + qe[2] * qe[2] + qe[3] * qe[3])
        if vn < 1e-12:
            err = (0.0, 0.0, 0.0)
        else:
            ang = 2.0 * math.atan2(vn, abs(qe[0])) * (1.0 if qe[0] >= 0 else -1.0)
            err = (ang * qe[1] / vn, ang * qe[2] / vn, ang * qe[3] / vn)
        gains = (prm["MC_ROLL_P"], prm["MC_PITCH_P"], prm["MC_YAW_P"])
        limits = (prm["MC_ROLLRATE_MAX"], prm["MC_PITCHRATE_MAX"], prm["MC_YAWRATE_MAX"])
        integrate = not self.landed
        sq = self.spec.style == "ardupilot" and self.spec.accel_max_rad_s2 > 0
        out = []
        for i in range(3):
            lim = limits[i] * _DEG
            raw = (sqrt_controller(err[i], gains[i], self.spec.accel_max_rad_s2, self.dt)
                   if sq and i < 2 else gains[i] * err[i])
            rate_sp = _clip(raw, -lim, lim)
            u = self._rate[i].update(prm, rate_sp, att[3 + i], integrate)
            out.append(_clip(u, -1.0, 1.0))
        return out[0], out[1], out[2]

    def _position(self, mode: FlightMode, att: tuple[float, ...],
                  posv: tuple[float, ...]) -> tuple[float, float, float, float]:
        prm = self.params
        up, hup = -posv[2], self._hold_pos[2]
        if mode is FlightMode.AUTO_LAND:
            vup_sp = -prm["MPC_LAND_SPEED"]
        else:
            vup_sp = _clip(prm["MPC_Z_P"] * (hup - up), -prm["MPC_Z_VEL_MAX_DN"],
                           prm["MPC_Z_VEL_MAX_UP"])
        if self.landed and (mode is FlightMode.AUTO_LAND or hup - up < 0.3):
            for ax in self._axes:
                ax.reset()
            self._pos_out = None
            return (0.0, 0.0, 0.0, 0.0)  # idle on the ground
        self._pos_count += 1
        if self._pos_out is None or self._pos_count >= self.position_every:
            self._pos_count = 0
            self._pos_out = self._velocity(mode, att, posv, vup_sp)
        roll_sp, pitch_sp, thrust = self._pos_out
        q_sp = quat_from_euler(roll_sp, pitch_sp, self._hold_yaw)
        return (*self._attitude(q_sp, att), thrust)

    def _velocity(self, mode: FlightMode, att: tuple[float, ...], posv: tuple[float, ...],
                  vup_sp: float) -> tuple[float, float, float]:
        """The position loop's outputs: roll and pitch set points (rad) and thrust."""
        prm, g = self.params, GRAVITY_M_S2
        north, east = posv[0], posv[1]
        vn, ve, vup = posv[3], posv[4], -posv[5]
        hn, he, _ = self._hold_pos
        integrate = not self.landed
        acc_up = self._vel[2].update(prm, vup_sp, vup, integrate)
        thrust = _clip(prm["MPC_THR_HOVER"] * (1.0 + acc_up / g), 0.0, 1.0)
        if mode is FlightMode.ALTCTL:
            roll_sp = pitch_sp = 0.0
        else:
            vmax = prm["MPC_XY_VEL_MAX"]
            vn_sp = _clip(prm["MPC_XY_P"] * (hn - north), -vmax, vmax)
            ve_sp = _clip(prm["MPC_XY_P"] * (he - east), -vmax, vmax)
            an = self._vel[0].update(prm, vn_sp, vn, integrate)
            ae = self._vel[1].update(prm, ve_sp, ve, integrate)
            cy, sy = math.cos(att[2]), math.sin(att[2])
            a_fwd, a_right = cy * an + sy * ae, -sy * an + cy * ae
            tilt = prm["MPC_TILTMAX_AIR"] * _DEG
            roll_sp = _clip(a_right / g, -tilt, tilt)
            pitch_sp = _clip(-a_fwd / g, -tilt, tilt)
        return roll_sp, pitch_sp, thrust
