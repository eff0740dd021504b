"""Typed telemetry: what every source (live link, SITL, log replay) yields.

Wire messages (MAVLink, ULog topics, DataFlash records, CSV rows) are turned
into these frozen dataclasses once, at the boundary of the module that reads
them; nothing downstream touches raw messages. All times are seconds on the
source's own clock (``t_s``); angles in radians; positions in metres, NED
(north, east, down) as MAVLink's LOCAL_POSITION_NED.

A :class:`TelemetrySource` answers :meth:`~TelemetrySource.next_sample`; the
live link, the SITL and every log reader implement it, so ``tune`` and
``dry-run`` share one pipeline (:func:`collect` turns a stream into arrays).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

__all__ = [
    "Attitude",
    "LocalPosition",
    "ActuatorTarget",
    "AttitudeTarget",
    "quat_from_euler",
    "AttitudeSetpoint",
    "RateTarget",
    "PidTuning",
    "ThrottleReport",
    "StatusText",
    "Heartbeat",
    "ParamValue",
    "Sample",
    "TelemetrySource",
    "EndOfStream",
    "TelemetryLog",
    "collect",
    "is_finite_sample",
]


@dataclass(frozen=True, slots=True)
class Attitude:
    """Body attitude (MAVLink ATTITUDE)."""

    t_s: float
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    rollspeed_rad_s: float
    pitchspeed_rad_s: float
    yawspeed_rad_s: float


@dataclass(frozen=True, slots=True)
class LocalPosition:
    """Position and velocity in the local NED frame (MAVLink LOCAL_POSITION_NED)."""

    t_s: float
    x_m: float
    y_m: float
    z_m: float
    vx_m_s: float
    vy_m_s: float
    vz_m_s: float


@dataclass(frozen=True, slots=True)
class ActuatorTarget:
    """Normalised torque and thrust command (SET_ACTUATOR_CONTROL_TARGET group 0).

    ``roll``, ``pitch``, ``yaw`` in [-1, 1] (1 = largest moment about that axis),
    ``thrust`` in [0, 1] (1 = full collective thrust).
    """

    t_s: float
    roll: float
    pitch: float
    yaw: float
    thrust: float


@dataclass(frozen=True, slots=True)
class AttitudeTarget:
    """Attitude quaternion (w, x, y, z) and thrust setpoint (SET_ATTITUDE_TARGET);
    ``body_rates`` (roll, pitch, yaw, rad/s) sent with it as the feed-forward where given
    (ArduCopter: the rate path's yaw beside roll and pitch held onboard), else ignored."""

    t_s: float
    q_wxyz: tuple[float, float, float, float]
    thrust: float
    body_rates: tuple[float, float, float] | None = None


def quat_from_euler(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """ZYX Euler angles (rad) to a unit quaternion ``(w, x, y, z)``."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy)


@dataclass(frozen=True, slots=True)
class AttitudeSetpoint:
    """The attitude set point the vehicle's own controller tracks, on the vehicle clock
    (MAVLink ATTITUDE_TARGET, sent by the vehicle): Euler angles in rad, thrust in [0, 1]."""

    t_s: float
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    thrust: float


@dataclass(frozen=True, slots=True)
class RateTarget:
    """Body-rate set point with thrust (SET_ATTITUDE_TARGET with the attitude ignored):
    roll, pitch, yaw rates in rad/s (body frame), ``thrust`` in [0, 1]."""

    t_s: float
    roll_rate_rad_s: float
    pitch_rate_rad_s: float
    yaw_rate_rad_s: float
    thrust: float


@dataclass(frozen=True, slots=True)
class PidTuning:
    """One axis of the vehicle's rate loop (MAVLink PID_TUNING, ArduPilot ``GCS_PID_MASK``):
    ``axis`` 1 roll, 2 pitch, 3 yaw; ``desired`` and ``achieved`` rates in rad/s; the
    output's terms ``ff``, ``p``, ``i``, ``d`` in normalised command units. ``t_s`` is the
    receive time on this computer's monotonic clock (the message has no timestamp)."""

    t_s: float
    axis: int
    desired: float
    achieved: float
    ff: float
    p: float
    i: float
    d: float


@dataclass(frozen=True, slots=True)
class ThrottleReport:
    """The throttle the vehicle's motors get (MAVLink VFR_HUD ``throttle``, 0-100 %). ``t_s``
    is the vehicle time of the latest ATTITUDE or LOCAL_POSITION_NED (VFR_HUD has none)."""

    t_s: float
    throttle_pct: float


@dataclass(frozen=True, slots=True)
class StatusText:
    """A human-readable message from the vehicle (STATUSTEXT)."""

    t_s: float
    severity: int
    text: str


class AutopilotFamily(enum.Enum):
    """Which autopilot a heartbeat announces (MAV_AUTOPILOT)."""

    PX4 = "px4"
    ARDUPILOT = "ardupilot"
    GENERIC = "generic"
    OTHER = "other"


@dataclass(frozen=True, slots=True)
class Heartbeat:
    """A vehicle heartbeat: who it is, armed or not, which custom mode."""

    t_s: float
    autopilot: int
    vehicle_type: int
    base_mode: int
    custom_mode: int
    system_status: int

    @property
    def armed(self) -> bool:
        return bool(self.base_mode & 128)  # MAV_MODE_FLAG_SAFETY_ARMED


@dataclass(frozen=True, slots=True)
class ParamValue:
    """One parameter as the vehicle reports it (PARAM_VALUE)."""

    t_s: float
    name: str
    value: float
    index: int = -1
    count: int = -1


Sample = (Attitude | LocalPosition | ActuatorTarget | AttitudeTarget | StatusText | Heartbeat
          | ParamValue | AttitudeSetpoint)


class EndOfStream(Exception):
    """Raised by a finite source (a log) when it has no more samples."""


@runtime_checkable
class TelemetrySource(Protocol):
    """Anything that yields typed telemetry samples.

    ``next_sample`` returns the next sample, ``None`` if nothing arrived within
    ``timeout_s`` (live sources only), and raises :class:`EndOfStream` when a
    finite source is exhausted.
    """

    def next_sample(self, timeout_s: float = 1.0) -> Sample | None: ...

    def close(self) -> None: ...


def is_finite_sample(sample: Sample) -> bool:
    """True if every numeric field of ``sample`` is finite (NaN telemetry is rejected)."""
    for name in sample.__slots__:  # type: ignore[attr-defined]
        value = getattr(sample, name)
        if isinstance(value, float) and not math.isfinite(value):
            return False
        if isinstance(value, tuple) and not all(math.isfinite(v) for v in value):
            return False
    return True


def _empty(n: int) -> np.ndarray:
    return np.empty((0, n))


@dataclass(frozen=True)
class TelemetryLog:
    """A whole stream as arrays, one table per message type.

    Each table is ``(N, k)`` float64 with time in column 0:

    - ``attitude``: t, roll, pitch, yaw, rollspeed, pitchspeed, yawspeed
    - ``position``: t, x, y, z, vx, vy, vz (NED)
    - ``actuator``: t, roll, pitch, yaw, thrust (commanded, normalised)
    - ``attitude_target``: t, qw, qx, qy, qz, thrust

    ``loops`` holds per-loop signals given explicitly (the documented CSV format):
    key is a :class:`~mrft_gcs.loops.Loop` value (``roll`` ...), table columns t, u, y
    (u the relay/controller output in the loop's input units, y the measured variable).
    """

    attitude: np.ndarray = field(default_factory=lambda: _empty(7))
    position: np.ndarray = field(default_factory=lambda: _empty(7))
    actuator: np.ndarray = field(default_factory=lambda: _empty(5))
    attitude_target: np.ndarray = field(default_factory=lambda: _empty(6))
    status: tuple[StatusText, ...] = ()
    params: dict[str, float] = field(default_factory=dict)
    heartbeats: tuple[Heartbeat, ...] = ()
    loops: dict[str, np.ndarray] = field(default_factory=dict)
    source: str = ""

    @property
    def duration_s(self) -> float:
        tables = (self.attitude, self.position, self.actuator, *self.loops.values())
        ends = [a[[0, -1], 0] for a in tables if len(a)]
        if not ends:
            return 0.0
        return float(max(e[1] for e in ends) - min(e[0] for e in ends))

    def summary(self) -> dict[str, int]:
        """Message counts, for 'what did this log contain' messages."""
        return {
            "attitude": len(self.attitude),
            "position": len(self.position),
            "actuator": len(self.actuator),
            "attitude_target": len(self.attitude_target),
            "status": len(self.status),
            "params": len(self.params),
            **{f"loop:{k}": len(v) for k, v in self.loops.items()},
        }


def collect(samples: Iterable[Sample], source: str = "") -> TelemetryLog:
    """Gather typed samples into a :class:`TelemetryLog`; non-finite samples are dropped."""
    att: list[tuple[float, ...]] = []
    pos: list[tuple[float, ...]] = []
    act: list[tuple[float, ...]] = []
    atg: list[tuple[float, ...]] = []
    status: list[StatusText] = []
    beats: list[Heartbeat] = []
    params: dict[str, float] = {}
    for s in samples:
        if not is_finite_sample(s):
            continue
        if isinstance(s, Attitude):
            att.append((s.t_s, s.roll_rad, s.pitch_rad, s.yaw_rad,
                        s.rollspeed_rad_s, s.pitchspeed_rad_s, s.yawspeed_rad_s))
        elif isinstance(s, LocalPosition):
            pos.append((s.t_s, s.x_m, s.y_m, s.z_m, s.vx_m_s, s.vy_m_s, s.vz_m_s))
        elif isinstance(s, ActuatorTarget):
            act.append((s.t_s, s.roll, s.pitch, s.yaw, s.thrust))
        elif isinstance(s, AttitudeTarget):
            atg.append((s.t_s, *s.q_wxyz, s.thrust))
        elif isinstance(s, StatusText):
            status.append(s)
        elif isinstance(s, Heartbeat):
            beats.append(s)
        elif isinstance(s, ParamValue):
            params[s.name] = s.value

    def table(rows: list[tuple[float, ...]], n: int) -> np.ndarray:
        if not rows:
            return _empty(n)
        a = np.asarray(rows, dtype=float)
        return a[np.argsort(a[:, 0], kind="stable")]

    return TelemetryLog(
        attitude=table(att, 7),
        position=table(pos, 7),
        actuator=table(act, 5),
        attitude_target=table(atg, 6),
        status=tuple(status),
        params=params,
        heartbeats=tuple(beats),
        source=source,
    )
