"""ArduPilot DataFlash logs (.bin).

A DataFlash log describes itself: every record is ``A3 95 <type>`` followed by
fields packed end to end, and FMT records (type 128) give each type's name,
length, format characters and column names. This module indexes the records in
one pass and decodes each wanted type as one numpy table. Format characters and
their multipliers follow ArduPilot's ``AP_Logger/LogStructure.h`` (as
pymavlink's ``DFReader`` does); the reader is written here rather than calling
``DFReader`` because that one prints a line to the process's stderr for every
bad byte of a damaged log, and a library must stay silent. Bytes that do not
start a known record are skipped to the next ``A3 95``; a record cut by the end
of the file ends the log.

Clock: ``t_s`` is the autopilot's boot clock (``TimeUS``, or ``TimeMS`` in old
logs) in seconds; records without a time stamp (old PARM) take the time of the
last timed record before them.

========================  =================================================================
record                    becomes
========================  =================================================================
ATT Roll, Pitch, Yaw      :class:`~mrft_gcs.telemetry.Attitude` (deg to rad, yaw wrapped to
                          [-pi, pi)); body rates from RATE R, P, Y (deg/s), else IMU (or GYR)
                          GyrX, GyrY, GyrZ of instance 0 (rad/s), interpolated to ATT times,
                          else the time derivative of the angles
XKF1 (EKF3), else NKF1    :class:`~mrft_gcs.telemetry.LocalPosition` PN, PE, PD, VN, VE, VD
(EKF2), core 0
RATE ROut, POut, YOut,    :class:`~mrft_gcs.telemetry.ActuatorTarget` (Copter's rate
AOut                      controller outputs and throttle)
ATT DesRoll, DesPitch,    :class:`~mrft_gcs.telemetry.AttitudeTarget`, thrust from CTUN ThO
DesYaw                    (else RATE AOut); absent when the log has neither
PARM Name, Value          :class:`~mrft_gcs.telemetry.ParamValue`
MSG Message               :class:`~mrft_gcs.telemetry.StatusText` (severity 6, info)
========================  =================================================================
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mrft_gcs.logs._common import input_error, interp_columns, read_bytes
from mrft_gcs.logs.replay import DecodedLog
from mrft_gcs.telemetry import ParamValue, Sample, StatusText

__all__ = ["decode_dataflash", "sniff_dataflash", "DATAFLASH_MAGIC", "euler_to_quaternion"]

#: A DataFlash log starts with the FMT record that defines FMT itself.
DATAFLASH_MAGIC = b"\xa3\x95\x80"
_HEAD = b"\xa3\x95"
_FMT_TYPE = 0x80
_FMT_LEN = 89
# format char -> (numpy dtype, multiplier)
_CHARS: dict[str, tuple[str, float | None]] = {
    "a": ("(32,)<i2", None), "b": ("i1", None), "B": ("u1", None), "h": ("<i2", None),
    "H": ("<u2", None), "i": ("<i4", None), "I": ("<u4", None), "f": ("<f4", None),
    "d": ("<f8", None), "n": ("S4", None), "N": ("S16", None), "Z": ("S64", None),
    "c": ("<i2", 0.01), "C": ("<u2", 0.01), "e": ("<i4", 0.01), "E": ("<u4", 0.01),
    "L": ("<i4", 1e-7), "M": ("u1", None), "q": ("<i8", None), "Q": ("<u8", None),
}
_WANTED = ("ATT", "RATE", "IMU", "GYR", "XKF1", "NKF1", "CTUN", "PARM", "MSG")
_MSG_SEVERITY_INFO = 6


def sniff_dataflash(head: bytes) -> bool:
    """True if ``head`` starts like a DataFlash log."""
    return head.startswith(DATAFLASH_MAGIC)


def euler_to_quaternion(rpy: np.ndarray) -> np.ndarray:
    """Quaternions (w, x, y, z) of ZYX Euler angles.

    Parameters
    ----------
    rpy : ndarray, shape (N, 3)
        Roll, pitch, yaw in rad.

    Returns
    -------
    ndarray, shape (N, 4)
    """
    hr, hp, hy = (rpy[:, i] / 2 for i in range(3))
    cr, sr, cp, sp, cy, sy = np.cos(hr), np.sin(hr), np.cos(hp), np.sin(hp), np.cos(hy), np.sin(hy)
    return np.column_stack([
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    ])


@dataclass(frozen=True)
class _Type:
    """One message type as its FMT record defines it."""

    name: str
    length: int
    dtype: np.dtype
    scale: dict[str, float]


def _parse_fmt(payload: bytes) -> tuple[int, _Type] | None:
    """The type an FMT payload defines, or None if it is not self-consistent."""
    mtype, length = payload[0], payload[1]
    name = payload[2:6].split(b"\0", 1)[0].decode("ascii", "replace")
    fmt = payload[6:22].split(b"\0", 1)[0].decode("ascii", "replace")
    cols = payload[22:86].split(b"\0", 1)[0].decode("ascii", "replace").split(",")
    if mtype == _FMT_TYPE or not fmt or any(c not in _CHARS for c in fmt):
        return None
    if len(cols) != len(fmt):
        cols = [f"F{i}" for i in range(len(fmt))]
    names: list[str] = []
    for c in cols:
        c = c.strip() or "F"
        while c in names:
            c += "_"
        names.append(c)
    try:
        dtype = np.dtype({"names": names, "formats": [_CHARS[c][0] for c in fmt]})
    except (ValueError, TypeError):
        return None
    if dtype.itemsize + 3 != length:
        return None
    scale = {n: m for n, c in zip(names, fmt, strict=True) if (m := _CHARS[c][1]) is not None}
    return mtype, _Type(name, length, dtype, scale)


def _index(buf: bytes) -> tuple[dict[int, _Type], dict[int, list[int]], int]:
    """One pass: formats, record offsets per wanted type, bytes skipped."""
    n = len(buf)
    types: dict[int, _Type] = {}
    lengths = [0] * 256
    lengths[_FMT_TYPE] = _FMT_LEN
    offsets: dict[int, list[int]] = {}
    skipped = 0
    p = 0
    while p + 3 <= n:
        if buf[p] == 0xA3 and buf[p + 1] == 0x95:
            t = buf[p + 2]
            length = lengths[t]
            if length:
                if p + length > n:
                    break  # cut by the end of the file
                if t == _FMT_TYPE:
                    parsed = _parse_fmt(buf[p + 3:p + length])
                    if parsed is not None and parsed[0] not in types:
                        types[parsed[0]] = parsed[1]
                        lengths[parsed[0]] = parsed[1].length
                        if parsed[1].name in _WANTED:
                            offsets[parsed[0]] = []
                elif t in offsets:
                    offsets[t].append(p)
                p += length
                continue
        q = buf.find(_HEAD, p + 1)
        if q < 0:
            skipped += n - p
            break
        skipped += q - p
        p = q
    return types, offsets, skipped


@dataclass(frozen=True)
class _Table:
    pos: np.ndarray
    rec: np.ndarray
    kind: _Type

    def has(self, *names: str) -> bool:
        present = self.rec.dtype.names or ()
        return all(n in present for n in names)

    def col(self, name: str) -> np.ndarray:
        with np.errstate(invalid="ignore", over="ignore"):  # garbage bytes may be NaN patterns
            v = self.rec[name].astype(float)
        return v * self.kind.scale[name] if name in self.kind.scale else v

    def time(self) -> np.ndarray | None:
        if self.has("TimeUS"):
            return self.rec["TimeUS"].astype(float) * 1e-6
        if self.has("TimeMS"):
            return self.rec["TimeMS"].astype(float) * 1e-3
        return None

    def instance0(self) -> _Table:
        for key in ("I", "C"):
            if self.has(key) and self.rec[key].dtype.kind in "iu":
                m = self.rec[key] == 0
                return _Table(self.pos[m], self.rec[m], self.kind)
        return self



def decode_dataflash(path: str | Path) -> DecodedLog:
    """Decode an ArduPilot DataFlash log into typed tables and events.

    Raises
    ------
    InputFileError
        Missing or empty file, bad magic, or no record a reader could use.
    """
    buf = read_bytes(path)
    if not sniff_dataflash(buf[:3]):
        raise input_error(path, "not an ArduPilot DataFlash log (bad magic)")
    types, offsets, _ = _index(buf)
    if not types:
        raise input_error(path, "no valid FMT record (damaged DataFlash log)",
                          "the log may be corrupted; try another copy")
    arr = np.frombuffer(buf, dtype=np.uint8)
    tables: dict[str, _Table] = {}
    for t, offs in offsets.items():
        kind = types[t]
        pos = np.asarray(offs, dtype=np.int64)
        block = arr[pos[:, None] + np.arange(3, kind.length)] if len(pos) else \
            np.empty((0, kind.length - 3), dtype=np.uint8)
        tables[kind.name] = _Table(pos, np.ascontiguousarray(block).view(kind.dtype).ravel(), kind)
    return _assemble(tables, str(path))


def _assemble(tables: dict[str, _Table], source: str) -> DecodedLog:
    att = tables.get("ATT")
    rate = tables.get("RATE")
    attitude = np.empty((0, 7))
    attitude_target = np.empty((0, 6))
    if att is not None and att.has("Roll", "Pitch", "Yaw") and (t := att.time()) is not None:
        rpy = np.deg2rad(np.column_stack([att.col("Roll"), att.col("Pitch"), att.col("Yaw")]))
        rpy[:, 2] = (rpy[:, 2] + np.pi) % (2 * np.pi) - np.pi
        rates = _rates(tables, t, rpy)
        attitude = np.column_stack([t, rpy, rates])
        if att.has("DesRoll", "DesPitch", "DesYaw"):
            thrust = _thrust(tables, t)
            if thrust is not None:
                des = np.deg2rad(np.column_stack(
                    [att.col("DesRoll"), att.col("DesPitch"), att.col("DesYaw")]))
                attitude_target = np.column_stack([t, euler_to_quaternion(des), thrust])

    position = np.empty((0, 7))
    for name in ("XKF1", "NKF1"):
        ekf = tables.get(name)
        if ekf is not None and len(ekf.pos) and ekf.has("PN", "PE", "PD", "VN", "VE", "VD"):
            ekf = ekf.instance0()
            if (t := ekf.time()) is not None:
                position = np.column_stack(
                    [t, *(ekf.col(c) for c in ("PN", "PE", "PD", "VN", "VE", "VD"))])
                break

    actuator = np.empty((0, 5))
    if rate is not None and rate.has("ROut", "POut", "YOut", "AOut") and \
            (t := rate.time()) is not None:
        actuator = np.column_stack([t, *(rate.col(c) for c in ("ROut", "POut", "YOut", "AOut"))])

    events = _events(tables)
    return DecodedLog(attitude=attitude, position=position, actuator=actuator,
                      attitude_target=attitude_target, events=tuple(events), source=source)


def _rates(tables: dict[str, _Table], t: np.ndarray, rpy: np.ndarray) -> np.ndarray:
    """Body rates (rad/s) at times ``t``: RATE, else IMU/GYR instance 0, else d(angles)/dt."""
    rate = tables.get("RATE")
    if rate is not None and len(rate.pos) and rate.has("R", "P", "Y") and \
            (tr := rate.time()) is not None:
        return interp_columns(t, tr, np.deg2rad(np.column_stack([rate.col(c) for c in "RPY"])))
    for name in ("IMU", "GYR"):
        imu = tables.get(name)
        if imu is not None and imu.has("GyrX", "GyrY", "GyrZ"):
            imu = imu.instance0()
            ti = imu.time()
            if ti is not None and len(ti):
                gyro = np.column_stack([imu.col(c) for c in ("GyrX", "GyrY", "GyrZ")])
                return interp_columns(t, ti, gyro)
    if len(t) < 2 or np.any(np.diff(t) <= 0):
        return np.full((len(t), 3), np.nan)
    return np.column_stack([np.gradient(np.unwrap(rpy[:, i]), t) for i in range(3)])


def _thrust(tables: dict[str, _Table], t: np.ndarray) -> np.ndarray | None:
    for name, col in (("CTUN", "ThO"), ("RATE", "AOut")):
        tab = tables.get(name)
        if tab is not None and len(tab.pos) and tab.has(col) and (ts := tab.time()) is not None:
            return interp_columns(t, ts, tab.col(col)[:, None])[:, 0]
    return None


def _text(raw: bytes) -> str:
    return raw.split(b"\0", 1)[0].decode("utf-8", errors="replace")


def _events(tables: dict[str, _Table]) -> list[Sample]:
    """PARM and MSG records, in file order, with untimed ones given the preceding time."""
    timed_pos: list[np.ndarray] = []
    timed_t: list[np.ndarray] = []
    for tab in tables.values():
        if (t := tab.time()) is not None:
            timed_pos.append(tab.pos)
            timed_t.append(t)
    all_pos = np.concatenate(timed_pos) if timed_pos else np.empty(0, dtype=np.int64)
    all_t = np.concatenate(timed_t) if timed_t else np.empty(0)
    order = np.argsort(all_pos, kind="stable")
    all_pos, all_t = all_pos[order], all_t[order]

    def times(tab: _Table) -> np.ndarray:
        t = tab.time()
        if t is not None:
            return t
        if not len(all_pos):
            return np.zeros(len(tab.pos))
        i = np.searchsorted(all_pos, tab.pos) - 1
        return np.where(i >= 0, all_t[np.clip(i, 0, None)], all_t[0])

    events: list[tuple[int, Sample]] = []
    parm = tables.get("PARM")
    if parm is not None and parm.has("Name", "Value"):
        params = zip(parm.pos.tolist(), times(parm).tolist(), parm.rec["Name"].tolist(),
                     parm.col("Value").tolist(), strict=True)
        for p, t, name, value in params:
            events.append((p, ParamValue(t, _text(name), value)))
    msg = tables.get("MSG")
    if msg is not None and msg.has("Message"):
        texts = zip(msg.pos.tolist(), times(msg).tolist(), msg.rec["Message"].tolist(), strict=True)
        for p, t_s, text in texts:
            events.append((p, StatusText(t_s, _MSG_SEVERITY_INFO, _text(text))))
    events.sort(key=lambda e: e[0])
    return [e for _, e in events]

