"""``mrft-tune tune``: take off, relay-test, identify, write the gains, hover (live display)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated

import typer
from rich.live import Live
from rich.table import Table

from mrft_gcs.cli.app import DECLINED, app, console, err_console, heartbeat_spinner
from mrft_gcs.errors import MrftError
from mrft_gcs.flight import TuneResult, tune
from mrft_gcs.flight.api import parse_actuation, requested_loops
from mrft_gcs.flight.report import write_report
from mrft_gcs.link import load_signing_key, parse_connection_string
from mrft_gcs.link.latency import CpuWakeLatency
from mrft_gcs.profiles import load_profile

__all__ = ["tune_command", "progress_table", "result_table"]


def _f(x: float, fmt: str = ".3g") -> str:
    return "-" if x is None or not math.isfinite(x) else format(x, fmt)


def progress_table(snap: dict) -> Table:
    """Live view: phase, elapsed, and each loop's oscillation state, period and amplitude."""
    table = Table(title=f"phase: {snap['phase'].value}   elapsed {snap['elapsed_s']:.1f} s   "
                        f"setpoints sent {snap.get('stream_sent', 0)}")
    for col in ("loop", "state", "cycles", "period (s)", "amplitude", "steady"):
        table.add_column(col)
    for lp, (state, cycles, period, amp, steady) in snap["loops"].items():
        table.add_row(lp.value, state.value, str(cycles), _f(period), _f(amp),
                      "yes" if steady else "no")
    return table


def result_table(result: TuneResult) -> Table:
    """Final table: identified models and gains, and loops left alone with the reason."""
    table = Table(title=f"tune {result.status}: {_f(result.duration_s, '.1f')} s from take-off "
                        f"to the last gains ({result.actuation} path)")
    for col in ("loop", "state", "model", "class", "period (s)", "Kc", "Kd", "in the air",
                "note"):
        table.add_column(col, overflow="fold")
    for lp, lr in result.loops.items():
        ident = lr.identification
        model = ", ".join(f"{k} {v:.3g}" for k, v in ident.model.as_dict().items()) if ident \
            else "-"
        check = lr.verification.line() if lr.verification else "-"
        table.add_row(lp.value, lr.state, model, str(ident.class_index) if ident else "-",
                      _f(lr.period_s), _f(lr.gains.Kc) if lr.gains else "-",
                      _f(lr.gains.Kd) if lr.gains else "-", check, lr.note or "")
    if (y := result.yaw) is not None:  # relay-tested on the rate path
        ident = y.identification
        model = ", ".join(f"{k} {v:.3g}" for k, v in ident.model.as_dict().items()) if ident \
            else "-"
        pm = f"PM {y.pm_predicted_deg:.0f} deg predicted" if y.gains else "-"
        table.add_row("yaw", y.state, model, str(ident.class_index) if ident else "-",
                      _f(y.period_s), _f(y.gains.Kc) if y.gains else "-",
                      _f(y.gains.Kd) if y.gains else "-", pm,
                      y.reason or ", ".join(f"{k} {v:.4g}" for k, v in y.written.items()))
    return table


def _write_outputs(result: TuneResult, report: Path | None, plot: Path | None) -> None:
    if report is not None:
        console.print(f"report: {write_report(result, report)}")
    if plot is not None:
        from mrft_gcs.plots import plot_tune

        written = plot_tune(result, plot)
        console.print(f"plot: {written}" if written else
                      f"no plot written to {plot}: no loop reached a relay test")


@app.command("tune")
def tune_command(
    connect: Annotated[str, typer.Option("--connect", "-c", help="udp:HOST:PORT, udpin:, "
                                         "udpout:, tcp:HOST:PORT, tcpin:, or a serial device")],
    profile: Annotated[str, typer.Option("--profile", "-p", help="px4, ardupilot, sitl or a "
                                         ".toml path")] = "px4",
    actuation: Annotated[str | None, typer.Option(
        "--actuation", help="torque (SET_ACTUATOR_CONTROL_TARGET, PX4 <= 1.13, SITL), "
        "attitude (SET_ATTITUDE_TARGET) or rate (ArduCopter: body rates through its rate loop "
        "reduced to feed-forward, all five loops; docs/ardupilot.md); default from the "
        "profile")] = None,
    loops: Annotated[str | None, typer.Option(
        "--loops", help="comma-separated loops to tune (altitude, roll, pitch, x, y); default "
        "all the path can tune. Loops not named are never written; x/y not named are not "
        "relay-tested (held in place, left alone: 'not requested'); roll, pitch (torque path) "
        "and altitude are still flown and identified, since the ground station flies the "
        "vehicle with them, but written only if named. Roll/pitch on the attitude path is an "
        "error")] = None,
    yes: Annotated[bool, typer.Option("--yes", "-y", help="do not ask before take-off")] = False,
    report: Annotated[Path | None, typer.Option("--report", help="write the JSON report")] = None,
    plot: Annotated[Path | None, typer.Option(
        "--plot", help="PNG: per loop the relay cycles, the predicted step response and the "
        "open-loop Bode plot of the written gains with their margins")] = None,
    dry_link: Annotated[bool, typer.Option("--dry-link", help="connect and check the link and "
                                           "parameters, never arm")] = False,
    signing_key: Annotated[Path | None, typer.Option(
        "--signing-key", help="MAVLink 2 signing key file (32 bytes, or 64 hex digits)")] = None,
    baud: Annotated[int | None, typer.Option(
    "--baud", help="serial baud rate (default 57600; a relay test needs 460800 or more)")] = None,
    altitude: Annotated[float, typer.Option("--altitude", help="climb set point above take-off, "
                                            "m (the tests run there, or up to 0.3 m lower "
                                            "where a slow climb is braked)")] = 1.0,
    max_tilt: Annotated[float | None, typer.Option("--max-tilt", help="deg (profile default)")]
    = None,
    max_altitude: Annotated[float | None, typer.Option("--max-altitude", help="m")] = None,
    max_distance: Annotated[float | None, typer.Option("--max-distance", help="m from take-off")]
    = None,
    max_duration: Annotated[float | None, typer.Option("--max-duration", help="s of test")]
    = None,
    backup_dir: Annotated[Path, typer.Option("--backup-dir", help="folder for the parameter "
                                             "backup and the .tlog")] = Path("."),
    timeout: Annotated[float, typer.Option("--timeout", help="seconds to wait for a heartbeat")]
    = 5.0,
    hold_compare: Annotated[float | None, typer.Option(
        "--hold-compare", min=0.0, metavar="SECONDS",
        help="after the hand-over, hold SECONDS in the position mode (LOITER/POSCTL) on the "
        "written gains, then as long on the values they replaced, and keep the written ones "
        "only if they hold at least as well (altitude spread, drift, throttle saturation, "
        "attitude tracking); else put the old values back and exit 4 saying which figure "
        "was worse. 0 = off; default the profile's (ardupilot: 8, px4 and sitl: off)")] = None,
) -> None:
    """Take off, run the relay tests, identify every loop, write the PD gains, hover.

    Example:  mrft-tune tune --connect udp:127.0.0.1:14540 --profile px4 --report tune.json

    Some loops only:  mrft-tune tune -c udp:127.0.0.1:14540 -p sitl --loops altitude,roll,pitch
    """
    prof = load_profile(profile)
    # checked before anything connects: a typo must not cost a take-off
    wanted = requested_loops(loops, parse_actuation(actuation) if actuation else prof.actuation) \
        if loops is not None else None
    limits = prof.safety.with_overrides(max_tilt_deg=max_tilt, max_altitude_m=max_altitude,
                                        max_distance_m=max_distance,
                                        max_test_duration_s=max_duration)
    parse_connection_string(connect, baud)  # so is a typo here or in the key file
    if signing_key is not None:
        load_signing_key(signing_key)
    CpuWakeLatency()  # and a bad MRFT_CPU_LATENCY_US
    if not (yes or dry_link):
        console.print(f"The vehicle at {connect} will arm, take off to {altitude:g} m and "
                      f"oscillate on purpose (limits: tilt {limits.max_tilt_deg:g} deg, "
                      f"altitude {limits.max_altitude_m:g} m, distance "
                      f"{limits.max_distance_m:g} m). Clear the area.")
        if not typer.confirm("take off and tune?"):
            err_console.print("nothing done")
            raise typer.Exit(DECLINED)
    try:
        with Live(heartbeat_spinner(connect, timeout), console=console, refresh_per_second=8,
                  transient=True) as live:
            result = tune(connect, prof, actuation=actuation, limits=limits, z_ref_m=altitude,
                          dry_link=dry_link, baud=baud, signing_key=signing_key,
                          backup_dir=backup_dir, heartbeat_timeout_s=timeout, loops=wanted,
                          hold_compare_s=hold_compare,
                          on_progress=lambda snap: live.update(progress_table(snap)))
    except MrftError as err:
        if err.partial_result is not None:
            _write_outputs(err.partial_result, report, plot)
        raise
    if result.status == "dry-link":
        console.print(f"link ok: {result.link.line() if result.link else ''}")
        console.print("--dry-link: link and parameters checked; not arming")
        for note in result.notes[1:]:
            console.print(note)
        _write_outputs(result, report, None)
        return
    console.print(result_table(result))
    for note in result.notes:
        console.print(f"note: {note}")
    if result.stream is not None:
        console.print(f"setpoint stream: {result.stream.line()}")
    for c in result.parameters:
        console.print(f"  {c.name}: {c.old:.6g} -> {c.new:.6g}")
    if result.backup:
        console.print(f"parameter backup: {result.backup}  (undo: mrft-tune params restore "
                      f"{result.backup} -c {connect})")
    _write_outputs(result, report, plot)
