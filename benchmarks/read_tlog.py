"""Benchmark: read a 10-minute .tlog of 250 Hz telemetry.

Generates, in a temporary folder, what a tuning session logs: ATTITUDE and
LOCAL_POSITION_NED from the vehicle at 250 Hz each, SET_ACTUATOR_CONTROL_TARGET
and SET_ATTITUDE_TARGET from the ground station at 250 Hz each, a heartbeat
each way at 1 Hz and a parameter list; frames are encoded with pymavlink and
written with :class:`mrft_gcs.logs.TlogWriter`. Then times
:func:`mrft_gcs.logs.read_log` (best of ``--repeat``) and reports file size,
frame count, seconds, frames per second and peak memory (tracemalloc, the
Python heap; the file's bytes are part of it).

    .venv/bin/python benchmarks/read_tlog.py [--minutes 10] [--rate-hz 250] [--repeat 3]
"""

from __future__ import annotations

import argparse
import math
import platform
import tempfile
import time
import tracemalloc
from pathlib import Path

from mrft_gcs.logs import TlogWriter, read_log


def generate(path: Path, minutes: float, rate_hz: float) -> int:
    """Write the session's .tlog; return the number of frames."""
    from pymavlink.dialects.v20 import common as mav

    veh = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    gcs = mav.MAVLink(None, srcSystem=255, srcComponent=190)
    t0 = 1_700_000_000.0
    n = int(minutes * 60 * rate_hz)
    dt = 1.0 / rate_hz
    frames = 0
    with TlogWriter(path, overwrite=True) as w:
        for k in range(300):
            msg = veh.param_value_encode(f"PARAM_{k}".encode(), float(k), 9, 300, k)
            w.write(msg.pack(veh), t0)
            frames += 1
        for i in range(n):
            t = i * dt
            boot_ms = int(5000 + t * 1000)
            wall = t0 + t
            r = 0.1 * math.sin(2 * math.pi * 2.0 * t)
            u = 0.1 if r < 0 else -0.1
            att = veh.attitude_encode(boot_ms, r, 0.02, 0.5, 0.1, 0.0, 0.0)
            w.write(att.pack(veh), wall + 0.002)
            w.write(veh.local_position_ned_encode(boot_ms, 0.1, 0.2, -1.5, 0.0, 0.0, 0.0).pack(veh),
                    wall + 0.002)
            w.write(gcs.set_actuator_control_target_encode(
                0, 0, 1, 1, [u, 0.0, 0.0, 0.5, 0, 0, 0, 0]).pack(gcs), wall + 0.001)
            w.write(gcs.set_attitude_target_encode(
                0, 1, 1, 7, [1.0, 0.0, 0.0, 0.0], 0, 0, 0, 0.5).pack(gcs), wall + 0.001)
            frames += 4
            if i % int(rate_hz) == 0:
                w.write(veh.heartbeat_encode(2, 12, 137, 6 << 16, 4, 3).pack(veh), wall)
                w.write(gcs.heartbeat_encode(6, 8, 0, 0, 4, 3).pack(gcs), wall)
                frames += 2
    return frames


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--rate-hz", type=float, default=250.0)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "session.tlog"
        start = time.perf_counter()
        frames = generate(path, args.minutes, args.rate_hz)
        gen_s = time.perf_counter() - start
        size = path.stat().st_size
        times = []
        for _ in range(args.repeat):
            start = time.perf_counter()
            log = read_log(path)
            times.append(time.perf_counter() - start)
        tracemalloc.start()
        read_log(path)
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    best = min(times)
    print(f"machine        {platform.machine()} {platform.python_implementation()} "
          f"{platform.python_version()}")
    print(f"log            {args.minutes:g} min at {args.rate_hz:g} Hz, written in {gen_s:.1f} s")
    print(f"file size      {size / 1e6:.1f} MB")
    print(f"frames         {frames}")
    print(f"decoded        attitude {len(log.attitude)}, position {len(log.position)}, "
          f"actuator {len(log.actuator)}, attitude target {len(log.attitude_target)}, "
          f"params {len(log.params)}, heartbeats {len(log.heartbeats)}")
    print(f"read time      {best:.2f} s (best of {args.repeat}: "
          f"{', '.join(f'{t:.2f}' for t in times)})")
    print(f"throughput     {frames / best / 1e6:.2f} M frames/s, {size / best / 1e6:.0f} MB/s")
    print(f"peak memory    {peak / 1e6:.0f} MB (tracemalloc)")


if __name__ == "__main__":
    main()
