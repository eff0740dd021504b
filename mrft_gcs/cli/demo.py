"""``mrft-tune demo``: start the bundled SITL, tune it over UDP, fly a step on the gains."""

from __future__ import annotations

import datetime as _dt
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from rich.live import Live
from rich.table import Table

from mrft_gcs.cli.app import app, console, heartbeat_spinner
from mrft_gcs.cli.tune import progress_table, result_table
from mrft_gcs.errors import MrftError
from mrft_gcs.flight import TuneResult, tune
from mrft_gcs.flight.report import write_report
from mrft_gcs.flight.scoring import StepFigures, score_gains, step_figures
from mrft_gcs.sitl import SimVehicle, SitlProcess, load_airframe
from mrft_gcs.sitl.onboard import FlightMode

__all__ = ["demo", "score_table", "step_in_posctl"]


def step_in_posctl(vehicle: str, params: dict[str, float], seed: int = 0, hover_s: float = 3.0,
                   step_m: float = 1.0, step_s: float = 6.0) -> tuple[float, StepFigures]:
    """Hover, then a ``step_m`` north step, in POSCTL on ``params``, on the in-process SITL.

    The MAVLink subset has no position set point in POSCTL (it holds where it was
    entered), so the step is made by starting the same simulated vehicle ``step_m``
    short of its hold point. Returns (hover position RMS in m, step figures).
    """
    v = SimVehicle(load_airframe(vehicle), seed=seed)
    for name, value in params.items():
        v.autopilot.params.set(name, value)
    v.physics.reset((0.0, 0.0, -1.0), airborne=True)
    v.step()
    v.autopilot.arm(True)
    v.autopilot.set_mode(FlightMode.POSCTL)  # holds (0, 0, 1 m up)
    pos = []
    for _ in range(int(hover_s / v.dt)):
        v.step()
        pos.append(v.physics.meas_posv[:3])
    p = np.asarray(pos[len(pos) // 3:])
    hover_rms = float(np.sqrt(np.mean(np.sum((p - [0.0, 0.0, -1.0]) ** 2, axis=1))))
    v.physics.reset((-step_m, 0.0, -1.0), airborne=True)
    t, x = [], []
    for _ in range(int(step_s / v.dt)):
        v.step()
        t.append(v.time_s)
        x.append(v.physics.meas_posv[0])
    return hover_rms, step_figures(np.asarray(t), np.asarray(x), -step_m, 0.0)


def score_table(vehicle: str, result: TuneResult) -> Table:
    """The written gains against the optimal PD of the simulated airframe's true models."""
    gains = {lp: lr.gains for lp, lr in result.loops.items() if lr.gains is not None}
    scores = score_gains(load_airframe(vehicle).linear_models(), gains)
    table = Table(title=f"written gains vs the optimal PD of {vehicle}'s true linear models "
                        "(the SITL knows them; a real vehicle does not)")
    for col in ("loop", "Kc", "Kd", "optimal Kc", "optimal Kd", "J (%)", "phase margin (deg)"):
        table.add_column(col)
    for lp, sc in scores.items():
        table.add_row(lp.value, f"{sc.gains.Kc:.3g}", f"{sc.gains.Kd:.3g}",
                      f"{sc.optimal.Kc:.3g}", f"{sc.optimal.Kd:.3g}",
                      f"{sc.J_pct:.1f}" if sc.stable else "unstable", f"{sc.pm_deg:.1f}")
    return table


@app.command()
def demo(
    vehicle: Annotated[str, typer.Option("--vehicle", help="bundled SITL airframe")] = "qdrone",
    seed: Annotated[int, typer.Option("--seed", help="sensor-noise seed")] = 0,
    out: Annotated[Path | None, typer.Option("--out", help="folder for report, plot, tlog, "
                                             "backup")] = None,
) -> None:
    """Start the bundled simulated vehicle (SITL), tune it end to end over UDP, fly a step.

    Example:  mrft-tune demo
    """
    folder = out or Path(f"mrft-demo-{_dt.datetime.now():%Y%m%d-%H%M%S}")
    folder.mkdir(parents=True, exist_ok=True)
    console.print(f"starting the SITL ({vehicle}) ...")
    with SitlProcess(vehicle=vehicle, port=None, seed=seed) as sitl:
        console.print(f"SITL at {sitl.connection_string}; tuning from the ground")
        try:
            with Live(heartbeat_spinner(sitl.connection_string, 5.0), console=console,
                      refresh_per_second=8, transient=True) as live:
                result = tune(sitl.connection_string, "sitl", backup_dir=folder,
                              tlog_path=folder / "session.tlog",
                              on_progress=lambda snap: live.update(progress_table(snap)))
        except MrftError as err:
            if err.partial_result is not None:
                console.print(f"report: {write_report(err.partial_result, folder / 'report.json')}")
            raise
    console.print(result_table(result))
    for note in result.notes:
        console.print(f"note: {note}")
    console.print(score_table(vehicle, result))
    if result.stream is not None:
        console.print(f"setpoint stream: {result.stream.line()}")
    console.print(f"report: {write_report(result, folder / 'report.json')}")
    written = {c.name: c.new for c in result.parameters}
    hover_rms, f = step_in_posctl(vehicle, written, seed=seed)
    table = Table(title="POSCTL on the written gains (hover, then a 1 m step north)")
    for col in ("hover RMS (m)", "rise 10-90 % (s)", "overshoot (%)", "settling 5 % (s)",
                "steady error (m)"):
        table.add_column(col)
    table.add_row(f"{hover_rms:.3f}", f"{f.rise_time_s:.2f}", f"{f.overshoot_pct:.1f}",
                  f"{f.settling_time_s:.2f}", f"{f.steady_error_m:+.3f}")
    console.print(table)
