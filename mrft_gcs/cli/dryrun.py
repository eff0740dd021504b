"""``mrft-tune dry-run LOG``: the identification of a tune on logged telemetry; touches nothing."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from mrft_gcs.cli import app, console
from mrft_gcs.dryrun import DryRunResult, dry_run
from mrft_gcs.errors import MissingDependency, UsageError
from mrft_gcs.loops import Loop

__all__ = ["dry_run_command", "render", "report_dict"]

SCHEMA = "mrft-gcs/dry-run/1"


def _f(x: float | None, fmt: str = ".3g") -> str:
    return "-" if x is None else format(x, fmt)


def render(res: DryRunResult) -> list:
    """Rich renderables of a dry-run result (tables and lines); computes nothing."""
    out: list = []
    if not res.loops:
        out.append(res.explanation())
        return out
    ident = Table(title="identified loops")
    for col in ("loop", "source", "beta", "h", "bias", "period s", "model", "class", "conf.",
                "Kc", "Kd"):
        ident.add_column(col)
    for r in res.loops:
        s, i, g = r.segment, r.identification, r.gains
        model = ", ".join(f"{k}={v:.3g}" for k, v in i.model.as_dict().items()) if i else "-"
        ident.add_row(r.loop.value, s.source, f"{s.beta:+.3f}", f"{s.h:.3g}", f"{s.bias:+.3g}",
                      _f(i.period_s if i else None), model, str(i.class_index) if i else "-",
                      _f(i.confidence if i else None, ".2f"), _f(g.Kc if g else None),
                      _f(g.Kd if g else None))
    out.append(ident)
    resid = Table(title="residual (simulated model under the same relay vs measured cycle)")
    for col in ("loop", "rms before", "period err", "ampl. err", "duty err", "effect",
                "value", "rms after", "gains with effect"):
        resid.add_column(col)
    for r in res.loops:
        rr = r.residual
        if rr is None:
            resid.add_row(r.loop.value, *["-"] * 8)
            continue
        val = ", ".join(f"{k}={v:.4g}" for k, v in rr.effect_params.items()) or "-"
        gains = (f"Kc {rr.gains_model.Kc:.3g}->{rr.gains_with_effect.Kc:.3g}, "
                 f"Kd {rr.gains_model.Kd:.3g}->{rr.gains_with_effect.Kd:.3g}"
                 if rr.gains_model and rr.gains_with_effect else "-")
        b = rr.before
        name = rr.effect or "none"
        if rr.alternatives:
            name += f" (or {', '.join(rr.alternatives)})"
        resid.add_row(r.loop.value, f"{rr.rms_before:.3f}", f"{b.period:+.1%}",
                      f"{b.amplitude:+.1%}", f"{b.duty:+.3f}", name, val,
                      f"{rr.rms_after:.3f}", gains)
    out.append(resid)
    if res.parameters:
        par = Table(title="parameters a tune would write (nothing is written)")
        par.add_column("parameter")
        par.add_column("value")
        for k, v in res.parameters.items():
            par.add_row(k, f"{v:.6g}")
        out.append(par)
    else:
        out.append("no parameters to write: no loop was identified")
    out.append(res.explanation())
    return out


def report_dict(res: DryRunResult, profile: str | None) -> dict:
    """JSON report of a dry-run (the loops part follows SPEC 4.3)."""
    return {
        "schema": SCHEMA,
        "log": res.source,
        "vehicle": {"connection": None, "profile": profile},
        "loops": {r.loop.value: r.as_dict() for r in res.loops},
        "parameters": [{"name": k, "old": None, "new": v} for k, v in res.parameters.items()],
        "status": "ok" if any(r.identification for r in res.loops) else "no_identification",
        "explanation": res.explanation(),
    }


def _plot(res: DryRunResult, path: Path) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as err:  # pragma: no cover - matplotlib is a dependency
        raise MissingDependency("--plot needs matplotlib: pip install matplotlib") from err
    n = max(len(res.loops), 1)
    fig, axes = plt.subplots(n, 1, figsize=(8, 2.6 * n), squeeze=False)
    for ax, r in zip(axes[:, 0], res.loops, strict=False):
        s = r.segment
        ax.plot(s.t - s.t[0], s.y, lw=0.8, label="measured y")
        ax2 = ax.twinx()
        ax2.step(s.t - s.t[0], s.u, where="post", color="gray", lw=0.6, label="relay u")
        title = f"{r.loop.value}: relay from {s.source}, beta {s.beta:+.2f}, h {s.h:.3g}"
        if r.residual:
            title += f"; residual {r.residual.rms_before:.3f}"
            if r.residual.effect:
                title += f" -> {r.residual.rms_after:.3f} with {r.residual.effect}"
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("t (s)")
    if not res.loops:
        axes[0, 0].text(0.5, 0.5, "no relay test found", ha="center")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


@app.command("dry-run")
def dry_run_command(
    log: Annotated[Path, typer.Argument(help="a .tlog, PX4 .ulg, ArduPilot .bin or CSV log")],
    loop: Annotated[list[str] | None, typer.Option(
        "--loop", help="only this loop (roll, pitch, altitude, x, y); repeatable")] = None,
    profile: Annotated[str | None, typer.Option(
        help="autopilot profile for the parameters it would write (px4, ardupilot, sitl or a "
             "path)")] = "px4",
    report: Annotated[Path | None, typer.Option(help="write a JSON report here")] = None,
    plot: Annotated[Path | None, typer.Option(help="write a PNG of the relay tests here")] = None,
    beta: Annotated[float | None, typer.Option(help="the relay's beta (else inferred)")] = None,
    h: Annotated[float | None, typer.Option(help="the relay's amplitude (else from the "
                                                 "levels)")] = None,
) -> None:
    """Identify the relay tests in a log, as a live tune would; print models, residuals and
    the parameter changes it would write. Never opens a link.

    Example:  mrft-tune dry-run session.tlog --loop roll --report dry.json
    """
    try:
        loops = tuple(Loop(x.lower()) for x in loop) if loop else None
    except ValueError:
        raise UsageError(f"--loop must be one of {', '.join(lp.value for lp in Loop)}; "
                         f"got {', '.join(loop or [])}") from None
    prof = None
    if profile:
        from mrft_gcs.profiles import load_profile

        prof = load_profile(profile)
    meta = {k: str(v) for k, v in (("beta", beta), ("h", h)) if v is not None}
    with console.status(f"reading and analysing {log} ..."):
        res = dry_run(log, loops=loops, profile=prof, meta=meta)
    for item in render(res):
        console.print(item, highlight=False)
    if report:
        report.write_text(json.dumps(report_dict(res, profile), indent=2))
        console.print(f"report written to {report}")
    if plot:
        _plot(res, plot)
        console.print(f"plot written to {plot}")
