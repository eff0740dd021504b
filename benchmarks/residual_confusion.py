"""Benchmark: residual analysis on relay tests with undeclared effects, and dry-run speed.

Confusion part: relay tests flown on the bundled SITL physics (qdrone, sensor noise on)
with one unmodelled effect switched on at several strengths, plus clean runs. Nothing
tells the analysis which effect is on: it gets the record, the relay settings and a
linear model. The model is the airframe's linear model with its delay calibrated once on
a clean noise-free run (the SITL's discrete physics lags its nominal linear model by about
1 ms; see README), i.e. the model of the clean vehicle. Prints the confusion table,
attribution accuracy over effect runs, false alarms on clean runs and the median residual
reduction when the effect is named. Then, apart from those figures: the dead zone (which an
unbiased relay cannot tell from a saturation), clean runs under a relay with a bias, and
roll runs analysed on the model the bundled classifier identifies from each run (as a live
tune does: that model holds the lag of a sensor filter already).

Speed part: writes a 10-minute .tlog at 250 Hz holding a roll relay test and times
``dry_run`` (read + find relay segments + residual analysis; identification when the
bundled classifiers exist).

    .venv/bin/python benchmarks/residual_confusion.py [--seeds 2] [--clean 10] [--speed-only]
        [--identified-only]
"""

from __future__ import annotations

import argparse
import time
from collections import Counter, defaultdict
from dataclasses import replace

import numpy as np

from mrft_gcs.loops import LoopKind
from mrft_gcs.residual import RelayTest, analyse_residual
from mrft_gcs.residual.effects import ExtraDelay
from mrft_gcs.residual.synth import sitl_relay_record

#: SITL effect -> the library effect it should be attributed to.
EXPECTED = {"input_bias": "input_bias", "extra_delay": "extra_delay",
            "sensor_lpf": "sensor_lpf", "torque_rate_limit": "actuator_rate_limit",
            "motor_saturation": "actuator_saturation", "quadratic_drag": "quadratic_drag",
            "motor_deadzone": "motor_deadzone", "thrust_curve": "thrust_curve"}

#: (loop, SITL effect, strengths)
MATRIX = [
    ("roll", "input_bias", (0.01, 0.02, 0.03)),
    ("roll", "extra_delay", (0.005, 0.01, 0.02)),
    ("roll", "sensor_lpf", (30.0, 15.0, 8.0)),
    ("roll", "torque_rate_limit", (8.0, 4.0, 2.0)),
    ("roll", "motor_deadzone", (0.01, 0.02, 0.04)),
    ("altitude", "motor_saturation", (0.495, 0.485, 0.475)),
    ("altitude", "quadratic_drag", (0.5, 1.0, 2.0)),
    ("altitude", "thrust_curve", (0.6, 0.8, 1.0)),
]

RELAY = {"roll": dict(beta=-0.5, h=0.08, duration_s=8.0),
         "altitude": dict(beta=-0.2, h=0.08, duration_s=20.0)}

#: Runs under a biased relay (roll, relay bias 0.02): (SITL effect, strengths); None = clean.
BIASED = [("motor_deadzone", (0.01, 0.02, 0.04)), (None, (0.0,))]
RELAY_BIAS = 0.02


class _SignedDelay(ExtraDelay):
    def bounds(self, ctx):
        return -0.01, 0.01


def reference_models() -> dict:
    """Linear model per loop with its delay fitted on a clean noise-free run."""
    out = {}
    for loop in RELAY:
        rec = sitl_relay_record(loop, noise=False, **RELAY[loop])
        rep = analyse_residual(rec.model, RelayTest(rec.beta, rec.h), rec.t, rec.u, rec.y,
                               effects=(_SignedDelay(),), floor=0.0, min_reduction=0.0,
                               redesign=False)
        out[loop] = replace(rec.model, tau=rec.model.tau + rep.fits[0].value)
    return out


def run_one(models, loop, effect, value, seed, relay_bias=0.0):
    rec = sitl_relay_record(loop, effects={effect: value} if effect else None, seed=seed,
                            relay_bias=relay_bias, **RELAY[loop])
    kind = LoopKind.ALTITUDE if loop == "altitude" else LoopKind.ATTITUDE
    return analyse_residual(models[loop], RelayTest(rec.beta, rec.h, rec.bias), rec.t, rec.u,
                            rec.y, kind=kind, hover=rec.hover, band=rec.band, redesign=False)


def _line(rep) -> str:
    driven = " ".join(f"{f.name}={f.rms:.4f}" for f in rep.open_loop)
    return (f"{rep.effect or 'none':20s} rms {rep.rms_before:.3f} -> {rep.rms_after:.3f} "
            f"{rep.effect_params} alt={list(rep.alternatives)}"
            + (f" | input-driven: {driven}" if driven else ""))


def confusion(seeds: int, clean: int) -> None:
    t0 = time.perf_counter()
    models = reference_models()
    print("reference models:", {k: {a: round(b, 4) for a, b in v.as_dict().items()}
                                for k, v in models.items()})
    table: dict[str, Counter] = defaultdict(Counter)
    reductions, correct, total = [], 0, 0
    for loop, effect, values in MATRIX:
        for v in values:
            for s in range(seeds):
                rep = run_one(models, loop, effect, v, 100 + s)
                got = rep.effect or "none"
                table[effect][got] += 1
                total += 1
                ok = got == EXPECTED[effect]
                correct += ok
                if rep.effect:
                    reductions.append(rep.reduction)
                print(f"  {loop:8s} {effect:18s} {v:<7g} seed {s}: {_line(rep)}", flush=True)
    alarms, n_clean = 0, 0
    for loop in RELAY:
        for s in range(clean):
            rep = run_one(models, loop, None, 0.0, 500 + s)
            n_clean += 1
            alarms += rep.effect is not None
            table[f"clean ({loop})"][rep.effect or "none"] += 1
            print(f"  {loop:8s} clean seed {s}: {rep.effect or 'none'} rms {rep.rms_before:.3f}",
                  flush=True)
    cols = sorted({c for row in table.values() for c in row})
    print("\nconfusion (rows: effect switched on in the SITL; columns: effect named)")
    print(f"{'':22s}" + "".join(f"{c[:12]:>13s}" for c in cols))
    for row, cnt in table.items():
        print(f"{row:22s}" + "".join(f"{cnt.get(c, 0):13d}" for c in cols))
    print(f"\nattribution accuracy: {correct}/{total} = {correct / total:.0%}")
    print(f"false alarms on clean runs: {alarms}/{n_clean} = {alarms / n_clean:.0%}")
    if reductions:
        print(f"median residual reduction when an effect is named: "
              f"{np.median(reductions):.0%} (n={len(reductions)})")
    named, runs, alarms, n_clean = 0, 0, 0, 0
    print(f"\nroll under a relay with bias {RELAY_BIAS} (not in the figures above)")
    for effect, values in BIASED:
        for v in values:
            for s in range(seeds):
                rep = run_one(models, "roll", effect, v, 300 + s, relay_bias=RELAY_BIAS)
                if effect is None:
                    n_clean += 1
                    alarms += rep.effect is not None
                else:
                    runs += 1
                    named += rep.effect == EXPECTED[effect]
                print(f"  roll     {effect or 'clean':18s} {v:<7g} seed {s}: {_line(rep)}",
                      flush=True)
    print(f"biased relay: dead zone named {named}/{runs}, false alarms {alarms}/{n_clean}")
    print(f"benchmark time {time.perf_counter() - t0:.0f} s")


#: Roll runs whose model is the one the bundled classifier identifies from the run itself,
#: as a live tune hands it over (the relay at the classifier's beta; the identification
#: takes in the lag of whatever the run holds): (SITL effect, strengths); None = clean.
IDENTIFIED = [("sensor_lpf", (10.0, 12.0, 15.0, 30.0)), ("extra_delay", (0.01, 0.02)),
              ("torque_rate_limit", (4.0, 2.0)), ("input_bias", (0.02,)), (None, (0.0,) * 4)]


def identified(seeds: int) -> None:
    """Confusion on identified models (the live condition), roll only."""
    from mrft_gcs.errors import MrftError
    from mrft_gcs.identify import identify, relay_settings

    try:
        beta = relay_settings(LoopKind.ATTITUDE).beta
    except MrftError as err:
        print(f"identified models: skipped ({err})")
        return
    print(f"\nroll, model identified from the run (beta {beta}, h 0.08, 8 s; last 3 cycles)")
    table: dict[str, Counter] = defaultdict(Counter)
    for effect, values in IDENTIFIED:
        for k, v in enumerate(values):
            for s in range(seeds):
                seed = 700 + 10 * k + s
                rec = sitl_relay_record("roll", effects={effect: v} if effect else None,
                                        seed=seed, beta=beta, h=0.08, duration_s=8.0)
                cut = rec.t >= rec.t[-1] - 3.2
                try:
                    ident = identify(LoopKind.ATTITUDE, rec.t[cut], rec.u[cut], rec.y[cut],
                                     beta=beta, h=rec.h)
                except MrftError as err:
                    print(f"  {effect or 'clean':18s} {v:<7g} seed {seed}: not identified ({err})")
                    table[effect or "clean"]["not identified"] += 1
                    continue
                rep = analyse_residual(ident.model, RelayTest(beta, rec.h), rec.t, rec.u, rec.y,
                                       band=rec.band, redesign=False)
                table[effect or "clean"][rep.effect or "none"] += 1
                print(f"  {effect or 'clean':18s} {v:<7g} seed {seed}: {_line(rep)}", flush=True)
    cols = sorted({c for row in table.values() for c in row})
    print(f"{'':22s}" + "".join(f"{c[:12]:>13s}" for c in cols))
    for row, cnt in table.items():
        print(f"{row:22s}" + "".join(f"{cnt.get(c, 0):13d}" for c in cols))


def speed(repeat: int = 3) -> None:
    """Time ``dry_run`` on a 10-minute 250 Hz .tlog holding a roll relay test at the bundled
    classifier's beta (read, pairing, cycle detector, identification, residual analysis on
    the identified model); best of ``repeat``."""
    import tempfile
    from pathlib import Path

    from mrft_gcs.dryrun import dry_run
    from mrft_gcs.errors import MrftError
    from mrft_gcs.loops import Loop
    from mrft_gcs.residual.synth import write_relay_tlog

    try:
        from mrft_gcs.identify import relay_settings

        beta = relay_settings(LoopKind.ATTITUDE).beta
    except MrftError:
        beta = RELAY["roll"]["beta"]
    rec = sitl_relay_record("roll", beta=beta, h=0.12, duration_s=600.0)
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "session.tlog"
        write_relay_tlog(path, "roll", rec.t, rec.u, rec.y)
        times = []
        for _ in range(repeat):
            t0 = time.perf_counter()
            res = dry_run(path, models={Loop.ROLL: rec.model})
            times.append(time.perf_counter() - t0)
    r = res.loops[0] if res.loops else None
    what = "nothing found" if r is None else (
        f"{r.loop.value}: identified {r.identification is not None}, residual "
        f"{'analysed' if r.residual is not None else 'not analysed'}")
    print(f"10-minute .tlog at 250 Hz ({path.name}, {rec.t.size} samples): read + dry-run "
          f"best {min(times):.2f} s of {repeat} ({', '.join(f'{x:.2f}' for x in times)}); "
          f"{what}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--clean", type=int, default=10)
    ap.add_argument("--speed-only", action="store_true")
    ap.add_argument("--identified-only", action="store_true",
                    help="only the runs on identified models (the live condition)")
    a = ap.parse_args()
    if a.identified_only:
        identified(a.seeds)
        return
    if not a.speed_only:
        confusion(a.seeds, a.clean)
        identified(a.seeds)
    speed()


if __name__ == "__main__":
    main()
