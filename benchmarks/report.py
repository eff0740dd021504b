"""Regenerate the README benchmark table: live tunes of the SITL airframes beside the paper.

Per airframe and seed (``benchmarks/tune_sitl.py``'s ``run_one``): a full tune over
loopback UDP with the bundled classifiers, J of each loop's written gains against the
optimal PD of the airframe's true linear model, then the figure-eight (2 x 1 m, 5.5 s)
flown on the tuned gains with the identified models as feed-forward. Then the Table VI
evaluation (``mrft_gcs.design.evaluate``: random processes of each inner domain, with noise and
bias; normalised / DF / exact gain scaling and the classic relay + describing-function
baseline). The markdown goes to stdout, and with ``--write-readme`` into README.md between
the ``benchmark-table`` markers.

    .venv/bin/python benchmarks/report.py [--seeds 2] [--n 500] [--runs runs.json] \
        [--evaluation eval.json] [--write-readme]

``--runs`` / ``--evaluation`` reuse records saved by an earlier call (``--save DIR`` writes
them) instead of flying / simulating again.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from tune_sitl import run_one  # noqa: E402

from mrft_gcs.loops import LoopKind  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
START, END = "<!-- benchmark-table:start -->", "<!-- benchmark-table:end -->"
LOOPS = ("roll", "pitch", "altitude", "x", "y")
#: the paper's figures (DNN-MRFT, Ayyad et al.): average tune time; Table VI attitude J with
#: exact gain scaling; the largest side-motion J; figure-eight mean error sim / flight
PAPER = {"tune_s": 15.0, "att_J_avg": -1.77, "att_J_max": 7.14, "side_J_max": 15.68,
         "f8_sim_m": 0.023, "f8_flight_m": 0.039}


def _fmt(x, f=".1f", none="-") -> str:
    return none if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, f)


def _stat(vals: list, f: str = ".1f") -> str:
    """``mean / max`` of the finite values, ``unstable`` counted."""
    ok = [v for v in vals if v is not None and math.isfinite(v)]
    bad = len(vals) - len(ok)
    if not ok:
        return f"unstable x{bad}" if bad else "-"
    s = f"{np.mean(ok):{f}} / {np.max(ok):{f}}"
    return s + (f" (+{bad} unstable)" if bad else "")


def tune_table(runs: list[dict]) -> str:
    head = ("| airframe | tunes ok | take-off → last gains (s), mean / max | J roll | J pitch "
            "| J altitude | J x | J y | min PM (deg) | max tilt (deg) | figure-8 mean error (m) "
            "| stream Hz / p99 jitter ms | OS floor p99 / max ms |")
    rows = [head, "|" + "|".join(["---"] * (head.count("|") - 1)) + "|"]
    for v in dict.fromkeys(r["vehicle"] for r in runs):
        rs = [r for r in runs if r["vehicle"] == v]
        ok = [r for r in rs if r.get("status") == "ok"]
        dur = [r["duration_s"] for r in ok]
        js = {lp: [r["loops"][lp].get("J_pct") for r in ok if "loops" in r] for lp in LOOPS}
        pm = [r["loops"][lp].get("pm_deg") for r in ok for lp in LOOPS
              if r["loops"][lp].get("pm_deg") is not None]
        f8 = [r["figure8_mean_m"] for r in ok if "figure8_mean_m" in r]
        tilt = [r["max_tilt_deg"] for r in rs if r.get("max_tilt_deg") is not None]
        hz = [r["stream_hz"] for r in rs if r.get("stream_hz")]
        jit = [r["jitter_p99_ms"] for r in rs if r.get("jitter_p99_ms")]
        fl = [r["os_floor_p99_ms"] for r in rs if r.get("os_floor_p99_ms") is not None]
        flmax = [r["os_floor_max_ms"] for r in rs if r.get("os_floor_max_ms") is not None]
        rows.append(
            f"| {v} (seeds {', '.join(str(r['seed']) for r in rs)}) | {len(ok)}/{len(rs)} | "
            f"{_stat(dur, '.1f')} | " + " | ".join(_stat(js[lp]) for lp in LOOPS) +
            f" | {_fmt(min(pm) if pm else None)} | {_fmt(max(tilt) if tilt else None)} | "
            f"{_stat(f8, '.3f')} | {_fmt(np.mean(hz) if hz else None)} / "
            f"{_fmt(max(jit) if jit else None)} | {_fmt(max(fl) if fl else None)} / "
            f"{_fmt(max(flmax) if flmax else None)} |")
    p = PAPER
    rows.append(f"| paper (DNN-MRFT) | | {p['tune_s']:.0f} (average) | avg {p['att_J_avg']} / "
                f"max {p['att_J_max']} (attitude, Table VI) | | | max {p['side_J_max']} (side) | "
                f"| | | {p['f8_sim_m']} sim / {p['f8_flight_m']} flight | | |")
    return "\n".join(rows)


def _j(x) -> str:
    if x is None:
        return "-"
    return "inf (unstable)" if math.isinf(x) else f"{x:.2f}"


def evaluation_table(evals: list[dict]) -> str:
    head = ("| loop | method | J avg (%) | J p95 (%) | J max (%) | PM avg (deg) | PM min (deg) "
            "| unstable | no cycle |")
    rows = [head, "|---|---|---|---|---|---|---|---|---|"]
    for ev in evals:
        for row in ev["table"]:
            acc = ev.get("accuracy")
            acc_s = f", classifier accuracy {acc:.0%}" if acc is not None and math.isfinite(acc) \
                else ""
            rows.append(f"| {ev['loop']} ({ev['n']} processes{acc_s}) | {row['method']} | "
                        f"{_j(row['J_avg'])} | "
                        f"{_j(row.get('J_p95'))} | {_j(row['J_max'])} | {_fmt(row['PM_avg'])} | "
                        f"{_fmt(row['PM_min'])} | {row['unstable']} | "
                        f"{row.get('no_cycle', '-')} |")
    rows.append(f"| attitude (paper, Table VI) | exact gain | {PAPER['att_J_avg']} | | "
                f"{PAPER['att_J_max']} | | | | |")
    rows.append(f"| side (paper) | exact gain | | | {PAPER['side_J_max']} | | | | |")
    return "\n".join(rows)


def run_evaluations(n: int, seed: int = 1, n_side: int = 0) -> list[dict]:
    """Table VI for attitude and altitude (``n`` processes each) and, if asked, side motion."""
    from mrft_gcs.design import evaluate as ev_mod

    out = []
    jobs = [(k.value, lambda k=k: ev_mod.evaluate(k, n, seed), n)
            for k in (LoopKind.ATTITUDE, LoopKind.ALTITUDE)]
    if n_side > 0 and hasattr(ev_mod, "evaluate_side"):
        jobs.append(("side", lambda: ev_mod.evaluate_side(n_side, seed), n_side))
    for name, job, count in jobs:
        t = time.monotonic()
        ev = job()
        out.append({"loop": name, "n": count, "seed": seed, "accuracy": ev.accuracy,
                    "table": ev.table(), "seconds": time.monotonic() - t})
    return out


def markdown(runs: list[dict], evals: list[dict]) -> str:
    machine = (f"{platform.machine()}, {os.cpu_count()} cores, CPython "
               f"{platform.python_version()}")
    return "\n".join([
        START,
        f"Regenerated by `python benchmarks/report.py` on {time.strftime('%Y-%m-%d')} "
        f"({machine}; SITL at real-time pace on the same machine).",
        "",
        "Live tunes (bundled classifiers; J of the written gains against the optimal PD of the "
        "airframe's true linear models, mean / max over seeds; x/y on the true cascade under "
        "the written attitude gains):",
        "",
        tune_table(runs),
        "",
        "Table VI evaluation (`mrft-tune evaluate`; random processes with noise and relay bias):",
        "",
        evaluation_table(evals) if evals else "(not run)",
        END,
    ])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vehicles", default="qdrone,racer250,f550")
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--n", type=int, default=500, help="processes per Table VI evaluation")
    ap.add_argument("--n-side", type=int, default=200, help="side-motion trials (0: skip)")
    ap.add_argument("--runs", type=Path, help="reuse tune records (JSON list)")
    ap.add_argument("--evaluation", type=Path, help="reuse Table VI records (JSON list)")
    ap.add_argument("--no-figure8", action="store_true")
    ap.add_argument("--floor", action="store_true",
                    help="measure the OS floor during each tune (a bare pacing loop in its own "
                         "process; it adds a process, so the tunes' own figures get a little worse)")
    ap.add_argument("--save", type=Path, help="folder to save runs.json and evaluation.json")
    ap.add_argument("--write-readme", action="store_true")
    args = ap.parse_args()
    if args.runs:
        runs = json.loads(args.runs.read_text())
    else:
        runs = []
        for v in args.vehicles.split(","):
            for seed in range(args.seeds):
                runs.append(run_one(v, seed, figure8=not args.no_figure8, floor=args.floor))
                print(f"# {v} seed {seed}: {runs[-1].get('status')}", file=sys.stderr, flush=True)
    evals = json.loads(args.evaluation.read_text()) if args.evaluation else (
        run_evaluations(args.n, n_side=args.n_side) if args.n > 0 else [])
    if args.save:
        args.save.mkdir(parents=True, exist_ok=True)
        (args.save / "runs.json").write_text(json.dumps(runs, indent=1))
        (args.save / "evaluation.json").write_text(json.dumps(evals, indent=1))
    md = markdown(runs, evals)
    print(md)
    if args.write_readme:
        readme = ROOT / "README.md"
        text = readme.read_text()
        if START in text and END in text:
            a, b = text.index(START), text.index(END) + len(END)
            text = text[:a] + md + text[b:]
        else:
            text = text.rstrip("\n") + "\n\n## Benchmarks\n\n" + md + "\n"
        readme.write_text(text)


if __name__ == "__main__":
    main()
