"""Tune a real ArduCopter (its own SITL build) and compare LOITER hold before and after.

    python benchmarks/tune_ardupilot.py [--hold-s 10] [--instance N] [--runs 1]
                                        [--baro-noise 0.2] [--gust 4] [--autotune]
                                        [--autotune-axes 3] [--actuation attitude|rate]
                                        [--scripting] [--json PATH]
                                        [--compare JSON [--compare-run N] [--repeats N]
                                         [--config NAME=BASE:P=V,...]]

Starts ArduCopter SITL (:mod:`mrft_gcs.sitl.arducopter`: parameters wiped, an instance of
its own; ``--scripting``: SCR_ENABLE 1, so that the rate path installs its link-loss guard),
then per run:

1. *before*: take off in GUIDED to 1 m, LOITER for ``--hold-s``, land (the firmware's own
   gains);
2. ``tune(profile=--profile, actuation=--actuation)`` (default ``ardupilot`` and its
   attitude path; ``rate``: all five loops through the rate loop reduced to feed-forward,
   :mod:`mrft_gcs.flight.ratepath`, with its zero-gain window) from the ground (time to
   tune, loops written, the hover check after the hand-over to LOITER); land;
3. *after*: the same take-off and LOITER hold on the written gains; land; restore the backup.

Hold quality over the LOITER window, from an observer link (SERIAL2): altitude spread
(max - min) and its standard deviation, largest |climb rate|, largest horizontal distance from
where the hold began, largest tilt, throttle saturation (share of VFR_HUD samples at 0 % or
100 %) and the throttle's standard deviation. ``--baro-noise 0.2`` turns on the SITL's baro
noise for the whole run (tune included); ``--gust 4`` flies both holds in turbulent wind
with an upward component, so that the altitude loop has something to reject (``--gust-in
handover``: also in the tune from its hand-over to LOITER on, the tool's own hold comparison
included; ``all``: the whole run). The hold
after is called worse where altitude spread, its deviation, drift or saturation grew by
more than 20 % (and 5 mm), or roll/pitch followed their target less closely (rms against
ATTITUDE_TARGET interpolated to each ATTITUDE's vehicle time, and its part above 2 Hz, by
more than 20 % and 0.01 deg, per unit of the target's motion too; each hold's ``noise``: how
far its two halves' figures differ, and ``worse_beyond_noise``: the verdict against it);
more lean spent holding position is reported beside it. ``--compare JSON`` flies no tune:
LOITER holds on the values a run of an earlier ``--json`` wrote, split into stock, tuned,
attitude only and position only (``--config`` adds sets), interleaved ``--repeats`` times,
which separates what the attitude and the position gains each do. ``--autotune`` first
flies ArduPilot's own AUTOTUNE of roll and pitch (``--autotune-axes``: AUTOTUNE_AXES 3; 7
adds yaw) from a 3 m LOITER, saved by landing and disarming in AUTOTUNE with the simulated
RC throttle low, holds on its gains the same way, and puts them back before the tool's
runs (``--runs 0``: AUTOTUNE alone). ``--json`` writes every figure, as far as the
benchmark got. The figures and the verdict are the tool's own
(:mod:`mrft_gcs.flight.holdcompare`), which flies the same comparison after its hand-over
(``--hold-compare``, the profile's 8 s by default: its holds go in each run's
``hold_compare``; a tune that reverted gets no *after* hold here).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import signal
import socket
import struct
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from pymavlink import mavutil

from mrft_gcs.errors import MrftError
from mrft_gcs.flight.api import tune
from mrft_gcs.flight.holdcompare import WORSE_SLACK, effort_in, synced_error, worse_in  # noqa: F401
from mrft_gcs.flight.holdcompare import hold_figures as figures_of
from mrft_gcs.link import VehicleLink
from mrft_gcs.params import ParamClient
from mrft_gcs.sitl.arducopter import ArduCopterSitl, free_instance, why_not

GUIDED, LOITER, LAND = 4, 5, 9


class Observer:
    """A second MAVLink link (SERIAL2) that flies the before/after holds and records them."""

    def __init__(self, connection: str) -> None:
        #: SIM_* values set (from this link) once the tune hands over to LOITER (empty: none)
        self.wind_at_handover: dict[str, float] = {}
        self.m = mavutil.mavlink_connection(connection, source_system=254)
        self.m.wait_heartbeat(timeout=10)
        # ATTITUDE, LOCAL_POSITION_NED, VFR_HUD, ATTITUDE_TARGET at 25 Hz
        for msg_id in (30, 32, 74, 83):
            self.command(511, msg_id, 40_000)

    def command(self, cmd: int, *p: float) -> None:
        params = list(p) + [0.0] * (7 - len(p))
        self.m.mav.command_long_send(self.m.target_system, self.m.target_component, cmd, 0,
                                     *params)
        self.m.recv_match(type="COMMAND_ACK", blocking=True, timeout=2)

    def set_params(self, values: dict[str, float]) -> None:
        """PARAM_SET each value from this link (the SITL's SIM_* settings)."""
        for name, value in values.items():
            self.m.mav.param_set_send(self.m.target_system, self.m.target_component,
                                      name.encode(), value, mavutil.mavlink.MAV_PARAM_TYPE_REAL32)
            self.m.recv_match(type="PARAM_VALUE", blocking=True, timeout=2)

    def mode(self, number: int) -> None:
        self.command(176, 1, number)

    def record(self, seconds: float) -> dict[str, np.ndarray]:
        rows: dict[str, list[tuple[float, ...]]] = {"pos": [], "att": [], "thr": [],
                                                    "err": [], "att_t": [], "tgt_t": []}
        target: tuple[float, float] | None = None
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            msg = self.m.recv_match(type=["LOCAL_POSITION_NED", "ATTITUDE", "VFR_HUD",
                                          "ATTITUDE_TARGET"], blocking=True, timeout=0.2)
            if msg is None:
                continue
            kind = msg.get_type()
            if kind == "LOCAL_POSITION_NED":
                rows["pos"].append((msg.x, msg.y, -msg.z, -msg.vz))
            elif kind == "ATTITUDE_TARGET":
                w, x, y, z = msg.q
                target = (math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y)),
                          math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x)))))
                rows["tgt_t"].append((msg.time_boot_ms * 1e-3, *target))
            elif kind == "ATTITUDE":
                rows["att"].append((msg.roll, msg.pitch))
                rows["att_t"].append((msg.time_boot_ms * 1e-3, msg.roll, msg.pitch))
                if target is not None:  # the attitude loop's own error, against its target
                    rows["err"].append((msg.roll - target[0], msg.pitch - target[1]))
            else:
                rows["thr"].append((msg.throttle,))
        return {k: np.asarray(v, float) for k, v in rows.items()}

    def watch_handover(self, stop: threading.Event) -> threading.Thread:
        """Set :attr:`wind_at_handover` when the vehicle is armed in LOITER (the tune's
        hand-over); a thread that runs until ``stop`` or the wind is set."""
        def run() -> None:
            while not stop.is_set():
                msg = self.m.recv_match(type="HEARTBEAT", blocking=True, timeout=0.5)
                if (msg is not None and msg.get_srcSystem() == self.m.target_system
                        and msg.get_srcComponent() == 1 and msg.custom_mode == LOITER
                        and msg.base_mode & 128):
                    break
            else:
                return
            self.set_params(self.wind_at_handover)
            print("wind on at the hand-over to LOITER", flush=True)

        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        return thread

    def height(self) -> float:
        msg = self.m.recv_match(type="LOCAL_POSITION_NED", blocking=True, timeout=2)
        return -msg.z if msg is not None else math.nan

    def armed(self) -> bool:
        msg = self.m.recv_match(type="HEARTBEAT", blocking=True, timeout=2)
        return bool(msg and msg.base_mode & 128)

    def land_and_wait(self, timeout_s: float = 30.0) -> None:
        self.mode(LAND)
        end = time.monotonic() + timeout_s
        while time.monotonic() < end and self.armed():
            time.sleep(0.2)

    def loiter_hold(self, hold_s: float, altitude_m: float = 1.0) -> dict[str, float]:
        """Take off in GUIDED, hold in LOITER, land; the hold's figures."""
        self.mode(GUIDED)
        self.command(400, 1)
        self.command(22, 0, 0, 0, 0, 0, 0, altitude_m)
        end = time.monotonic() + 20
        while time.monotonic() < end and self.height() < 0.9 * altitude_m:
            pass
        time.sleep(2.0)
        self.mode(LOITER)
        data = self.record(hold_s)
        self.land_and_wait()
        f = figures_of(data)  # with the scatter between the hold's halves
        return f.as_dict() | {"noise": dict(f.noise)}


def hold_figures(data: dict[str, np.ndarray]) -> dict[str, float]:
    """The hold's figures (:func:`mrft_gcs.flight.holdcompare.hold_figures`) as a dict."""
    return figures_of(data).as_dict()


def line(name: str, f: dict[str, float]) -> str:
    return (f"{name:7s} alt spread {f['alt_spread_m']:.3f} m (std {f['alt_std_m']:.3f}), "
            f"|climb| <= {f['max_climb_m_s']:.2f} m/s, drift {f['max_drift_m']:.3f} m, tilt "
            f"<= {f['max_tilt_deg']:.1f} deg (std {f['tilt_std_deg']:.2f}, against the target "
            f"{f['att_err_rms_deg']:.2f} rms, synced "
            f"{f.get('att_err_sync_rms_deg', math.nan):.3f}, "
            f"above 2 Hz {f.get('att_err_hf_rms_deg', math.nan):.3f}; target moving "
            f"{f.get('target_rate_rms_deg_s', math.nan):.1f} deg/s rms), throttle saturated "
            f"{100 * f['throttle_saturated']:.0f} % (std {f['throttle_std_pct']:.1f} %)")


#: ArduPilot's attitude gains AUTOTUNE may change (read before and after; the changed are kept)
AUTOTUNE_PARAMS = tuple(f"ATC_{k}" for k in (
    "ANG_RLL_P", "ANG_PIT_P", "ANG_YAW_P", "RAT_RLL_P", "RAT_RLL_I", "RAT_RLL_D", "RAT_PIT_P",
    "RAT_PIT_I", "RAT_PIT_D", "RAT_YAW_P", "RAT_YAW_I", "RAT_YAW_D", "RAT_YAW_FLTE",
    "ACCEL_R_MAX", "ACCEL_P_MAX", "ACCEL_Y_MAX"))
AUTOTUNE = 15
#: AUTOTUNE_AXES bits
AUTOTUNE_AXES = {1: "roll", 2: "pitch", 4: "yaw", 8: "yaw_d"}


def run_autotune(obs: Observer, serial0: str, rc_port: int, tmp: str, axes: int = 3,
                 timeout_s: float = 900.0) -> dict[str, object]:
    """ArduPilot's own AUTOTUNE (``AUTOTUNE_AXES`` ``axes``) from a 3 m LOITER, saved the way a
    pilot saves it (landed and disarmed in AUTOTUNE, here with the simulated RC throttle low).

    Returns a dict: ``success``, ``autotune_s`` (entering AUTOTUNE to its success),
    ``from_takeoff_s`` (the take-off command to its success), ``total_s`` (to the gains saved),
    ``changed`` (``name -> [old, new]``), ``messages`` (its STATUSTEXTs, with times)."""
    t_start = time.monotonic()
    with VehicleLink.connect(serial0, timeout_s=10) as link:
        client = ParamClient(link)
        old = {n: p.value for n, p in client.read_many(AUTOTUNE_PARAMS).items()}
        client.write({"AUTOTUNE_AXES": float(axes)}, tmp, label="autotune")
    obs.mode(GUIDED)
    obs.command(400, 1)
    t_takeoff = time.monotonic()
    obs.command(22, 0, 0, 0, 0, 0, 0, 3.0)
    end = time.monotonic() + 20
    while time.monotonic() < end and obs.height() < 2.7:
        pass
    obs.mode(LOITER)
    time.sleep(2.0)
    obs.mode(AUTOTUNE)
    t0 = time.monotonic()
    done = math.nan
    messages: list[str] = []
    while time.monotonic() < t0 + timeout_s:
        msg = obs.m.recv_match(type="STATUSTEXT", blocking=True, timeout=1.0)
        text = msg.text if msg is not None else ""
        if "AutoTune" in text:
            print(f"  {time.monotonic() - t0:5.0f} s {text}", flush=True)
            messages.append(f"{time.monotonic() - t0:.0f} s {text}")
        if "Success" in text:
            done = time.monotonic()
            break
        if "Failed" in text:
            break
    rc = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

    def sticks(throttle: int) -> None:
        rc.sendto(struct.pack("<8H", 1500, 1500, throttle, 1500, 1800, 1000, 1000, 1800),
                  ("127.0.0.1", rc_port))

    end = time.monotonic() + 30
    while time.monotonic() < end and obs.height() > 0.05:
        sticks(1000)  # descend in AUTOTUNE mode (its altitude hold follows the stick)
        time.sleep(0.1)
    for _ in range(30):
        sticks(1000)
        time.sleep(0.1)
    obs.command(400, 0)  # disarm landed in AUTOTUNE: the firmware saves the tuned gains
    for _ in range(10):
        sticks(1500)
        time.sleep(0.05)
    rc.close()
    with VehicleLink.connect(serial0, timeout_s=10) as link:
        new = {n: p.value for n, p in ParamClient(link).read_many(AUTOTUNE_PARAMS).items()}
    return {"axes": [name for bit, name in AUTOTUNE_AXES.items() if axes & bit],
            "success": done == done, "autotune_s": done - t0, "from_takeoff_s": done - t_takeoff,
            "total_s": time.monotonic() - t_start,
            # float32 on the wire: a value read back may differ in its last bits
            "changed": {n: [old[n], new[n]] for n in old
                        if not math.isclose(new[n], old[n], rel_tol=1e-6)},
            "messages": messages}


def tune_run(run: int, serial0: str, obs: Observer, hold: Callable[[], dict[str, float]],
             args: argparse.Namespace, tmp: str) -> dict[str, object]:
    """One run of the tool: hold before, tune, hold after on the written gains, restore."""
    before = hold()
    print(line("before", before), flush=True)
    t = time.monotonic()
    stop = threading.Event()
    watcher = obs.watch_handover(stop) if obs.wind_at_handover else None
    try:
        result = tune(serial0, args.profile, backup_dir=tmp, heartbeat_timeout_s=10,
                      actuation=args.actuation, hold_compare_s=args.hold_compare,
                      tlog_path=(str(Path(tmp) / f"tune{run}.tlog")
                                 if args.keep_logs is not None else None))
        status, error = result.status, ""
    except MrftError as err:
        if err.partial_result is None:
            raise
        result = err.partial_result
        status, error = result.status, str(err)
    finally:
        stop.set()
        if watcher is not None:
            watcher.join(timeout=5)
            obs.set_params(dict.fromkeys(obs.wind_at_handover, 0.0))  # calm for the landing
    total_s = time.monotonic() - t
    load = os.getloadavg()[0]
    written = {c.name: f"{c.old:.4g}->{c.new:.4g}" for c in result.parameters}
    tuned = [lp.value for lp, r in result.loops.items() if r.state == "tuned"]
    print(f"run {run}: tune {status} in {total_s:.1f} s "
          f"({result.duration_s:.1f} s from take-off, load "
          f"{load:.1f}); loops tuned {tuned}; written {written}; "
          f"hover check {result.hover_check}; link "
          f"{result.link.line() if result.link else '-'} {error}", flush=True)
    notes = [n for n in result.notes if n.startswith(("rate path:", "in-air check"))]
    for note in notes:  # k measured, alignment, zero-gain window
        print(f"run {run}: {note}", flush=True)
    for lp, lr in result.loops.items():  # the in-air check of the written gains
        if lr.verification is not None and lp.value in ("roll", "pitch"):
            v = lr.verification
            print(f"run {run}: {lp.value} {v.line()}; {v.note}", flush=True)
    row: dict[str, object] = {
        "status": status, "error": error, "total_s": total_s,
        "from_takeoff_s": result.duration_s, "load_avg_1min": load, "loops_tuned": tuned,
        "written": {c.name: [c.old, c.new] for c in result.parameters},
        "hover_check": str(result.hover_check), "notes": notes, "before": before,
        "hold_compare": result.hold_compare.as_dict() if result.hold_compare else None}
    if result.yaw is not None:  # the rate path's yaw relay: tuned or held, and why
        y = result.yaw
        row["yaw"] = {"state": y.state, "reason": y.reason, "steady_after_s": y.steady_after_s,
                      "pm_predicted_deg": y.pm_predicted_deg, "note": y.note}
        print(f"run {run}: yaw {y.state}: {y.reason or y.note}", flush=True)
    if result.hold_compare is not None:
        print(f"run {run}: {result.hold_compare.line()}", flush=True)
    obs.land_and_wait()
    if not result.backup or (result.hold_compare is not None
                             and result.hold_compare.outcome == "reverted"):
        return row  # reverted: the vehicle holds its own values again, nothing to hold on
    after = hold()
    print(line("after", after), flush=True)
    worse = worse_in(before, after)
    effort = effort_in(before, after)
    # the same holds judged against their scatter, as the tool's comparison judges its own
    noise = {k: max(before["noise"].get(k, 0.0), after["noise"].get(k, 0.0))  # type: ignore
             for k in WORSE_SLACK}
    worse_noise = worse_in(before, after, noise)
    print(f"run {run}: hold after the tune "
          f"{'worse in ' + ', '.join(worse) if worse else 'as good or better'}"
          f" (beyond the halves' scatter: {', '.join(worse_noise) or 'none'})"
          f"{'; ' + effort if effort else ''}; backup restored", flush=True)
    with VehicleLink.connect(serial0, timeout_s=10) as link:
        ParamClient(link).restore(result.backup, tmp)
    row.update(after=after, worse_in=worse, worse_beyond_noise=worse_noise, effort=effort)
    return row


def compare_configs(source: Path, run: int, extra: list[str]) -> dict[str, dict[str, float]]:
    """Parameter sets to hold on, from run ``run``'s written values in an earlier ``--json``:
    ``stock`` (every written parameter at its value before), ``tuned`` (all written),
    ``attitude`` (the ATC_* written, PSC_* stock), ``position`` (the PSC_* written, ATC_*
    stock); ``extra``: ``NAME=BASE:P=V,P=V`` adds BASE with those values set on top."""
    written = json.loads(source.read_text())["runs"][run]["written"]
    old = {n: float(v[0]) for n, v in written.items()}
    new = {n: float(v[1]) for n, v in written.items()}
    out = {"stock": dict(old), "tuned": dict(new),
           "attitude": {n: (new if n.startswith("ATC_") else old)[n] for n in old},
           "position": {n: (new if n.startswith("PSC_") else old)[n] for n in old}}
    for spec in extra:
        name, rest = spec.split("=", 1)
        base, _, sets = rest.partition(":")
        cfg = dict(out[base])
        for kv in filter(None, sets.split(",")):
            k, v = kv.split("=")
            cfg[k] = float(v)
            old.setdefault(k, math.nan)
        out[name] = cfg
    return out


def run_compare(sitl: ArduCopterSitl, args: argparse.Namespace, tmp: str,
                hold: Callable[[], dict[str, float]], out: dict[str, object]) -> None:
    """``--compare``: LOITER holds on each parameter set of :func:`compare_configs`, the sets
    interleaved ``--repeats`` times; the vehicle's own values put back after."""
    configs = compare_configs(args.compare, args.compare_run, args.config)
    names = sorted({n for c in configs.values() for n in c})
    with VehicleLink.connect(sitl.serial0, timeout_s=10) as link:
        own = {n: p.value for n, p in ParamClient(link).read_many(names).items()}
    for c in configs.values():  # names a set leaves out stay at the vehicle's own value
        for n in names:
            c.setdefault(n, own[n])
    rows: list[dict[str, object]] = []
    out["compare"] = {"source": str(args.compare), "run": args.compare_run,
                      "configs": configs, "holds": rows}
    try:
        for rep in range(args.repeats):
            for name, values in configs.items():
                with VehicleLink.connect(sitl.serial0, timeout_s=10) as link:
                    ParamClient(link).write(values, tmp, label="compare")
                f = hold()
                print(line(name[:7], f) + f" [repeat {rep}, load {os.getloadavg()[0]:.1f}]",
                      flush=True)
                rows.append({"config": name, "repeat": rep, "load_avg_1min":
                             os.getloadavg()[0], **f})
    finally:
        with VehicleLink.connect(sitl.serial0, timeout_s=10) as link:
            ParamClient(link).write(own, tmp, label="compare-undo")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hold-s", type=float, default=10.0)
    ap.add_argument("--instance", type=int, default=None)
    ap.add_argument("--runs", type=int, default=1)
    ap.add_argument("--profile", default="ardupilot", help="profile name or .toml")
    ap.add_argument("--baro-noise", type=float, default=None, metavar="M",
                    help="SIM_BARO_RND for the whole run (the SITL's default is 0)")
    ap.add_argument("--gust", type=float, default=0.0, metavar="M_S",
                    help="turbulent wind in the LOITER holds only (SIM_WIND_SPD, half of it "
                    "SIM_WIND_TURB, 30 deg up from level: a vertical disturbance)")
    ap.add_argument("--gust-in", default="holds", choices=("holds", "handover", "all"),
                    help="with --gust: where the wind blows: the benchmark's holds only; "
                    "also from the tune's hand-over to LOITER on (its hover check and its own "
                    "hold comparison); or the whole run, the tune's tests included")
    ap.add_argument("--autotune", action="store_true",
                    help="first fly ArduPilot's own AUTOTUNE (roll, pitch), hold on its gains, "
                    "restore them, then the tool's runs")
    ap.add_argument("--autotune-axes", type=int, default=3, metavar="BITS",
                    help="AUTOTUNE_AXES for --autotune (1 roll, 2 pitch, 4 yaw; default 3)")
    ap.add_argument("--autotune-timeout-s", type=float, default=480.0, metavar="S",
                    help="longest wait for AUTOTUNE's success (then land and keep its gains)")
    ap.add_argument("--actuation", default=None, choices=("attitude", "rate"),
                    help="the tune's path (default: the profile's, attitude)")
    ap.add_argument("--scripting", action="store_true",
                    help="boot the SITL with SCR_ENABLE 1 (the rate path's link-loss guard)")
    ap.add_argument("--compare", type=Path, metavar="JSON",
                    help="no tune: hold on the written values of an earlier --json run, split "
                    "into stock / tuned / attitude only / position only (--compare-run, "
                    "--repeats, --config)")
    ap.add_argument("--compare-run", type=int, default=0, metavar="N")
    ap.add_argument("--repeats", type=int, default=1, metavar="N")
    ap.add_argument("--config", action="append", default=[], metavar="NAME=BASE:P=V,...",
                    help="with --compare: another set, BASE's with these values on top")
    ap.add_argument("--hold-compare", type=float, default=None, metavar="S",
                    help="the tool's own hold comparison after its hand-over (s each; 0 off; "
                    "default the profile's)")
    ap.add_argument("--json", type=Path, help="write the figures here")
    ap.add_argument("--keep-logs", type=Path, metavar="DIR",
                    help="keep each tune's tlog and copy the SITL's folder (dataflash logs, "
                         "backups, tlogs) here at the end")
    args = ap.parse_args()
    # a timeout's TERM unwinds like an error: the SITL is stopped and --json still written
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(128 + signal.SIGTERM))
    reason = why_not()
    if reason is not None:
        print(f"error: {reason}", file=sys.stderr)
        return 2
    instance = args.instance if args.instance is not None else free_instance(61, 99)
    out: dict[str, object] = {"settings": {k: (str(v) if isinstance(v, Path) else v)
                                           for k, v in vars(args).items()}}
    with tempfile.TemporaryDirectory() as tmp:
        t = time.monotonic()
        with ArduCopterSitl.start(instance, tmp,
                                  {"SCR_ENABLE": 1} if args.scripting else None) as sitl:
            print(f"ArduCopter SITL instance {instance} ready after {time.monotonic() - t:.0f} "
                  f"s; load {os.getloadavg()[0]:.1f}", flush=True)
            out["sitl"] = {"instance": instance, "ready": sitl.ready,
                           "boot_s": time.monotonic() - t, "load_avg_1min": os.getloadavg()[0]}
            try:
                run_all(sitl, args, tmp, out)
            finally:
                if args.json:
                    args.json.write_text(json.dumps(out, indent=1) + "\n")
                if args.keep_logs is not None:  # the dataflash logs show what the run hid
                    shutil.copytree(tmp, args.keep_logs, dirs_exist_ok=True,
                                    ignore=shutil.ignore_patterns("*.sock"))
    return 0


def run_all(sitl: ArduCopterSitl, args: argparse.Namespace, tmp: str,
            out: dict[str, object]) -> None:
    """The AUTOTUNE leg (``--autotune``) and the tool's runs on one booted SITL, into ``out``."""
    obs = Observer(sitl.serial2)
    if args.baro_noise is not None:
        with VehicleLink.connect(sitl.serial0, timeout_s=10) as link:
            ParamClient(link).write({"SIM_BARO_RND": args.baro_noise}, tmp, label="sim")
        print(f"SIM_BARO_RND {args.baro_noise} m", flush=True)
    wind = {"SIM_WIND_SPD": args.gust, "SIM_WIND_TURB": args.gust / 2,
            "SIM_WIND_DIR_Z": 30.0, "SIM_WIND_T": 1.0} if args.gust else {}
    calm = dict.fromkeys(wind, 0.0)
    if wind and args.gust_in == "all":  # on once, for everything: the holds switch nothing
        with VehicleLink.connect(sitl.serial0, timeout_s=10) as link:
            ParamClient(link).write(wind, tmp, label="sim")
    switch = bool(wind) and args.gust_in != "all"
    if wind and args.gust_in == "handover":
        obs.wind_at_handover = wind

    def hold() -> dict[str, float]:
        with VehicleLink.connect(sitl.serial0, timeout_s=10) as link:
            if switch:
                ParamClient(link).write(wind, tmp, label="sim")
        try:
            return obs.loiter_hold(args.hold_s)
        finally:
            if switch:
                with VehicleLink.connect(sitl.serial0, timeout_s=10) as link:
                    ParamClient(link).write(calm, tmp, label="sim")

    if wind:
        where = {"holds": "holds", "handover": "holds and the tune from its hand-over on",
                 "all": "whole run"}[args.gust_in]
        print(f"{where} in wind {args.gust} m/s, "
              f"turbulence {args.gust / 2} m/s, 30 deg up", flush=True)
    if args.autotune:
        before = hold()
        print(line("before", before), flush=True)
        at = run_autotune(obs, sitl.serial0, sitl.rc_port, tmp, args.autotune_axes,
                          args.autotune_timeout_s)
        changed, axes = at["changed"], at["axes"]
        assert isinstance(changed, dict) and isinstance(axes, list)
        at.update(before=before, load_avg_1min=os.getloadavg()[0])
        out["autotune"] = at
        print(f"AUTOTUNE ({', '.join(axes)}) {at['autotune_s']:.0f} s to success, "
              f"{at['from_takeoff_s']:.0f} s from take-off (load {os.getloadavg()[0]:.1f}); "
              f"saved { {n: f'{a:.4g}->{b:.4g}' for n, (a, b) in changed.items()} }",
              flush=True)
        after = hold()
        worse = worse_in(before, after)
        at.update(after=after, worse_in=worse)
        print(line("autotune", after), flush=True)
        print(f"hold after AUTOTUNE "
              f"{'worse in ' + ', '.join(worse) if worse else 'as good or better'}", flush=True)
        if changed:
            with VehicleLink.connect(sitl.serial0, timeout_s=10) as link:
                ParamClient(link).write({n: a for n, (a, _) in changed.items()}, tmp,
                                        label="autotune-undo")
    if args.compare is not None:
        run_compare(sitl, args, tmp, hold, out)
        return
    runs: list[dict[str, object]] = []
    out["runs"] = runs
    for run in range(args.runs):
        runs.append(tune_run(run, sitl.serial0, obs, hold, args, tmp))


if __name__ == "__main__":
    sys.exit(main())
