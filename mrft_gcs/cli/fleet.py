"""``mrft-tune fleet FLEET.toml``: tune several vehicles, with one summary and one JSON."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.live import Live
from rich.table import Table

from mrft_gcs.cli import app, console
from mrft_gcs.errors import FleetError
from mrft_gcs.fleet import FleetResult, load_fleet, tune_fleet


def _status_table(state: dict[str, str]) -> Table:
    t = Table(title="fleet")
    t.add_column("vehicle")
    t.add_column("status")
    for name, status in state.items():
        t.add_row(name, status)
    return t


def _summary(res: FleetResult) -> Table:
    t = Table(title=f"fleet: {len(res.vehicles) - len(res.failed)} of {len(res.vehicles)} ok "
                    f"in {res.duration_s:.0f} s ({'serial' if res.serial else 'concurrent'})")
    for col in ("vehicle", "connection", "status", "time (s)", "gains written", "error"):
        t.add_column(col)
    for v in res.vehicles:
        n = len(getattr(v.result, "parameters", ()) or ())
        t.add_row(v.name, v.connect, "[green]ok[/]" if v.ok else f"[red]{v.status}[/]",
                  f"{v.duration_s:.0f}", str(n), v.error or "")
    return t


@app.command()
def fleet(
    fleet_file: Annotated[Path, typer.Argument(help="fleet TOML (see README 'Fleet')")],
    serial: Annotated[bool, typer.Option("--serial", help="one vehicle after the other")] = False,
    json_out: Annotated[Path, typer.Option("--json", help="one JSON with every report")] = Path(
        "fleet-report.json"),
) -> None:
    """Tune every vehicle of a fleet file; exit code 8 if any failed.

    Example:  mrft-tune fleet fleet.toml --json fleet.json
    """
    spec = load_fleet(fleet_file)
    state = {v.name: "waiting" for v in spec.vehicles}
    with Live(_status_table(state), console=console, refresh_per_second=4,
              transient=True) as live:
        def on_status(name: str, event: Any) -> None:
            if isinstance(event, dict):
                state[name] = str(event.get("phase", "flying"))
            else:
                state[name] = str(event)
            live.update(_status_table(state))

        res = tune_fleet(spec, serial=serial, on_status=on_status)
    console.print(_summary(res))
    json_out.write_text(json.dumps(res.as_dict(), indent=2) + "\n", encoding="utf-8")
    console.print(f"fleet report written to {json_out}")
    if res.failed:
        raise FleetError(f"{len(res.failed)} of {len(res.vehicles)} vehicles failed: "
                         + ", ".join(v.name for v in res.failed) + f" (details in {json_out})")
