"""PX4 ULog files (.ulg), read with pyulog.

Clock: ``t_s`` is PX4's boot clock (the topics' ``timestamp``, microseconds
since boot) in seconds.

=================================================  =========================================
topic                                              becomes
=================================================  =========================================
vehicle_attitude ``q`` (w, x, y, z)                :class:`~mrft_gcs.telemetry.Attitude`
                                                   roll, pitch, yaw (ZYX Euler angles)
vehicle_angular_velocity ``xyz`` (else the old     its body rates, interpolated linearly to
vehicle_attitude ``rollspeed`` ...)                the attitude time stamps
vehicle_local_position x, y, z, vx, vy, vz         :class:`~mrft_gcs.telemetry.LocalPosition`
actuator_controls_0 ``control[0..3]`` (older       :class:`~mrft_gcs.telemetry.ActuatorTarget`
PX4), else vehicle_torque_setpoint ``xyz`` with    (thrust as the magnitude of the thrust
vehicle_thrust_setpoint ``xyz`` interpolated       vector, in [0, 1])
vehicle_attitude_setpoint ``q_d``, thrust          :class:`~mrft_gcs.telemetry.AttitudeTarget`
(``thrust_body`` magnitude, or old ``thrust``)
initial and changed parameters                     :class:`~mrft_gcs.telemetry.ParamValue`
logged messages (log level 0-7 = MAVLink           :class:`~mrft_gcs.telemetry.StatusText`
severity)
=================================================  =========================================

Only instance 0 of each topic is read.
"""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

import numpy as np

from mrft_gcs.logs._common import input_error, interp_columns, read_bytes, read_head
from mrft_gcs.logs.replay import DecodedLog
from mrft_gcs.telemetry import ParamValue, Sample, StatusText

__all__ = ["decode_ulog", "sniff_ulog", "ULOG_MAGIC", "quaternion_to_euler"]

#: First seven bytes of every ULog file ("ULog" 0x01 0x12 0x35).
ULOG_MAGIC = b"ULog\x01\x12\x35"
_TOPICS = [
    "vehicle_attitude", "vehicle_angular_velocity", "vehicle_local_position",
    "actuator_controls_0", "vehicle_torque_setpoint", "vehicle_thrust_setpoint",
    "vehicle_attitude_setpoint",
]


class _WorkLimit(Exception):
    """The parser read far more than the file holds: it is looping on damage."""


class _BoundedFile(io.BytesIO):
    """The file's bytes, refusing to be read more than a few times over.

    pyulog seeks back after a corrupt message; near a damaged end of file that
    can repeat forever. Counting what is read bounds the work on any input.
    """

    def __init__(self, data: bytes, passes: int = 8) -> None:
        super().__init__(data)
        self._left = passes * len(data) + (1 << 20)

    def read(self, size: int | None = -1) -> bytes:
        out = super().read(size)
        self._left -= len(out) + 1
        if self._left < 0:
            raise _WorkLimit
        return out


def sniff_ulog(head: bytes) -> bool:
    """True if ``head`` starts with the ULog magic."""
    return head.startswith(ULOG_MAGIC)


def quaternion_to_euler(q: np.ndarray) -> np.ndarray:
    """ZYX Euler angles of unit quaternions.

    Parameters
    ----------
    q : ndarray, shape (N, 4)
        Quaternions (w, x, y, z), body to NED.

    Returns
    -------
    ndarray, shape (N, 3)
        Roll, pitch, yaw in rad (yaw in [-pi, pi]).

    Examples
    --------
    >>> import numpy as np
    >>> quaternion_to_euler(np.array([[np.cos(0.1), np.sin(0.1), 0.0, 0.0]])).round(6)
    array([[0.2, 0. , 0. ]])
    """
    w, x, y, z = (q[:, i] for i in range(4))
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return np.column_stack([roll, pitch, yaw])


def _cols(data: dict[str, np.ndarray], *names: str) -> np.ndarray | None:
    if not all(n in data for n in names):
        return None
    return np.column_stack([np.asarray(data[n], dtype=float) for n in names])



def decode_ulog(path: str | Path) -> DecodedLog:
    """Decode a PX4 ULog file into typed tables and events.

    Raises
    ------
    InputFileError
        Missing or empty file, bad magic, or a file pyulog cannot parse.
    """
    head = read_head(path, 16)
    if not sniff_ulog(head):
        raise input_error(path, "not a ULog file (bad magic)")
    try:
        from pyulog import ULog
    except ImportError as exc:  # pragma: no cover - pyulog is a core dependency
        raise input_error(path, f"cannot read ULog ({exc})", "pip install pyulog") from None
    data = read_bytes(path)
    try:
        # pyulog reports corruption on stdout; a library must stay silent.
        with contextlib.redirect_stdout(io.StringIO()):
            ulog = ULog(_BoundedFile(data), _TOPICS, disable_str_exceptions=True)
    except _WorkLimit:
        raise input_error(path, "damaged ULog file (the parser went round in circles)",
                          "the log may be truncated or corrupted; try another copy") from None
    except Exception as exc:  # noqa: BLE001 - any parser failure is a damaged file
        raise input_error(path, f"damaged ULog file ({type(exc).__name__}: "
                                f"{str(exc)[:80] or 'no detail'})",
                          "the log may be truncated or corrupted; try another copy") from None
    try:
        return _assemble(ulog, str(path))
    except (KeyError, ValueError, IndexError, TypeError) as exc:
        raise input_error(path, f"unexpected ULog content ({type(exc).__name__}: "
                                f"{str(exc)[:80]})", "the log may be corrupted") from None


def _topic(ulog: object, name: str) -> dict[str, np.ndarray] | None:
    for d in ulog.data_list:  # type: ignore[attr-defined]
        if d.name == name and d.multi_id == 0 and "timestamp" in d.data:
            return d.data
    return None


def _assemble(ulog: object, source: str) -> DecodedLog:
    att = _topic(ulog, "vehicle_attitude")
    attitude = np.empty((0, 7))
    if att is not None and (q := _cols(att, "q[0]", "q[1]", "q[2]", "q[3]")) is not None:
        t = att["timestamp"].astype(float) * 1e-6
        rates = _cols(att, "rollspeed", "pitchspeed", "yawspeed")
        avel = _topic(ulog, "vehicle_angular_velocity")
        if rates is None:
            rates = np.full((len(t), 3), np.nan)
            if avel is not None and (src := _cols(avel, "xyz[0]", "xyz[1]", "xyz[2]")) is not None:
                rates = interp_columns(t, avel["timestamp"].astype(float) * 1e-6, src)
        attitude = np.column_stack([t, quaternion_to_euler(q), rates])

    lp = _topic(ulog, "vehicle_local_position")
    position = np.empty((0, 7))
    if lp is not None and (xyz := _cols(lp, "x", "y", "z", "vx", "vy", "vz")) is not None:
        position = np.column_stack([lp["timestamp"].astype(float) * 1e-6, xyz])

    actuator = np.empty((0, 5))
    ac = _topic(ulog, "actuator_controls_0")
    torque = _topic(ulog, "vehicle_torque_setpoint")
    thrust = _topic(ulog, "vehicle_thrust_setpoint")
    if ac is not None and (u := _cols(ac, *(f"control[{i}]" for i in range(4)))) is not None:
        actuator = np.column_stack([ac["timestamp"].astype(float) * 1e-6, u])
    elif torque is not None and (tq := _cols(torque, "xyz[0]", "xyz[1]", "xyz[2]")) is not None:
        t = torque["timestamp"].astype(float) * 1e-6
        mag = np.full(len(t), np.nan)
        th = _cols(thrust, "xyz[0]", "xyz[1]", "xyz[2]") if thrust is not None else None
        if thrust is not None and th is not None:
            t_th = thrust["timestamp"].astype(float) * 1e-6
            mag = interp_columns(t, t_th, np.linalg.norm(th, axis=1)[:, None])[:, 0]
        actuator = np.column_stack([t, tq, mag])

    attitude_target = np.empty((0, 6))
    sp = _topic(ulog, "vehicle_attitude_setpoint")
    if sp is not None and (qd := _cols(sp, "q_d[0]", "q_d[1]", "q_d[2]", "q_d[3]")) is not None:
        tb = _cols(sp, "thrust_body[0]", "thrust_body[1]", "thrust_body[2]")
        old = _cols(sp, "thrust")
        mag = (np.linalg.norm(tb, axis=1) if tb is not None else
               np.abs(old[:, 0]) if old is not None else np.full(len(qd), np.nan))
        attitude_target = np.column_stack([sp["timestamp"].astype(float) * 1e-6, qd, mag])

    events: list[Sample] = []
    t0 = float(getattr(ulog, "start_timestamp", 0)) * 1e-6
    for name, value in getattr(ulog, "initial_parameters", {}).items():
        events.append(ParamValue(t0, str(name), float(value)))
    for t_us, name, value in getattr(ulog, "changed_parameters", []):
        events.append(ParamValue(float(t_us) * 1e-6, str(name), float(value)))
    for m in getattr(ulog, "logged_messages", []):
        level = int(m.log_level)
        severity = level - ord("0") if ord("0") <= level <= ord("7") else min(max(level, 0), 7)
        events.append(StatusText(float(m.timestamp) * 1e-6, severity, str(m.message)))
    return DecodedLog(attitude=attitude, position=position, actuator=actuator,
                      attitude_target=attitude_target, events=tuple(events), source=source)
