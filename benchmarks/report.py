"""Regenerate the README benchmark table: live tunes of the SITL airframes beside the paper.

Per airframe and seed (``benchmarks/tune_sitl.py``'s ``run_one``): a full tune over
loopback UDP with the bundled classifiers, J of each loop's written gains against the
optimal PD of the airframe's true linear model, then the figure-eight (2 x 1 m, 5.5 s)
flown on the tuned gains with the identified models as feed-forward. Then the Table VI
evaluation (``mrft_gcs.design.evaluate``: random processes of each inner domain, with noise and
bias; normalised / DF / exact gain scaling and the classic relay + describing-function
baseline). The markdown goes to stdout, and with ``--write-readme`` a one-table summary
goes into README.md between the ``benchmark-table`` markers and the detailed tables into
docs/benchmarks.md between the ``benchmark-detail`` markers.

    .venv/bin/python benchmarks/report.py [--seeds 2] [--n 500] [--runs runs.json] \
        [--evaluation eval.json] [--write-readme]

``--runs`` / ``--evaluation`` reuse records saved by an earlier call (``--save DIR`` writes
them) instead of flying / simulating again. Where the records were measured is read from
``<runs>.meta.json`` beside them (written by ``--save``), so the tables name the machine
that flew them, not the one that printed them.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import textwrap
import time
from pathlib import Path

import numpy as np

from mrft_gcs.loops import LoopKind

ROOT = Path(__file__).resolve().parents[1]
START, END = "<!-- benchmark-table:start -->", "<!-- benchmark-table:end -->"
DETAIL_START, DETAIL_END = "<!-- benchmark-detail:start -->", "<!-- benchmark-detail:end -->"
DETAIL_PAGE = ROOT / "docs" / "benchmarks.md"
LOOPS = ("roll", "pitch", "altitude", "x", "y")
#: the paper's figures (DNN-MRFT, Ayyad et al.): average tune time; Table VI attitude J with
#: exact gain scaling; the largest side-motion J; figure-eight mean error sim / flight
PAPER = {"tune_s": 15.0, "att_J_avg": -1.77, "att_J_max": 7.14, "att_PM_min": 11.24,
         "side_J_avg": -1.73, "side_J_max": 15.68, "f8_sim_m": 0.023, "f8_flight_m": 0.039}
INNER, SIDE = ("roll", "pitch", "altitude"), ("x", "y")


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
    """Per airframe: tunes completed, time, J per loop, PM, tilt, figure-eight, stream."""
    floor = any(r.get("os_floor_p99_ms") is not None for r in runs)
    head = ("| airframe | tunes ok | take-off → last gains (s), mean / max | J roll | J pitch "
            "| J altitude | J x | J y | min PM (deg) | max tilt (deg) | figure-8 mean error (m) "
            "| stream Hz / p99 jitter ms |" + (" OS floor p99 / max ms |" if floor else ""))
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
            f"| {v} | {len(ok)}/{len(rs)} | "
            f"{_stat(dur, '.1f')} | " + " | ".join(_stat(js[lp]) for lp in LOOPS) +
            f" | {_fmt(min(pm) if pm else None)} | {_fmt(max(tilt) if tilt else None)} | "
            f"{_stat(f8, '.3f')} | {_fmt(np.mean(hz) if hz else None)} / "
            f"{_fmt(max(jit) if jit else None)} |" +
            (f" {_fmt(max(fl) if fl else None)} / {_fmt(max(flmax) if flmax else None)} |"
             if floor else ""))
    p = PAPER
    rows.append(f"| paper (DNN-MRFT) | | {p['tune_s']:.0f} (average) | avg {p['att_J_avg']} / "
                f"max {p['att_J_max']} (attitude, Table VI) | | | max {p['side_J_max']} (side) | "
                f"| | | {p['f8_sim_m']} sim / {p['f8_flight_m']} flight | |" +
                (" |" if floor else ""))
    return "\n".join(rows)


def _finite(vals: list) -> list[float]:
    return [float(v) for v in vals if v is not None and math.isfinite(v)]


def summary_table(runs: list[dict], evals: list[dict]) -> str:
    """README's one table: the live batch and Table VI (exact gain) beside the paper."""
    p = PAPER
    rows = ["| figure | measured | paper |", "|---|---|---|"]
    ok = [r for r in runs if r.get("status") == "ok"]
    if runs:
        per = []
        for v in dict.fromkeys(r["vehicle"] for r in runs):
            rs = [r for r in runs if r["vehicle"] == v]
            d = [r["duration_s"] for r in rs if r.get("status") == "ok"]
            t = f" ({np.mean(d):.1f} / {max(d):.1f} s)" if d else ""
            per.append(f"{v} {sum(r.get('status') == 'ok' for r in rs)}/{len(rs)}{t}")
        rows.append("| live SITL tunes completed (take-off to last gains, mean / max) | "
                    f"{', '.join(per)} | {p['tune_s']:.0f} s average |")

        def loops_row(label: str, loops: tuple[str, ...], paper: str) -> None:
            js = [r["loops"][lp].get("J_pct") for r in ok for lp in loops if "loops" in r]
            pms = _finite([r["loops"][lp].get("pm_deg") for r in ok for lp in loops
                           if "loops" in r])
            unstable = sum(1 for j in js if j is not None and not math.isfinite(j))
            fin = _finite(js)
            j = f"{max(abs(x) for x in fin):.1f}" if fin else "-"
            j += f" ({unstable} unstable)" if unstable else ""
            rows.append(f"| {label}: largest \\|J\\| (%) / smallest PM (deg) | {j} / "
                        f"{_fmt(min(pms) if pms else None)} ({len(js)} loops) | {paper} |")

        loops_row("written roll, pitch, altitude gains", INNER, "")
        loops_row("written x, y gains", SIDE, "")
        tilt = _finite([r.get("max_tilt_deg") for r in runs])
        rows.append(f"| largest tilt in any tune (deg) | {_fmt(max(tilt) if tilt else None)} | |")
        f8 = [f"{v} {np.mean(f):.3f}" for v in dict.fromkeys(r["vehicle"] for r in ok)
              if (f := _finite([r.get("figure8_mean_m") for r in ok if r["vehicle"] == v]))]
        if f8:
            rows.append(f"| figure-eight on the tuned gains, mean error (m) | {', '.join(f8)} | "
                        f"{p['f8_sim_m']} sim, {p['f8_flight_m']} flight |")
        hz = _finite([r.get("stream_hz") for r in runs])
        jit = _finite([r.get("jitter_p99_ms") for r in runs])
        if hz:
            met = sum(1 for r in runs if (r.get("jitter_p99_ms") or math.inf) < 2.0)
            rows.append(f"| setpoint stream: rate (Hz) / p99 jitter (ms) | {min(hz):.1f}-"
                        f"{max(hz):.1f} / {min(jit):.2f}-{max(jit):.2f} (p99 < 2 ms in {met} of "
                        f"{len(runs)}) | |")
    paper = {"attitude": f"avg {p['att_J_avg']} / max {p['att_J_max']}, PM {p['att_PM_min']}",
             "side": f"avg {p['side_J_avg']} / max {p['side_J_max']}"}
    for ev in evals:
        row = next((r for r in ev["table"] if r["method"] == "exact gain"), None)
        if row is None:
            continue
        rows.append(f"| Table VI, {ev['loop']}, {ev['n']} random processes: J avg / max (%), "
                    f"PM min (deg) | {_j(row['J_avg'])} / {_j(row['J_max'])}, "
                    f"{_fmt(row['PM_min'])}; {row['unstable']} unstable, {row.get('no_cycle', '-')}"
                    f" refused | {paper.get(ev['loop'], '')} |")
    base = [(ev["loop"], r) for ev in evals for r in ev["table"] if "baseline" in r["method"]]
    if base:
        rows.append("| Table VI, classic relay + describing-function PD: J max (%) | " +
                    ", ".join(f"{lp} {r['J_max']:.0f}" for lp, r in base) + " | |")
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


def this_machine() -> str:
    """Where this process runs, for records measured now."""
    return (f"{time.strftime('%Y-%m-%d')}, {platform.machine()}, {os.cpu_count()} cores, "
            f"CPython {platform.python_version()}")


def measured_on(runs_path: Path | None) -> str:
    """Where the runs were flown: the ``.meta.json`` beside reused records, else here, now."""
    if runs_path is None:
        return this_machine() + "; SITL at real-time pace on the same machine"
    meta = runs_path.with_suffix(".meta.json")
    if meta.exists():
        return str(json.loads(meta.read_text())["measured_on"])
    return f"a machine {runs_path.name} does not name"


def regenerate_command(runs_path: Path | None, evals_path: Path | None) -> str:
    args = "".join(f" --{k} {v}" for k, v in (("runs", runs_path), ("evaluation", evals_path))
                   if v is not None)
    return f"python benchmarks/report.py{args} --write-readme"


def _wrap(text: str) -> str:
    """A paragraph wrapped as the rest of the page is (100 columns)."""
    return textwrap.fill(text, width=95, break_long_words=False, break_on_hyphens=False)


def markdown(runs: list[dict], evals: list[dict], where: str, command: str) -> str:
    """README's block: the one summary table, the machine, how to regenerate."""
    return "\n".join([
        START,
        _wrap(f"Live tunes measured on {where}. Written by `{command}`; per airframe and per "
              "method in [docs/benchmarks.md](docs/benchmarks.md)."),
        "",
        summary_table(runs, evals),
        END,
    ])


def detail_markdown(runs: list[dict], evals: list[dict], where: str, command: str) -> str:
    """docs/benchmarks.md's block: the live tunes per airframe and the whole Table VI."""
    return "\n".join([
        DETAIL_START,
        _wrap(f"Written by `{command}`. Live tunes measured on {where}."),
        "",
        "Live tunes (J of the written gains, mean / max over the tunes, %):",
        "",
        tune_table(runs) if runs else "(not run)",
        "",
        "Table VI evaluation (`mrft-tune evaluate`):",
        "",
        evaluation_table(evals) if evals else "(not run)",
        DETAIL_END,
    ])


def _replace_block(path: Path, start: str, end: str, block: str) -> None:
    text = path.read_text()
    if start not in text or end not in text:
        raise SystemExit(f"{path}: no {start} ... {end} markers to write between")
    a, b = text.index(start), text.index(end) + len(end)
    path.write_text(text[:a] + block + text[b:])


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
                         "process; it adds a process, so the tunes' own figures get a little "
                         "worse)")
    ap.add_argument("--save", type=Path, help="folder to save runs.json and evaluation.json")
    ap.add_argument("--write-readme", action="store_true")
    args = ap.parse_args()
    if args.runs:
        runs = json.loads(args.runs.read_text())
    else:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from tune_sitl import run_one  # only to fly: the tables alone need no SITL

        runs = []
        for v in args.vehicles.split(","):
            for seed in range(args.seeds):
                runs.append(run_one(v, seed, figure8=not args.no_figure8, floor=args.floor))
                print(f"# {v} seed {seed}: {runs[-1].get('status')}", file=sys.stderr, flush=True)
    evals = json.loads(args.evaluation.read_text()) if args.evaluation else (
        run_evaluations(args.n, n_side=args.n_side) if args.n > 0 else [])
    where = measured_on(args.runs)
    runs_path, evals_path = args.runs, args.evaluation
    if args.save:
        args.save.mkdir(parents=True, exist_ok=True)
        if not args.runs:
            runs_path = args.save / "runs.json"
            runs_path.write_text(json.dumps(runs, indent=1))
            runs_path.with_suffix(".meta.json").write_text(
                json.dumps({"measured_on": where}, indent=1) + "\n")
        if not args.evaluation:
            evals_path = args.save / "evaluation.json"
            evals_path.write_text(json.dumps(evals, indent=1))
    command = regenerate_command(
        *(None if p is None else p.resolve().relative_to(ROOT) if p.resolve().is_relative_to(ROOT)
          else p for p in (runs_path, evals_path)))
    md = markdown(runs, evals, where, command)
    detail = detail_markdown(runs, evals, where, command)
    print(md)
    print()
    print(detail)
    if args.write_readme:
        _replace_block(ROOT / "README.md", START, END, md)
        _replace_block(DETAIL_PAGE, DETAIL_START, DETAIL_END, detail)

if __name__ == "__main__":
    main()
