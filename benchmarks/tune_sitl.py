"""Benchmark: full tunes of the SITL over loopback UDP, each airframe, several seeds.

Prints per run: simulated time from take-off command to the last gains applied, max tilt,
setpoint rate and p99 jitter, and J (%) of each loop's written gains against the optimal PD
of the airframe's true linear model (x/y: of the true cascade under the attitude gains in
use), with the phase margin on the true process.

    .venv/bin/python benchmarks/tune_sitl.py [--vehicles qdrone,racer250,f550] [--seeds 5]

Identification uses the bundled classifiers (models/). Without them, ``--truth`` runs the
whole flight with the truth identifier of the tests (J is then 0 by construction: only the
timing, tilt and stream figures mean anything).
"""

from __future__ import annotations

import argparse
import platform
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from mrft_gcs.errors import MrftError  # noqa: E402
from mrft_gcs.flight import tune  # noqa: E402
from mrft_gcs.flight.scoring import score_gains  # noqa: E402
from mrft_gcs.loops import Loop, LoopKind  # noqa: E402
from mrft_gcs.profiles import load_profile, params_to_gains  # noqa: E402
from mrft_gcs.sitl import SitlProcess, load_airframe  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--vehicles", default="qdrone,racer250,f550")
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--truth", action="store_true", help="truth identifier (no classifiers)")
    args = ap.parse_args()
    kw = {}
    if args.truth:
        from flight_sim import ALT_RELAY, ATT_RELAY, SIDE_RELAY, truth_identifier

        kw["relay"] = {LoopKind.ATTITUDE: ATT_RELAY, LoopKind.ALTITUDE: ALT_RELAY,
                       LoopKind.SIDE: SIDE_RELAY}
    print(f"machine: {platform.machine()}, {platform.python_implementation()} "
          f"{platform.python_version()}, identifier: {'truth' if args.truth else 'bundled'}")
    prof = load_profile("sitl")
    for vehicle in args.vehicles.split(","):
        models = load_airframe(vehicle).linear_models()
        durations, Js = [], {lp: [] for lp in Loop}
        for seed in range(args.seeds):
            if args.truth:
                ti = truth_identifier(vehicle)
                kw["identifier"] = lambda lp, s, i, ti=ti: ti(lp, s, i)
            with tempfile.TemporaryDirectory() as d, \
                    SitlProcess(vehicle=vehicle, port=None, seed=seed) as sitl:
                try:
                    r = tune(sitl.connection_string, prof, backup_dir=d, **kw)
                except MrftError as err:
                    print(f"{vehicle} seed {seed}: FAILED {err}")
                    continue
            values = {c.name: c.new for c in r.parameters}
            values[prof.altitude.hover_thrust] = load_airframe(vehicle).hover_thrust
            # score what each loop ran with (x/y: their own gains before sharing one set)
            gains = {lp: lr.gains for lp, lr in r.loops.items() if lr.gains is not None}
            written = params_to_gains(prof, {k: v for k, v in values.items()})
            sc = score_gains(models, gains)
            scw = score_gains(models, {**gains, Loop.X: written.get(Loop.X, gains[Loop.X]),
                                       Loop.Y: written.get(Loop.Y, gains[Loop.Y])})
            durations.append(r.duration_s)
            st = r.stream
            line = " ".join(f"{lp.value} {sc[lp].J_pct:5.1f}% (PM {sc[lp].pm_deg:4.1f})"
                            for lp in Loop if lp in sc)
            wx = f"written x/y J {scw[Loop.X].J_pct:.1f}/{scw[Loop.Y].J_pct:.1f}%"
            for lp in Loop:
                if lp in sc:
                    Js[lp].append(sc[lp].J_pct)
            print(f"{vehicle} seed {seed}: {r.duration_s:5.2f} s, tilt {r.max_tilt_deg:4.1f} deg,"
                  f" stream {st.rate_hz_achieved:.1f} Hz p99 jitter {st.jitter_p99_ms:.2f} ms; "
                  f"J {line}; {wx}", flush=True)
        if durations:
            print(f"{vehicle}: duration mean {np.mean(durations):.2f} s max "
                  f"{np.max(durations):.2f} s; J max " +
                  ", ".join(f"{lp.value} {max(v):.1f}%" for lp, v in Js.items() if v))


if __name__ == "__main__":
    main()
