"""``mrft-tune verify``: fly the figure-eight on the vehicle's gains and report the error."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape
from rich.progress import Progress
from rich.table import Table

from mrft_gcs.cli.app import app, console, styled
from mrft_gcs.errors import UsageError
from mrft_gcs.verify import VerifyResult, load_models, plot_verify, verify_figure8

#: the paper's Table VII, 2 x 1 m in 5.5 s: mean Euclidean error (m)
PAPER_FIGURES = (("DNN-MRFT, simulation (paper)", 0.023), ("DNN-MRFT, flight (paper)", 0.039),
                 ("Mellinger, hand-tuned (paper)", 0.04))


def parse_size(text: str) -> tuple[float, float]:
    """``"2x1"`` -> ``(2.0, 1.0)`` (metres, W north by H east)."""
    w, sep, h = text.lower().partition("x")
    try:
        size = (float(w), float(h))
    except ValueError:
        size = (float("nan"), float("nan"))
    if not sep or not all(0 < v < 100 for v in size):
        raise UsageError(f"bad --size '{text}': write WxH in metres, e.g. 2x1")
    return size


def _table(r: VerifyResult) -> Table:
    e = r.errors
    t = Table(title=f"figure-eight {r.size_m[0]:g} x {r.size_m[1]:g} m, {r.period_s:g} s, "
                    f"{r.laps} lap(s) measured")
    for col in ("", "mean (m)", "max (m)", "x (m)", "y (m)", "z (m)"):
        t.add_column(col, justify="right" if col else "left")
    t.add_row(styled("this vehicle", "bold"), f"{e.mean_m:.3f}", f"{e.max_m:.3f}",
              *(f"{m:.3f} / {x:.3f}" for m, x in zip(e.axis_mean_m, e.axis_max_m, strict=True)))
    for name, value in PAPER_FIGURES:
        t.add_row(name, f"{value:.3f}", "", "", "", "")
    t.caption = "per axis: mean / max of |error|"
    return t


@app.command()
def verify(
    connect: Annotated[str, typer.Option("--connect", "-c", help="udp:HOST:PORT, udpin:, "
                                         "udpout:, tcp:HOST:PORT, tcpin:, or a serial device")],
    figure8: Annotated[bool, typer.Option(
        "--figure8", help="fly the minimum-snap figure-eight (the only check so far)")] = False,
    size: Annotated[str, typer.Option(help="W x H in metres (W north, H east)")] = "2x1",
    period: Annotated[float, typer.Option(help="seconds per lap")] = 5.5,
    laps: Annotated[int, typer.Option(help="laps measured (after one settling lap)")] = 2,
    settle_laps: Annotated[int, typer.Option(help="unmeasured laps before")] = 1,
    profile: Annotated[str, typer.Option(
        "--profile", "-p", help="autopilot profile: px4, ardupilot, sitl or a .toml path (the "
        "same default as tune)")] = "px4",
    altitude: Annotated[float, typer.Option(help="take-off height of the figure (m)")] = 1.0,
    report: Annotated[Path | None, typer.Option(
        help="tuning report JSON: its loop models give the attitude feed-forward")] = None,
    sitl_models: Annotated[str | None, typer.Option(
        help="use a bundled SITL airframe's true models for the feed-forward (qdrone, ...)")]
    = None,
    plot: Annotated[Path | None, typer.Option(help="write a PNG: top view and time profiles")]
    = None,
    json_out: Annotated[Path | None, typer.Option("--json", help="write the result as JSON")]
    = None,
    hold: Annotated[bool, typer.Option(
        "--hold", help="stay in the position mode at the end instead of landing")] = False,
    timeout: Annotated[float, typer.Option(help="seconds to wait for a heartbeat")] = 5.0,
) -> None:
    """Fly a figure-eight on the vehicle's current gains and report the position error.

    Position and altitude are closed on the ground station with the gains read from the
    vehicle; attitude is flown by the vehicle on its own gains (OFFBOARD, SET_ATTITUDE_TARGET).

    Example:  mrft-tune verify -c udp:127.0.0.1:14540 --figure8 --size 2x1 --plot f8.png
    """
    if not figure8:
        raise UsageError("say which check to fly: --figure8")
    if report and sitl_models:
        raise UsageError("give --report or --sitl-models, not both")
    models = load_models(report) if report else None
    if sitl_models:
        from mrft_gcs.sitl import load_airframe

        models = load_airframe(sitl_models).linear_models()
    with Progress(console=console, transient=True) as bar:
        # verify_figure8 connects first: say so until its first progress report
        task = bar.add_task(f"connecting to {escape(connect)} (heartbeat, up to {timeout:g} s)",
                            total=1.0)
        result = verify_figure8(
            connect, parse_size(size), period, laps, profile, settle_laps=settle_laps,
            altitude_m=altitude, models=models, land=not hold, timeout_s=timeout,
            progress=lambda phase, frac: bar.update(task, completed=frac, description=phase))
    console.print(_table(result))
    console.print(styled(f"how: {result.method}", "dim"))
    console.print(styled(f"feed-forward: {result.feedforward}", "dim"))
    for note in result.notes:
        console.print(f"note: {note}")
    if plot:
        console.print(f"plot written to {plot_verify(result, plot)}")
    if json_out:
        json_out.write_text(json.dumps(result.as_dict(), indent=2) + "\n", encoding="utf-8")
        console.print(f"result written to {json_out}")
