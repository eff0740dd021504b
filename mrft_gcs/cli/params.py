"""``mrft-tune params ...``: show, back up and restore autopilot parameters."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from mrft_gcs.cli.app import DECLINED, app, console, err_console, heartbeat_wait
from mrft_gcs.errors import UsageError
from mrft_gcs.link import VehicleLink, parse_connection_string
from mrft_gcs.params import ParamClient, WriteResult, read_params_file, write_params_file
from mrft_gcs.profiles import load_profile

params_app = typer.Typer(help="Show, back up and restore autopilot parameters (QGC .params files).",
                         no_args_is_help=True, rich_markup_mode=None)
app.add_typer(params_app, name="params")

Connect = Annotated[str, typer.Option("--connect", "-c", help="udp:HOST:PORT, udpin:, udpout:, "
                                      "tcp:HOST:PORT, tcpin:, or a serial device")]
Baud = Annotated[int | None, typer.Option(
    "--baud", help="serial baud rate (default 57600)")]
SigningKey = Annotated[Path | None, typer.Option(
    "--signing-key", help="MAVLink 2 signing key file (32 bytes, or 64 hex digits)")]
Timeout = Annotated[float, typer.Option("--timeout", help="seconds to wait for a heartbeat")]


def _connect(connect: str, baud: int | None, signing_key: Path | None,
             timeout: float) -> VehicleLink:
    parse_connection_string(connect, baud)  # a typo is one line, not a wait and then an error
    with heartbeat_wait(connect, timeout):
        return VehicleLink.connect(connect, baud=baud, timeout_s=timeout, signing_key=signing_key)


def _changes_table(result: WriteResult, title: str) -> Table:
    table = Table(title=title)
    for col in ("parameter", "before", "after"):
        table.add_column(col)
    for c in result.changes:
        table.add_row(c.name, f"{c.old:.6g}", f"{c.new:.6g}")
    return table


@params_app.command("restore")
def restore(
    backup: Annotated[Path, typer.Argument(help="a .params file written by a tune (or QGC)")],
    connect: Connect,
    baud: Baud = None,
    signing_key: SigningKey = None,
    timeout: Timeout = 5.0,
    yes: Annotated[bool, typer.Option("--yes", "-y", help="do not ask before writing")] = False,
) -> None:
    """Write back the values of a parameter backup (each read back; rolled back on failure).

    The values it replaces are backed up first, next to BACKUP.

    Example:  mrft-tune params restore params-backup-20250101-120000.params -c udp:127.0.0.1:14540
    """
    entries = read_params_file(backup)  # fail on a bad file before touching the link
    with _connect(connect, baud, signing_key, timeout) as link:
        client = ParamClient(link)
        if not yes:
            names = [e.param.name for e in entries]
            current = client.read_many(names)
            table = Table(title=f"restore from {backup}")
            for col in ("parameter", "now", "backup"):
                table.add_column(col)
            for e in entries:
                table.add_row(e.param.name, f"{current[e.param.name].value:.6g}",
                              f"{e.param.value:.6g}")
            console.print(table)
            if not typer.confirm(f"write {len(entries)} parameters to the vehicle?"):
                err_console.print("nothing written")
                raise typer.Exit(DECLINED)
        result = client.restore(backup)
    console.print(_changes_table(result, f"restored from {backup}"))
    console.print(f"values replaced are backed up in {result.backup_path}")


@params_app.command("backup")
def backup(
    connect: Connect,
    out: Annotated[Path, typer.Option("--out", "-o", help="file to write")] = Path(
        "params-backup.params"),
    profile: Annotated[str | None, typer.Option(
        "--profile", help="back up only the parameters this autopilot profile tunes")] = None,
    baud: Baud = None,
    signing_key: SigningKey = None,
    timeout: Timeout = 5.0,
) -> None:
    """Save parameters to a QGroundControl .params file (all of them, or a profile's).

    Example:  mrft-tune params backup -c udp:127.0.0.1:14540 --profile px4 -o before.params
    """
    if out.exists():
        raise UsageError(f"{out} exists: choose another --out (a backup is never overwritten)")
    names = load_profile(profile).parameter_names() if profile else None
    with _connect(connect, baud, signing_key, timeout) as link:
        client = ParamClient(link)
        params = client.read_many(names) if names else client.read_all()
        write_params_file(out, params.values(), link.target_system, link.target_component,
                          stack=link.family.value)
    console.print(f"{len(params)} parameters saved to {out}")


@params_app.command("show")
def show(
    connect: Connect,
    names: Annotated[list[str] | None, typer.Argument(help="parameter names")] = None,
    profile: Annotated[str | None, typer.Option(
        "--profile", help="show the parameters this autopilot profile tunes")] = None,
    baud: Baud = None,
    signing_key: SigningKey = None,
    timeout: Timeout = 5.0,
) -> None:
    """Print parameter values (named ones, a profile's, or all).

    Example:  mrft-tune params show -c udp:127.0.0.1:14540 --profile sitl
    """
    wanted = list(names or []) + (load_profile(profile).parameter_names() if profile else [])
    with _connect(connect, baud, signing_key, timeout) as link:
        client = ParamClient(link)
        params = client.read_many(wanted) if wanted else client.read_all()
    table = Table(title=f"{len(params)} parameters")
    table.add_column("parameter")
    table.add_column("value")
    for p in params.values():
        table.add_row(p.name, f"{p.value:.6g}")
    console.print(table)
