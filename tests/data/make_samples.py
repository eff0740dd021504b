"""Regenerate the small sample logs of tests/data (run from the repository root).

    .venv/bin/python tests/data/make_samples.py

Writes ``sample.tlog`` (MAVLink v2 and v1 frames, vehicle and ground station
traffic), ``sample.bin`` (a Copter-style DataFlash log) and ``sample.csv``.
The signals are closed-form, so tests can check decoded values exactly; the
files are small enough to fuzz quickly.
"""

from __future__ import annotations

import math
import struct
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1]))

from mrft_gcs.logs.tlog_writer import TlogWriter  # noqa: E402

T0_UNIX = 1_700_000_000.0  # wall clock of the first record
BOOT0_S = 12.0  # vehicle boot time at the first record
LATENCY_S = 0.002  # vehicle -> ground station
N = 100  # samples per signal
DT = 0.02  # s (50 Hz)


def roll(t: float) -> float:
    return 0.1 * math.sin(2 * math.pi * 1.0 * t)


def tlog(path: Path) -> None:
    from pymavlink.dialects.v10 import common as v1
    from pymavlink.dialects.v20 import common as v2

    veh = v2.MAVLink(None, srcSystem=1, srcComponent=1)
    gcs = v2.MAVLink(None, srcSystem=255, srcComponent=190)
    old = v1.MAVLink(None, srcSystem=1, srcComponent=1)
    with TlogWriter(path, overwrite=True) as w:
        w.write(gcs.heartbeat_encode(6, 8, 0, 0, 4, 3).pack(gcs), T0_UNIX - 0.5)
        w.write(veh.heartbeat_encode(2, 12, 129 | 8, 6 << 16, 4, 3).pack(veh), T0_UNIX - 0.4)
        w.write(veh.param_value_encode(b"MC_ROLL_P", 6.5, 9, 3, 0).pack(veh), T0_UNIX - 0.3)
        i32 = struct.unpack("<f", struct.pack("<i", 7))[0]  # PX4 sends integers byte-wise
        w.write(veh.param_value_encode(b"SYS_AUTOSTART", i32, 6, 3, 1).pack(veh), T0_UNIX - 0.3)
        w.write(veh.param_value_encode(b"MC_PITCH_P", 6.0, 9, 3, 2).pack(veh), T0_UNIX - 0.3)
        for i in range(N):
            t = i * DT
            boot_ms = round((BOOT0_S + t) * 1000)
            wall = T0_UNIX + t + LATENCY_S
            r = roll(t)
            # every 10th attitude frame as MAVLink v1: tlogs mix both
            mav = old if i % 10 == 5 else veh
            att = mav.attitude_encode(boot_ms, r, -0.05, 1.0,
                                      0.2 * math.pi * math.cos(2 * math.pi * t), 0.0, 0.01)
            w.write(att.pack(mav), wall)
            w.write(veh.local_position_ned_encode(boot_ms, 1.0 + t, -2.0, -3.0, 1.0, 0.0, 0.0
                                                  ).pack(veh), wall)
            u = 0.1 if r < 0 else -0.1  # a relay on roll
            w.write(gcs.set_actuator_control_target_encode(
                0, 0, 1, 1, [u, 0.0, 0.0, 0.55, 0, 0, 0, 0]).pack(gcs), T0_UNIX + t + 0.001)
            w.write(gcs.set_attitude_target_encode(
                0, 1, 1, 7, [1.0, 0.0, 0.0, 0.0], 0, 0, 0, 0.55).pack(gcs), T0_UNIX + t + 0.001)
            if i % 25 == 0:
                w.write(veh.heartbeat_encode(2, 12, 129 | 8, 6 << 16, 4, 3).pack(veh), wall)
        w.write(veh.statustext_encode(4, b"Relay test done").pack(veh), T0_UNIX + N * DT)
        # a frame from a gimbal (another component): its ATTITUDE must be ignored
        gimbal = v2.MAVLink(None, srcSystem=1, srcComponent=154)
        w.write(gimbal.attitude_encode(0, 1.0, 1.0, 1.0, 0, 0, 0).pack(gimbal), T0_UNIX + N * DT)


def _fmt(mtype: int, name: str, fmt: str, cols: str) -> bytes:
    sizes = {"n": 4, "Q": 8, "f": 4, "c": 2, "C": 2, "B": 1, "N": 16, "Z": 64, "h": 2}
    length = 3 + sum(sizes[c] for c in fmt)
    return b"\xa3\x95\x80" + struct.pack("<BB4s16s64s", mtype, length, name.encode(),
                                         fmt.encode(), cols.encode())


def dataflash(path: Path) -> None:
    out = bytearray(_fmt(0x80, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns"))
    out += _fmt(0x81, "PARM", "QNf", "TimeUS,Name,Value")
    out += _fmt(0x82, "MSG", "QZ", "TimeUS,Message")
    out += _fmt(0x83, "ATT", "QccccCCCC",
                "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,ErrRP,ErrYaw")
    out += _fmt(0x84, "RATE", "Qffffffffffff",
                "TimeUS,RDes,R,ROut,PDes,P,POut,YDes,Y,YOut,ADes,A,AOut")
    out += _fmt(0x85, "XKF1", "QBffffffffff", "TimeUS,C,Roll,Pitch,Yaw,VN,VE,VD,dPD,PN,PE,PD")
    out += _fmt(0x86, "CTUN", "Qff", "TimeUS,ThI,ThO")
    rec = lambda t, fmt, *v: b"\xa3\x95" + bytes([t]) + struct.pack("<" + fmt, *v)  # noqa: E731
    out += rec(0x81, "Q16sf", 1_000_000, b"ATC_RAT_RLL_P", 0.135)
    out += rec(0x81, "Q16sf", 1_000_000, b"ATC_ANG_RLL_P", 4.5)
    out += rec(0x82, "Q64s", 1_500_000, b"ArduCopter V4.5.0 (sample)")
    for i in range(N):
        t_us = 2_000_000 + i * 20_000
        t = i * DT
        r_deg = math.degrees(roll(t))
        out += rec(0x83, "QhhhhHHHH", t_us, 0, round(r_deg * 100), 0, -300, 0, 18000, 0, 0)
        rate_dps = math.degrees(0.2 * math.pi * math.cos(2 * math.pi * t))
        u = 0.1 if r_deg < 0 else -0.1
        out += rec(0x84, "Q12f", t_us + 100, 0, rate_dps, u, 0, 0, 0, 0, 0, 0, 0, 0, 0.5)
        for core in (0, 1):
            out += rec(0x85, "QB10f", t_us + 200, core, 0, 0, 0, 1.0, 0, 0, 0,
                       1.0 + t + 100 * core, -2.0, -3.0)
        out += rec(0x86, "Qff", t_us + 300, 0.5, 0.45)
    out += b"\xa3\x95\x83" + b"\x00" * 7  # a record cut by the end of the file
    path.write_bytes(bytes(out))


def csv(path: Path) -> None:
    lines = ["# mrft-gcs loop csv v1", "# beta=-0.3 h=0.1 vehicle=sample", "t,loop,u,y"]
    for i in range(N):
        t = i * DT
        r = roll(t)
        lines.append(f"{t:.3f},roll,{0.1 if r < 0 else -0.1},{r:.6f}")
        lines.append(f"{t:.3f},altitude,{0.6 if i % 20 < 10 else 0.5},{1.0 + 0.01 * i:.4f}")
    lines.insert(10, "0.5,roll,nan,0.0")  # dropped on reading
    path.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    tlog(HERE / "sample.tlog")
    dataflash(HERE / "sample.bin")
    csv(HERE / "sample.csv")
