"""``mrft-tune fleet FLEET.toml``: tune several vehicles: one live table, one summary, one JSON."""

from __future__ import annotations

import json
import math
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.live import Live
from rich.table import Table
from rich.text import Text

from mrft_gcs.cli.app import DECLINED, app, console, err_console, styled
from mrft_gcs.errors import FleetError
from mrft_gcs.fleet import FleetResult, FleetSpec, VehicleOutcome, load_fleet, tune_fleet
from mrft_gcs.loops import Loop

__all__ = ["fleet", "FleetBoard", "status_table", "summary_table"]

_LOOP_ORDER = (Loop.ALTITUDE, Loop.ROLL, Loop.PITCH, Loop.X, Loop.Y)
_SHORT = {"waiting": "-", "oscillating": "osc", "identifying": "ident", "tuned": "tuned",
          "left alone": "left"}


@dataclass
class _Row:
    phase: str = "waiting"
    loops: dict[Loop, str] = field(default_factory=dict)  # plain text (consoles have no markup)
    started: float | None = None
    ended: float | None = None
    outcome: VehicleOutcome | None = None


class FleetBoard:
    """What the live table shows, fed by :func:`mrft_gcs.fleet.tune_fleet`'s ``on_status``.

    ``update`` only stores (it runs in a vehicle's tune thread, next to its setpoint
    stream); the table is built by the display's own refresh (:func:`status_table`).
    """

    def __init__(self, spec: FleetSpec) -> None:
        self.rows = {v.name: _Row() for v in spec.vehicles}
        self._lock = threading.Lock()

    def update(self, name: str, event: Any) -> None:
        with self._lock:
            row = self.rows[name]
            if isinstance(event, VehicleOutcome):
                row.outcome, row.ended = event, time.monotonic()
            elif isinstance(event, dict):
                phase = event.get("phase")
                row.phase = str(getattr(phase, "value", phase))
                for lp, st in event.get("loops", {}).items():
                    state, cycles = st[0], st[1]
                    text = _SHORT.get(getattr(state, "value", str(state)), str(state))
                    row.loops[lp] = f"{text} {cycles}" if text == "osc" else text
            elif event == "started":
                row.started, row.phase = time.monotonic(), "connecting"

    def snapshot(self) -> dict[str, _Row]:
        with self._lock:
            return {n: _Row(r.phase, dict(r.loops), r.started, r.ended, r.outcome)
                    for n, r in self.rows.items()}


def _loop_cell(text: str) -> Text | str:
    return styled(text, "green") if text == "tuned" else text


def status_table(board: FleetBoard) -> Table:
    """Live view: per vehicle its phase, each loop's state, elapsed time and outcome."""
    t = Table(title="fleet (live)")
    for col in ("vehicle", "phase", *(lp.value for lp in _LOOP_ORDER), "elapsed (s)", "result"):
        t.add_column(col)
    now = time.monotonic()
    for name, r in board.snapshot().items():
        elapsed = "-" if r.started is None else f"{(r.ended or now) - r.started:.0f}"
        result: str | Text
        if r.outcome is None:
            result = "" if r.started is None else "running"
        else:
            result = styled("ok", "green") if r.outcome.ok else styled(r.outcome.status, "red")
        t.add_row(name, r.phase, *(_loop_cell(r.loops.get(lp, "-")) for lp in _LOOP_ORDER),
                  elapsed, result)
    return t


def _loops_tuned(v: VehicleOutcome) -> str:
    loops = getattr(v.result, "loops", None) or {}
    done = sum(1 for lr in loops.values() if getattr(lr, "state", "") == "tuned")
    return f"{done}/{len(loops)}" if loops else "-"


def summary_table(res: FleetResult) -> Table:
    """Final table: one row per vehicle, its outcome, loops tuned and parameters written."""
    t = Table(title=f"fleet: {len(res.vehicles) - len(res.failed)} of {len(res.vehicles)} ok "
                    f"in {res.duration_s:.0f} s ({'serial' if res.serial else 'concurrent'})")
    for col in ("vehicle", "connection", "status", "exit", "time (s)", "tune (s)",
                "loops tuned", "parameters written", "error"):
        t.add_column(col, overflow="fold")
    for v in res.vehicles:
        tune_s = getattr(v.result, "duration_s", math.nan)
        t.add_row(v.name, v.connect, styled(v.status, "green" if v.ok else "red"),
                  str(v.exit_code), f"{v.duration_s:.0f}",
                  f"{tune_s:.1f}" if math.isfinite(tune_s) else "-", _loops_tuned(v),
                  str(len(getattr(v.result, "parameters", ()) or ())), v.error or "")
    return t


@app.command()
def fleet(
    fleet_file: Annotated[Path, typer.Argument(help="fleet TOML (see README 'Fleet')")],
    serial: Annotated[bool, typer.Option("--serial", help="one vehicle after the other")] = False,
    json_out: Annotated[Path, typer.Option("--json", help="one JSON with every report")] = Path(
        "fleet-report.json"),
    yes: Annotated[bool, typer.Option("--yes", "-y", help="do not ask before take-off")] = False,
) -> None:
    """Tune every vehicle of a fleet file; exit code 8 if any failed.

    Example:  mrft-tune fleet fleet.toml --json fleet.json --yes
    """
    spec = load_fleet(fleet_file)
    flying = [v.name for v in spec.vehicles if not v.dry_link]
    if flying and not yes:
        console.print(f"{len(flying)} vehicle(s) will arm, take off and oscillate on purpose "
                      f"({', '.join(flying)}). Clear the areas.")
        if not typer.confirm("take off and tune?"):
            err_console.print("nothing done")
            raise typer.Exit(DECLINED)
    board = FleetBoard(spec)
    with Live(console=console, refresh_per_second=4, transient=True,
              get_renderable=lambda: status_table(board)):
        res = tune_fleet(spec, serial=serial, on_status=board.update)
    console.print(summary_table(res))
    json_out.write_text(json.dumps(res.as_dict(), indent=2, allow_nan=False) + "\n",
                        encoding="utf-8")
    console.print(f"fleet report written to {json_out}")
    if res.failed:
        raise FleetError(f"{len(res.failed)} of {len(res.vehicles)} vehicles failed: "
                         + ", ".join(f"{v.name} (exit {v.exit_code})" for v in res.failed)
                         + f" (details in {json_out})")
