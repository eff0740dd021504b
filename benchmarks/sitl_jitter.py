"""Jitter of the SITL's 250 Hz ATTITUDE stream as a ground station receives it.

Starts the SITL subprocess in real time, asks for ATTITUDE at 250 Hz, timestamps every
arrival with a monotonic clock on the receiving side and prints p50/p99/max of the period.

Usage:  .venv/bin/python benchmarks/sitl_jitter.py [--seconds 10] [--vehicle qdrone]
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402

from mrft_gcs.sitl import SitlProcess  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--vehicle", default="qdrone")
    ap.add_argument("--hz", type=float, default=250.0)
    args = ap.parse_args()
    with SitlProcess(vehicle=args.vehicle, port=None) as sitl:
        gcs = mavutil.mavlink_connection(sitl.connection_string, source_system=255)
        gcs.recv_match(type="HEARTBEAT", blocking=True, timeout=10)
        gcs.mav.command_long_send(1, 1, mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                  mavutil.mavlink.MAVLINK_MSG_ID_ATTITUDE, 1e6 / args.hz,
                                  0, 0, 0, 0, 0)
        time.sleep(0.5)
        while gcs.recv_match(blocking=False) is not None:
            pass
        wall, sim = [], []
        end = time.monotonic() + args.seconds
        while time.monotonic() < end:
            msg = gcs.recv_match(type="ATTITUDE", blocking=True, timeout=0.1)
            if msg is not None:
                wall.append(time.monotonic())
                sim.append(msg.time_boot_ms)
    period = np.diff(wall) * 1e3
    sim_period = np.diff(sim)
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python "
          f"{platform.python_version()}")
    print(f"ATTITUDE requested {args.hz:.0f} Hz for {args.seconds:.0f} s: received "
          f"{len(wall)} ({len(wall) / args.seconds:.1f} Hz)")
    print(f"arrival period ms: p50 {np.percentile(period, 50):.3f}  p99 "
          f"{np.percentile(period, 99):.3f}  max {period.max():.3f}  "
          f"std {period.std():.3f}")
    print(f"time_boot_ms step: p50 {np.percentile(sim_period, 50):.0f}  "
          f"max {sim_period.max():.0f}  (simulated time stamps)")


if __name__ == "__main__":
    main()
