"""``mrft-tune design ...`` and ``mrft-tune evaluate``: the offline pipeline behind ``models/``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from mrft_gcs.cli.app import app, console
from mrft_gcs.errors import UsageError
from mrft_gcs.loops import LoopKind

design_app = typer.Typer(
    help="Offline design: optimal PD, discretisation, distinguishing phase, zeta, classifiers.\n\n"
    "Steps run in order per loop and write models/<loop>/; e.g.\n\n"
    "  mrft-tune design discretize --loop attitude\n\n"
    "  mrft-tune design phase --loop attitude\n\n"
    "  mrft-tune design zeta --loop attitude\n\n"
    "  mrft-tune design dataset --loop attitude\n\n"
    "  mrft-tune design train --loop attitude   (needs pip install -e '.[design]')",
    no_args_is_help=True,
    rich_markup_mode=None,  # as the app's: brackets in help are text
)
app.add_typer(design_app, name="design")

LoopOpt = Annotated[str, typer.Option("--loop", help="attitude | altitude | side")]
ModelsOpt = Annotated[Path | None, typer.Option("--models",
                                                help="models folder (default: bundled)")]


def _kind(loop: str) -> LoopKind:
    try:
        return LoopKind(loop)
    except ValueError:
        raise UsageError(f"unknown --loop '{loop}': use attitude, altitude or side") from None


def _side_design_only(models: Path | None) -> None:
    """Side motion: classes, phase and zeta come out of one step per attitude shape."""
    from mrft_gcs.design.pipeline import step_side

    with console.status("side classes, distinguishing phase and zeta per attitude shape"):
        infos = step_side(_models(models), train=False)
    for i in infos:
        console.print(f"attitude shape {i['shape']}: {i['classes']} side classes, beta "
                      f"{i['beta']:.2f}, zeta {i['zeta_min']:.3f}-{i['zeta_max']:.3f}")


def _models(models: Path | None) -> Path:
    from mrft_gcs.design.pipeline import MODELS_DIR

    return models or MODELS_DIR


def _progress() -> Progress:
    return Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/"
                    "{task.total}"), TimeElapsedColumn(), console=console, transient=True)


@design_app.command("pd")
def pd_cmd(
    K: Annotated[float, typer.Option("--K", help="process gain")] = 1.0,
    T_prop: Annotated[float, typer.Option("--T-prop", help="propulsion time constant (s)")] = 0.05,
    T1: Annotated[float, typer.Option("--T1", help="drag time constant (s)")] = 0.5,
    tau: Annotated[float, typer.Option("--tau", help="delay (s)")] = 0.01,
    loop: LoopOpt = "attitude",
    as_json: Annotated[bool, typer.Option("--json", help="print JSON only")] = False,
) -> None:
    """Optimal PD (ISE, phase margin >= 20 deg) for one inner-loop process.

    Example:  mrft-tune design pd --loop attitude --K 2 --T-prop 0.05 --T1 0.5 --tau 0.01
    """
    from mrft_gcs.pd_design import frequency_grid, optimal_pd
    from mrft_gcs.plant import inner_response

    kind = _kind(loop)
    if kind is LoopKind.SIDE:
        raise UsageError("design pd takes an inner-loop process (attitude or altitude)")
    if min(T_prop, T1) <= 0 or tau < 0 or K <= 0:
        raise UsageError("K, T-prop and T1 must be positive and tau non-negative")
    w = frequency_grid(T_prop, T1, tau, n=1500)
    d = optimal_pd(inner_response(1.0, T_prop, T1, tau, w)[0], w)
    out = {"loop": kind.value, "model": {"K": K, "T_prop": T_prop, "T1": T1, "tau": tau},
           **d.as_dict(), "Kc": d.pd.Kc / K, "Kd": d.pd.Kd / K, "ise": d.ise}
    if as_json:
        console.print_json(json.dumps(out))
        return
    t = Table(title=f"Optimal PD for K e^(-{tau} s)/(s({T_prop} s+1)({T1} s+1)), K={K}")
    for k in ("Kc", "Kd", "ise", "pm_deg", "gm_db", "wc_rad_s"):
        t.add_row(k, f"{out[k]:.6g}")
    console.print(t)


@design_app.command("discretize")
def discretize_cmd(loop: LoopOpt = "attitude", J_target: Annotated[float, typer.Option(
        "--J-target", help="adjacent joint cost, %")] = 10.0, grid: Annotated[int, typer.Option(
        help="candidate shapes per chart axis")] = 16, models: ModelsOpt = None) -> None:
    """Discretise the domain into representative processes (writes discretisation.json).

    For --loop side this runs Algorithm 3 (classes, phase and zeta per attitude shape).
    """
    from mrft_gcs.design.pipeline import step_discretize

    if _kind(loop) is LoopKind.SIDE:
        return _side_design_only(models)

    with _progress() as p:
        task = p.add_task("discretising", total=None)
        d = step_discretize(_kind(loop), _models(models), J_target, grid_n=grid,
                            progress=lambda a, b, what: p.update(task, completed=a, total=b,
                                                                description=what))
    fin = d.adjacent_J[np.isfinite(d.adjacent_J)]
    console.print(f"{len(d.shapes)} representative shapes, {len(d.reps)} representative "
                  f"processes from {d.candidates} candidates in {d.seconds:.0f} s; adjacent joint "
                  f"cost median {np.median(fin):.1f} % (10-90 %: {np.percentile(fin, 10):.1f}-"
                  f"{np.percentile(fin, 90):.1f} %)")


@design_app.command("phase")
def phase_cmd(loop: LoopOpt = "attitude", models: ModelsOpt = None) -> None:
    """Distinguishing phase by Algorithm 1 (writes phase.json); side: see 'design side'."""
    from mrft_gcs.design.pipeline import step_phase

    if _kind(loop) is LoopKind.SIDE:
        return _side_design_only(models)

    with console.status("simulating MRFT cycles and searching tuning rules"):
        out = step_phase(_kind(loop), _models(models))
    console.print(f"distinguishing beta = {out['beta']} (phase {out['phase_deg']:.1f} deg), worst "
                  f"deterioration of the best rule {min(out['worst_J']):.2f} %")


@design_app.command("zeta")
def zeta_cmd(loop: LoopOpt = "attitude", models: ModelsOpt = None) -> None:
    """Exact gain scaling table zeta (writes zeta.json); side: see 'design side'."""
    from mrft_gcs.design.pipeline import step_zeta

    if _kind(loop) is LoopKind.SIDE:
        return _side_design_only(models)

    with console.status("simulating unit cycles"):
        out = step_zeta(_kind(loop), _models(models))
    z = np.asarray(out["zeta"])
    console.print(f"zeta {z.min():.4f} .. {z.max():.4f} (describing function: 4/pi = "
                  f"{4 / np.pi:.4f})")


@design_app.command("dataset")
def dataset_cmd(loop: LoopOpt = "attitude", n_train: int = 6000, n_val: int = 2000, seed: int = 0,
                models: ModelsOpt = None) -> None:
    """Simulated training and validation sets (noise, bias up to h/2)."""
    from mrft_gcs.design.pipeline import step_dataset

    with _progress() as p:
        task = p.add_task("simulating", total=n_train + n_val)
        done = [0]

        def prog(a, b):
            p.update(task, completed=min(done[0] + a, n_train + n_val))
            if a == b:
                done[0] += b

        tr, va = step_dataset(_kind(loop), _models(models), n_train, n_val, seed, progress=prog)
    console.print(f"{len(tr)} training and {len(va)} validation rows")


@design_app.command("train")
def train_cmd(loop: LoopOpt = "attitude", epochs: int = 60, seed: int = 0,
              models: ModelsOpt = None) -> None:
    """Train the classifier, export ONNX and the class table (needs the design extra)."""
    from mrft_gcs.design.pipeline import step_train

    with _progress() as p:
        task = p.add_task("architecture search", total=None)
        info = step_train(_kind(loop), _models(models), seed, epochs,
                          progress=lambda a, b: p.update(task, completed=a, total=b))
    console.print(f"chose {info['config']}: validation accuracy {info['val_accuracy']:.3f}, mean "
                  f"J of the chosen class {info['val_mean_J']:.1f} %, {info['seconds']:.0f} s")


@app.command("evaluate")
def evaluate_cmd(
    loop: LoopOpt = "attitude",
    n: Annotated[int, typer.Option("--n", help="random processes")] = 500,
    seed: int = 1,
    json_out: Annotated[Path | None, typer.Option("--json", help="write the table as JSON")] = None,
    worst: Annotated[int, typer.Option(
        help="also list this many worst trials (exact gain): true and fitted model, J, PM")] = 0,
) -> None:
    """Table VI: J and phase margin over random processes, for each gain scaling and the baseline.

    Example:  mrft-tune evaluate --loop attitude --n 500 --worst 10
    """
    from mrft_gcs.design.evaluate import evaluate, evaluate_side

    kind = _kind(loop)
    with _progress() as p:
        task = p.add_task("identifying", total=n)
        prog = lambda a, b: p.update(task, completed=a)  # noqa: E731
        ev = (evaluate_side(n, seed, prog) if kind is LoopKind.SIDE
              else evaluate(kind, n, seed, prog))
    acc = "" if np.isnan(ev.accuracy) else f", classifier accuracy {ev.accuracy:.1%}"
    t = Table(title=f"{ev.kind}: {n} random processes (seed {seed}){acc}")
    for col in ("method", "J avg %", "J p95 %", "J max %", "PM avg", "PM min", "unstable",
                "no cycle"):
        t.add_column(col)
    for row in ev.table():
        t.add_row(row["method"], f"{row['J_avg']:.2f}", f"{row['J_p95']:.2f}",
                  f"{row['J_max']:.2f}", f"{row['PM_avg']:.1f}", f"{row['PM_min']:.1f}",
                  str(row["unstable"]), str(row["no_cycle"]))
    console.print(t)
    if worst > 0:
        w = Table(title=f"{ev.kind}: worst {worst} trials, exact gain")
        for col in ("trial", "J %", "PM", "true", "fitted", "noise", "bias / h"):
            w.add_column(col)
        for tr in ev.worst(worst):
            w.add_row(str(tr.index), f"{tr.J:.2f}", f"{tr.pm_deg:.1f}", _model_text(tr.true),
                      _model_text(tr.fitted), f"{tr.noise:.2%}", f"{tr.bias:+.2f}")
        console.print(w)
    if json_out:
        out = {"loop": ev.kind, "n": n, "seed": seed, "accuracy": ev.accuracy,
               "table": ev.table()}
        if worst > 0:
            out["worst"] = [tr.as_dict() for tr in ev.worst(worst)]
        json_out.write_text(json.dumps(out, indent=2))


def _model_text(m: dict) -> str:
    """``K 1.2 T_prop 0.031 ...`` with the attitude model of a side trial in brackets."""
    main = " ".join(f"{k} {v:.3g}" for k, v in m.items() if k != "attitude")
    return main + (f" [att {' '.join(f'{v:.3g}' for v in m['attitude'])}]" if "attitude" in m
                   else "")


@design_app.command("side")
def side_cmd(
    grid: Annotated[int, typer.Option(help="side candidates per axis")] = 6,
    rows: Annotated[int, typer.Option(help="training rows per attitude shape")] = 900,
    seed: int = 0,
    workers: Annotated[int, typer.Option(help="local worker processes")] = 1,
    dask: Annotated[str | None, typer.Option(help="Dask scheduler address, e.g. tcp://host:8786")]
    = None,
    no_train: Annotated[bool, typer.Option("--no-train", help="classes, phase, zeta only")] = False,
    models: ModelsOpt = None,
) -> None:
    """Side motion (Algorithm 3): per attitude shape, side classes, phase, zeta and classifier.

    Example:  mrft-tune design side --workers 2
    """
    from mrft_gcs.design.pipeline import step_side

    with console.status("designing side classes for every attitude shape"):
        infos = step_side(_models(models), grid, rows, seed, workers, dask, not no_train)
    t = Table(title="side motion per attitude shape")
    for col in ("shape", "classes", "beta", "worst J %", "zeta", "val acc"):
        t.add_column(col)
    for i in infos:
        t.add_row(str(i["shape"]), str(i["classes"]), f"{i['beta']:.2f}", f"{i['worst_J']:.1f}",
                  f"{i['zeta_min']:.3f}-{i['zeta_max']:.3f}", f"{i.get('val_accuracy', 0):.2f}")
    console.print(t)
