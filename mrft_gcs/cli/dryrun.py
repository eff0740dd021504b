"""``mrft-tune dry-run LOG``: the identification of a tune on logged telemetry; touches nothing."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from mrft_gcs.cli.app import app, console, err_console, styled
from mrft_gcs.dryrun import DryRunResult, dry_run
from mrft_gcs.errors import IdentificationError, UsageError
from mrft_gcs.loops import Loop

__all__ = ["dry_run_command", "render", "report_dict", "outcome_error"]

SCHEMA = "mrft-gcs/dry-run/1"
#: what "written" means in dry-run's tables (dry-run itself writes nothing)
WRITTEN_CAPTION = "written: the gains a tune writes (onboard loop, SI units; parameters below)"


def _f(x: float | None, fmt: str = ".3g") -> str:
    return "-" if x is None else format(x, fmt)


def render(res: DryRunResult) -> list:
    """Rich renderables of a dry-run result (tables and lines); computes nothing."""
    out: list = []
    if not res.loops:
        out.append(res.explanation())
        return out
    retargeted = any(r.gains is not None and r.identification is not None
                     and r.gains != r.identification.gains for r in res.loops)
    ident = Table(title="identified loops")
    for col in ("loop", "source", "beta", "h", "bias", "period s", "model", "class", "conf.",
                "written Kc", "written Kd"):
        ident.add_column(col)
    if retargeted:
        ident.add_column("identified Kc, Kd")
    for r in res.loops:
        s, i, g = r.segment, r.identification, r.gains
        model = ", ".join(f"{k}={v:.3g}" for k, v in i.model.as_dict().items()) if i else "-"
        row = [r.loop.value, s.source, f"{s.beta:+.3f}", f"{s.h:.3g}", f"{s.bias:+.3g}",
               _f(i.period_s if i else None), model, str(i.class_index) if i else "-",
               _f(i.confidence if i else None, ".2f"), _f(g.Kc if g else None),
               _f(g.Kd if g else None)]
        if retargeted:
            row.append(f"{i.gains.Kc:.3g}, {i.gains.Kd:.3g}" if i else "-")
        ident.add_row(*row)
    ident.caption = WRITTEN_CAPTION + ("; identified: for the loop as the relay test ran it "
                                       "(through the ground station)" if retargeted else "")
    ident.caption_justify = "left"
    out.append(ident)
    resid = Table(title="residual (simulated model under the same relay vs measured cycle)")
    for col in ("loop", "rms before", "period err", "ampl. err", "duty err", "effect",
                "value", "rms after", "model's optimal PD, without -> with effect"):
        resid.add_column(col)
    resid.caption = ("the last column: what the effect would change in the identified model's "
                     "design; not written (written gains: table above)")
    resid.caption_justify = "left"
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
    """JSON report of a dry-run (the loops part follows README's report schema)."""
    return {
        "schema": SCHEMA,
        "log": res.source,
        "vehicle": {"connection": None, "profile": profile},
        "loops": {r.loop.value: r.as_dict() for r in res.loops},
        "parameters": [{"name": k, "old": None, "new": v} for k, v in res.parameters.items()],
        "status": "ok" if any(r.identification for r in res.loops) else "no_identification",
        "explanation": res.explanation(),
        "warnings": list(res.warnings),
    }


def outcome_error(res: DryRunResult, log: Path) -> IdentificationError | None:
    """The error a dry-run ends with (exit code 6) when it identified nothing, else None."""
    if not res.loops:
        return IdentificationError(f"{log}: no relay test found, nothing identified (the lines "
                                   "above say what the log holds); dry-run needs a log of a "
                                   "tune ('mrft-tune tune' writes a .tlog)")
    if not any(r.identification for r in res.loops):
        return IdentificationError(
            f"{log}: relay tests on {', '.join(r.loop.value for r in res.loops)} but none "
            "identified (see the notes above)")
    return None


@app.command("dry-run")
def dry_run_command(
    log: Annotated[Path, typer.Argument(help="a .tlog, PX4 .ulg, ArduPilot .bin or CSV log")],
    loop: Annotated[list[str] | None, typer.Option(
        "--loop", help="only this loop (roll, pitch, altitude, x, y); repeatable")] = None,
    profile: Annotated[str | None, typer.Option(
        help="autopilot profile for the parameters it would write (px4, ardupilot, sitl or a "
             "path)")] = "px4",
    report: Annotated[Path | None, typer.Option(help="write a JSON report here")] = None,
    json_out: Annotated[bool, typer.Option(
        "--json", help="print the JSON report to stdout instead of the tables (for scripts)")]
    = False,
    plot: Annotated[Path | None, typer.Option(
        help="write a PNG here: per loop the relay test, and the predicted step response and "
             "open-loop Bode plot (with margins) of the gains a tune would write")] = None,
    beta: Annotated[float | None, typer.Option(help="the relay's beta (else inferred)")] = None,
    h: Annotated[float | None, typer.Option(help="the relay's amplitude (else from the "
                                                 "levels)")] = None,
) -> None:
    """Identify the relay tests in a log, as a live tune would; print models, residuals and
    the parameter changes it would write. Never opens a link.

    Exit code 6 when nothing was identified (no relay test in the log, or none identified);
    the report is still written.

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
    with err_console.status(f"reading and analysing {log} ..."):
        res = dry_run(log, loops=loops, profile=prof, meta=meta)
    for warning in res.warnings:  # a log cut short: said, not an error (the rest was used)
        err_console.print(styled(f"warning: {warning}", "yellow"), soft_wrap=True)
    data = report_dict(res, profile)
    if json_out:
        console.print_json(json.dumps(data))
    else:
        for item in render(res):
            console.print(item, highlight=False)
    say = err_console if json_out else console
    if report:
        report.write_text(json.dumps(data, indent=2))
        say.print(f"report written to {report}")
    if plot:
        from mrft_gcs.plots import plot_dry_run

        written = plot_dry_run(res, plot)
        say.print(f"plot written to {written}" if written else
                  f"no plot written to {plot}: no relay test to show")
    error = outcome_error(res, log)
    if error is not None:
        raise error
