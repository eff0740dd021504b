"""MAVLink telemetry logs (.tlog), the format QGroundControl and MAVProxy write.

A .tlog is a sequence of records, each an 8-byte big-endian unsigned integer
(microseconds since the Unix epoch, when the ground station logged the frame)
followed by one raw MAVLink v1 (``0xFE``) or v2 (``0xFD``) frame. Traffic in
both directions is logged, so a tuning session's .tlog holds what the vehicle
sent (ATTITUDE, LOCAL_POSITION_NED ...) and what the ground station commanded
(SET_ACTUATOR_CONTROL_TARGET, SET_ATTITUDE_TARGET).

Fast path: frames are delimited in one pass over the bytes, then only the
message ids this project reads are checked (CRC-16/MCRF4XX with the message's
CRC extra) and decoded with numpy, a whole message type at a time. Field layouts
and CRC extras come from pymavlink's ``common`` dialect. Frames with a bad CRC
are dropped; bytes that do not start a record are skipped until the next STX.

Clock (``t_s``)
---------------
``t_s`` is the vehicle's boot clock in seconds (``time_boot_ms`` /
``time_usec`` of the vehicle's own messages). Messages without a vehicle
time stamp (the ground station's SET_* commands, STATUSTEXT, HEARTBEAT,
PARAM_VALUE) are placed on that clock through the .tlog time stamp:
``t_s = t_unix - offset``, with ``offset`` the lower envelope of ``t_unix - t_boot``
over ATTITUDE and LOCAL_POSITION_NED (the least-delayed frames), kept up to date over
the log as a live tune keeps it (:mod:`mrft_gcs.link.clock`: the clocks drift, and a
simulated vehicle on a busy host slips behind real time; ``DecodedLog.clock`` holds the
fit). After a vehicle
reboot (boot time going back) the new boot clock is shifted by the wall-clock
gap so ``t_s`` keeps increasing. A log with no vehicle time stamps at all uses
seconds since its first record.

Which messages become what
--------------------------
=============================  ======================================================
ATTITUDE                       :class:`~mrft_gcs.telemetry.Attitude`
LOCAL_POSITION_NED             :class:`~mrft_gcs.telemetry.LocalPosition`
SET_ACTUATOR_CONTROL_TARGET    :class:`~mrft_gcs.telemetry.ActuatorTarget` (group 0);
ACTUATOR_CONTROL_TARGET        the vehicle's report, used only if the log holds no SET_
SET_ATTITUDE_TARGET            :class:`~mrft_gcs.telemetry.AttitudeTarget`;
ATTITUDE_TARGET                the vehicle's report, used only if the log holds no SET_
STATUSTEXT, HEARTBEAT          :class:`~mrft_gcs.telemetry.StatusText`, ``Heartbeat``
PARAM_VALUE                    :class:`~mrft_gcs.telemetry.ParamValue` (integer types
                               decoded byte-wise for PX4, by value otherwise)
=============================  ======================================================

Order: ``DecodedLog.file_order`` keeps where each ATTITUDE, LOCAL_POSITION_NED
and SET_* row was logged. A ground station logs what it receives and sends as
it happens, so a command answered telemetry logged before it; dry-run pairs them
by that order. The clock cannot: a command carries no vehicle time, and its
wall-clock stamp, moved by the smallest ``wall - boot`` offset, lands after the
next sample whenever that sample's link delay was above the smallest one.

Only the vehicle's messages are read: the system and component of the first
heartbeat from an autopilot (else the most frequent sender of ATTITUDE); SET_
messages count when addressed to that system (or to all).
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np

from mrft_gcs.link.clock import ClockFit, clock_bins, fit_clock
from mrft_gcs.logs._common import input_error, read_bytes
from mrft_gcs.logs.replay import DecodedLog
from mrft_gcs.telemetry import Heartbeat, ParamValue, Sample, StatusText

__all__ = ["decode_tlog", "sniff_tlog", "TLOG_MESSAGES"]

ATTITUDE = 30
LOCAL_POSITION_NED = 32
SET_ATTITUDE_TARGET = 82
ATTITUDE_TARGET = 83
SET_ACTUATOR_CONTROL_TARGET = 139
ACTUATOR_CONTROL_TARGET = 140
STATUSTEXT = 253
HEARTBEAT = 0
PARAM_VALUE = 22

#: MAVLink message ids the reader decodes.
TLOG_MESSAGES: frozenset[int] = frozenset({
    ATTITUDE, LOCAL_POSITION_NED, SET_ATTITUDE_TARGET, ATTITUDE_TARGET,
    SET_ACTUATOR_CONTROL_TARGET, ACTUATOR_CONTROL_TARGET, STATUSTEXT, HEARTBEAT, PARAM_VALUE,
})

_MAV_AUTOPILOT_INVALID = 8  # ground stations and other non-autopilot components
_MAV_AUTOPILOT_PX4 = 12
_ATT_TYPEMASK_IGNORE_ATTITUDE = 128
_STX = re.compile(b"[\xfd\xfe]")
# Wall-clock range accepted as a plausible .tlog time stamp (years ~1990 to ~2200), in us.
_T_MIN_US, _T_MAX_US = 6.3e14, 7.3e15

_NUMPY_CODES = {"B": "u1", "b": "i1", "H": "u2", "h": "i2", "I": "u4", "i": "i4",
                "Q": "u8", "q": "i8", "f": "f4", "d": "f8", "c": "S1"}


@dataclass(frozen=True)
class _Wire:
    """Wire layout of one message: packed numpy dtype and CRC extra."""

    dtype: np.dtype
    crc_extra: int


@cache
def _wire(msgid: int) -> _Wire:
    """Layout of ``msgid`` from pymavlink's ``common`` dialect (imported once, lazily)."""
    from pymavlink.dialects.v20 import common

    cls = common.mavlink_map[msgid]
    tokens = re.findall(r"(\d*)([a-zA-Z])", cls.unpacker.format.lstrip("<"))
    formats: list[object] = []
    for count, code in tokens:
        n = int(count) if count else 1
        if code == "s":
            formats.append(f"S{n}")
        elif n > 1:
            formats.append((np.dtype("<" + _NUMPY_CODES[code]), (n,)))
        else:
            formats.append("<" + _NUMPY_CODES[code])
    dtype = np.dtype({"names": list(cls.ordered_fieldnames), "formats": formats})
    return _Wire(dtype=dtype, crc_extra=int(cls.crc_extra))


def sniff_tlog(head: bytes) -> bool:
    """True if ``head`` (the first bytes of a file) looks like a .tlog record."""
    if len(head) < 17 or head[8] not in (0xFD, 0xFE):
        return False
    t_us = struct.unpack_from(">Q", head)[0]
    return _T_MIN_US < t_us < _T_MAX_US


def _scan(buf: bytes) -> tuple[list[int], int, int]:
    """Delimit records; return record offsets of wanted ids, frame count, skipped bytes."""
    n = len(buf)
    wanted = TLOG_MESSAGES
    offs: list[int] = []
    append = offs.append
    frames = 0
    skipped = 0
    p = 0
    while p + 9 <= n:
        stx = buf[p + 8]
        if stx == 0xFD:
            if p + 18 > n:
                break
            end = p + 20 + buf[p + 9] + (13 if buf[p + 10] & 1 else 0)
            msgid = buf[p + 15] | (buf[p + 16] << 8) | (buf[p + 17] << 16)
        elif stx == 0xFE:
            if p + 14 > n:
                break
            end = p + 16 + buf[p + 9]
            msgid = buf[p + 13]
        else:
            m = _STX.search(buf, p + 9)
            if m is None:
                skipped += n - p
                break
            skipped += m.start() - 8 - p
            p = m.start() - 8
            continue
        if end > n:
            break
        frames += 1
        if msgid in wanted:
            append(p)
        p = end
    return offs, frames, skipped


def _crc(block: np.ndarray, extra: int) -> np.ndarray:
    """CRC-16/MCRF4XX (MAVLink's X.25) of each row of ``block``, then of ``extra``."""
    crc: np.ndarray = np.full(block.shape[0], 0xFFFF, dtype=np.uint32)
    columns = [block[:, j].astype(np.uint32) for j in range(block.shape[1])]
    columns.append(np.full(block.shape[0], extra, dtype=np.uint32))
    for b in columns:
        tmp = (b ^ (crc & 0xFF)) & 0xFF
        tmp = (tmp ^ (tmp << 4)) & 0xFF
        crc = ((crc >> 8) ^ (tmp << 8) ^ (tmp << 3) ^ (tmp >> 4)) & 0xFFFF
    return crc


@dataclass(frozen=True)
class _Frames:
    """Valid frames of one message id: payloads decoded, with their metadata."""

    pos: np.ndarray  # record offset in the file (file order)
    t_unix: np.ndarray  # .tlog time stamp, s
    sysid: np.ndarray
    compid: np.ndarray
    rec: np.ndarray  # structured array of payloads


def _decode_frames(arr: np.ndarray, offs: np.ndarray, msgid: int) -> _Frames:
    """CRC-check and decode the records at ``offs`` (all carrying ``msgid``)."""
    wire = _wire(msgid)
    full = wire.dtype.itemsize
    v2 = arr[offs + 8] == 0xFD
    length = arr[offs + 9].astype(np.int64)
    keep = np.zeros(len(offs), dtype=bool)
    payload = np.zeros((len(offs), full), dtype=np.uint8)
    for is2 in (False, True):
        for ln in np.unique(length[v2 == is2]):
            sel = np.flatnonzero((v2 == is2) & (length == ln))
            h = 10 if is2 else 6
            start = offs[sel] + 8
            block = arr[start[:, None] + np.arange(1, h + ln)]
            lo, hi = arr[start + h + ln], arr[start + h + ln + 1]
            crc_rx = lo.astype(np.uint32) | (hi.astype(np.uint32) << 8)
            ok = _crc(block, wire.crc_extra) == crc_rx
            if not is2 and ln != full:
                ok[:] = False  # v1 frames carry the whole payload
            keep[sel] = ok
            m = min(int(ln), full)
            payload[sel, :m] = block[:, h - 1:h - 1 + m]
    pos = offs[keep]
    stamp = arr[pos[:, None] + np.arange(8)].copy().view(">u8").ravel()
    is2 = v2[keep]
    p8 = pos + 8
    return _Frames(
        pos=pos,
        t_unix=stamp.astype(np.float64) * 1e-6,
        sysid=np.where(is2, arr[p8 + 5], arr[p8 + 3]).astype(np.int64),
        compid=np.where(is2, arr[p8 + 6], arr[p8 + 4]).astype(np.int64),
        rec=payload[keep].view(wire.dtype).ravel(),
    )


def _text(raw: bytes) -> str:
    return raw.split(b"\0", 1)[0].decode("utf-8", errors="replace")


def _param_value(value: float, ptype: int, bytewise: bool) -> float:
    """A PARAM_VALUE's value: integer types are sent either cast or byte-wise."""
    if not bytewise or ptype in (9, 10):  # MAV_PARAM_TYPE_REAL32 / REAL64
        return value
    raw = struct.pack("<f", value)
    code = {1: "<B", 2: "<b", 3: "<H", 4: "<h", 5: "<I", 6: "<i"}.get(ptype)
    if code is None:
        return value
    return float(struct.unpack_from(code, raw)[0])


def decode_tlog(path: str | Path) -> DecodedLog:
    """Decode a .tlog file into typed tables and events.

    Parameters
    ----------
    path : str or Path
        The .tlog file.

    Returns
    -------
    DecodedLog
        Angles in rad, positions in m (NED), ``t_s`` on the vehicle's boot clock
        (see the module notes).

    Raises
    ------
    InputFileError
        If the file is missing, empty, or holds no valid MAVLink frame.
    """
    buf = read_bytes(path)
    offs_list, frames, skipped = _scan(buf)
    if frames == 0:
        raise input_error(path, "no MAVLink frames found (not a .tlog, or damaged)")
    arr = np.frombuffer(buf, dtype=np.uint8)
    offs = np.asarray(offs_list, dtype=np.int64)
    ids = np.where(arr[offs + 8] == 0xFD,
                   arr[offs + 15].astype(np.int64) | (arr[offs + 16].astype(np.int64) << 8)
                   | (arr[offs + 17].astype(np.int64) << 16),
                   arr[offs + 13].astype(np.int64)) if len(offs) else offs
    by_id = {mid: _decode_frames(arr, offs[ids == mid], mid) for mid in TLOG_MESSAGES}
    if not any(len(f.pos) for f in by_id.values()):
        raise input_error(path, f"no valid ATTITUDE, LOCAL_POSITION_NED, setpoint, HEARTBEAT, "
                                f"STATUSTEXT or PARAM_VALUE frame among {frames} candidate frames "
                                "(not a vehicle telemetry log, or damaged)")
    return _assemble(by_id, str(path))


def _vehicle(by_id: dict[int, _Frames]) -> tuple[int, int] | None:
    hb = by_id[HEARTBEAT]
    auto = hb.rec["autopilot"] != _MAV_AUTOPILOT_INVALID
    if auto.any():
        i = int(np.flatnonzero(auto)[0])
        return int(hb.sysid[i]), int(hb.compid[i])
    att = by_id[ATTITUDE]
    if len(att.pos):
        key = att.sysid * 256 + att.compid
        values, counts = np.unique(key, return_counts=True)
        k = int(values[np.argmax(counts)])
        return k // 256, k % 256
    return None


def _assemble(by_id: dict[int, _Frames], source: str) -> DecodedLog:
    vehicle = _vehicle(by_id)

    def from_vehicle(f: _Frames, component: bool = True) -> _Frames:
        if vehicle is None:
            return f
        m = f.sysid == vehicle[0]
        if component:
            m &= f.compid == vehicle[1]
        return _select(f, m)

    def to_vehicle(f: _Frames) -> _Frames:
        if vehicle is None:
            return f
        return _select(f, np.isin(f.rec["target_system"], (0, vehicle[0])))

    att = from_vehicle(by_id[ATTITUDE])
    lpn = from_vehicle(by_id[LOCAL_POSITION_NED])
    clock = _Clock.fit_log(
        np.concatenate([att.pos, lpn.pos]),
        np.concatenate([att.rec["time_boot_ms"], lpn.rec["time_boot_ms"]]).astype(float) * 1e-3,
        np.concatenate([att.t_unix, lpn.t_unix]),
        min((float(f.t_unix[0]) for f in by_id.values() if len(f.pos)), default=0.0),
    )

    r = att.rec
    attitude = np.column_stack([
        clock.boot(att.pos, r["time_boot_ms"] * 1e-3), r["roll"], r["pitch"], r["yaw"],
        r["rollspeed"], r["pitchspeed"], r["yawspeed"]]).astype(float)
    r = lpn.rec
    position = np.column_stack([
        clock.boot(lpn.pos, r["time_boot_ms"] * 1e-3),
        r["x"], r["y"], r["z"], r["vx"], r["vy"], r["vz"]]).astype(float)

    order = {"attitude": att.pos, "position": lpn.pos}
    sact = to_vehicle(by_id[SET_ACTUATOR_CONTROL_TARGET])
    sact = _select(sact, sact.rec["group_mlx"] == 0)
    if len(sact.pos):
        t_act = clock.wall(sact.t_unix)
        controls = sact.rec["controls"]
        order["actuator"] = sact.pos
    else:
        act = from_vehicle(by_id[ACTUATOR_CONTROL_TARGET])
        act = _select(act, act.rec["group_mlx"] == 0)
        t_act = clock.boot(act.pos, act.rec["time_usec"] * 1e-6)
        controls = act.rec["controls"]
    actuator = np.column_stack([t_act, controls[:, :4]]).astype(float)

    satt = to_vehicle(by_id[SET_ATTITUDE_TARGET])
    if len(satt.pos):
        t_atg, target = clock.wall(satt.t_unix), satt
        order["attitude_target"] = satt.pos
    else:
        target = from_vehicle(by_id[ATTITUDE_TARGET])
        t_atg = clock.boot(target.pos, target.rec["time_boot_ms"] * 1e-3)
    r = target.rec
    attitude_target = np.column_stack([t_atg, r["q"], r["thrust"]]).astype(float)
    with_attitude = (r["type_mask"] & _ATT_TYPEMASK_IGNORE_ATTITUDE) == 0
    attitude_target = attitude_target[with_attitude]
    if "attitude_target" in order:
        order["attitude_target"] = order["attitude_target"][with_attitude]

    events: list[tuple[int, Sample]] = []
    hb = from_vehicle(by_id[HEARTBEAT])
    hb = _select(hb, hb.rec["autopilot"] != _MAV_AUTOPILOT_INVALID)
    for p, t, rec in zip(hb.pos.tolist(), clock.wall(hb.t_unix).tolist(), hb.rec.tolist(),
                          strict=True):
        custom_mode, vtype, autopilot, base_mode, system_status, _ = rec
        events.append((p, Heartbeat(t, autopilot, vtype, base_mode, custom_mode, system_status)))
    st = from_vehicle(by_id[STATUSTEXT], component=False)
    for p, t, rec in zip(st.pos.tolist(), clock.wall(st.t_unix).tolist(), st.rec.tolist(),
                          strict=True):
        events.append((p, StatusText(t, int(rec[0]), _text(rec[1]))))
    pv = from_vehicle(by_id[PARAM_VALUE])
    bytewise = bool(len(hb.pos)) and int(hb.rec["autopilot"][0]) == _MAV_AUTOPILOT_PX4
    for p, t, rec in zip(pv.pos.tolist(), clock.wall(pv.t_unix).tolist(), pv.rec.tolist(),
                          strict=True):
        value, count, index, name, ptype = rec
        events.append((p, ParamValue(t, _text(name), _param_value(value, ptype, bytewise),
                                     index, count)))
    events.sort(key=lambda e: e[0])
    return DecodedLog(attitude=attitude, position=position, actuator=actuator,
                      attitude_target=attitude_target, events=tuple(e for _, e in events),
                      source=source, file_order=order,
                      clock=None if clock.fit.empty else clock.fit)


def _select(f: _Frames, mask: np.ndarray) -> _Frames:
    return _Frames(f.pos[mask], f.t_unix[mask], f.sysid[mask], f.compid[mask], f.rec[mask])


@dataclass(frozen=True)
class _Clock:
    """Maps vehicle boot times and .tlog wall times onto one clock (see module notes)."""

    seg_pos: np.ndarray  # file offset where each boot segment starts
    shift: np.ndarray  # seconds added to boot time in each segment
    offset0: float  # wall - boot of the first segment
    fit: ClockFit  # wall - boot tracked over the log (empty: offset0 throughout)

    @classmethod
    def fit_log(cls, pos: np.ndarray, boot: np.ndarray, wall: np.ndarray, first_wall: float
                ) -> _Clock:
        if len(pos) == 0:
            return cls(np.zeros(1, dtype=np.int64), np.zeros(1), first_wall,
                       fit_clock(clock_bins([], [])))
        order = np.argsort(pos, kind="stable")
        pos, boot, wall = pos[order], boot[order], wall[order]
        starts = np.concatenate([[0], np.flatnonzero(np.diff(boot) < -1.0) + 1])
        offsets = np.minimum.reduceat(wall - boot, starts)
        shift = offsets - offsets[0]
        # in file order, as the live link saw them: the same bins as its clock model
        vt = boot + np.repeat(shift, np.diff(np.append(starts, len(boot))))
        return cls(pos[starts], shift, float(offsets[0]), fit_clock(clock_bins(wall, vt)))

    def boot(self, pos: np.ndarray, boot_s: np.ndarray) -> np.ndarray:
        seg = np.clip(np.searchsorted(self.seg_pos, pos, side="right") - 1, 0, None)
        return np.asarray(boot_s, dtype=float) + self.shift[seg]

    def wall(self, wall_s: np.ndarray) -> np.ndarray:
        if self.fit.empty:
            return np.asarray(wall_s, dtype=float) - self.offset0
        return self.fit.to_vehicle(wall_s)
