"""``python -m mrft_gcs.sitl``: the SITL executable that :class:`SitlProcess` starts.

Prints one line ``SITL ready: udp:127.0.0.1:PORT`` on stdout once it serves, then runs until
SIGTERM or SIGINT (or, with ``--exit-with-parent``, until the process that started it is
gone). Exit code 2 for bad arguments (one line on stderr).
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading

from mrft_gcs.errors import MrftError
from mrft_gcs.sitl.process import DEFAULT_PORT, READY_PREFIX, SitlConfig, make_server, parse_effects


def _wind(text: str) -> tuple[float, float, float]:
    parts = [float(p) for p in text.split(",")]
    if len(parts) != 3:
        raise argparse.ArgumentTypeError("wind is N,E,D in m/s")
    return (parts[0], parts[1], parts[2])


def _watch_parent(stop, period_s: float = 0.25) -> None:
    """Call ``stop`` once this process is re-parented (its parent exited or was killed)."""
    parent = os.getppid()
    done = threading.Event()

    def watch() -> None:
        while not done.wait(period_s):
            if os.getppid() != parent:
                stop()
                return

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m mrft_gcs.sitl",
                                 description="Simulated multirotor serving MAVLink over UDP.")
    ap.add_argument("--vehicle", default=None,
                    help="profile or TOML path (default qdrone); with --physics rotorpy a "
                         "RotorPy parameter set (default crazyfliebrushless)")
    ap.add_argument("--physics", default="native", choices=("native", "rotorpy"),
                    help="rigid body, rotors and motors: the project's (native) or RotorPy's")
    ap.add_argument("--port", type=int, default=DEFAULT_PORT)
    ap.add_argument("--speedup", type=float, default=1.0)
    ap.add_argument("--effect", action="append", default=[], metavar="NAME=VALUE")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--random", type=int, default=None, metavar="SEED",
                    help="fly the random vehicle of SEED instead of --vehicle")
    ap.add_argument("--signing-key", default=None, metavar="FILE")
    ap.add_argument("--wind", type=_wind, default=(0.0, 0.0, 0.0), metavar="N,E,D")
    ap.add_argument("--exit-with-parent", action="store_true",
                    help="stop when the process that started this one exits")
    args = ap.parse_args(argv)
    try:
        cfg = SitlConfig(vehicle=args.vehicle, port=args.port, speedup=args.speedup,
                         effects=parse_effects(args.effect), seed=args.seed,
                         signing_key_file=args.signing_key, wind_m_s=args.wind,
                         random_seed=args.random, physics=args.physics)
        server = make_server(cfg)
    except (MrftError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    signal.signal(signal.SIGTERM, lambda *_: server.stop())
    signal.signal(signal.SIGINT, lambda *_: server.stop())
    if args.exit_with_parent:
        _watch_parent(server.stop)
    print(f"{READY_PREFIX} {cfg.connection_string}", flush=True)
    try:
        server.serve_forever()
    finally:
        server.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
