"""Yaw on ArduCopter's rate path: tune all loops and yaw, and compare the heading hold.

    python benchmarks/tune_yaw_ardupilot.py [--runs 2] [--instance N] [--hold-s 8]
                                            [--no-before] [--no-after] [--trace DIR]
                                            [--json FILE]

Starts ArduCopter SITL (parameters wiped, :mod:`tune_ardupilot`'s recipe), then per run:
*before* (the vehicle's own gains) and *after* (the gains the tune wrote, restored after):
take off in GUIDED to 1 m, hold in LOITER for ``--hold-s`` (heading peak-to-peak, yaw-rate
standard deviation), then in GUIDED a 45 deg heading step (MAV_CMD_CONDITION_YAW at
90 deg/s): overshoot past the new heading, time to stay within 2 deg, the error left; land.
Between them ``tune(actuation="rate")``: what yaw identified and wrote, the zero-gain window,
the time from take-off. One line per figure; nothing is written to disk but the SITL's run
folder (a temporary one), except with ``--trace DIR``: per run, the yaw relay's every tick
(``yaw-runN.npz``: time, heading error, yaw rate, output, state, cycles seen, amplitude,
period) and the tune's .tlog (``yaw-runN.tlog``), to see why a cycle did or did not come.
``--json FILE``: every run's figures (the holds, yaw's identified model and written values,
each loop's time tuned after the take-off command) and their spread across the runs.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from tune_ardupilot import GUIDED, LOITER, Observer  # noqa: E402

from mrft_gcs.errors import MrftError  # noqa: E402
from mrft_gcs.flight import api, ratepath  # noqa: E402
from mrft_gcs.flight.api import tune  # noqa: E402
from mrft_gcs.flight.controllers import wrap_pi  # noqa: E402
from mrft_gcs.flight.phases.yaw import YawRelay, YawState  # noqa: E402
from mrft_gcs.link import VehicleLink  # noqa: E402
from mrft_gcs.params import ParamClient  # noqa: E402
from mrft_gcs.sitl.arducopter import ArduCopterSitl, free_instance, why_not  # noqa: E402

YAW_NAMES = ("ATC_ANG_YAW_P", "ATC_RAT_YAW_P", "ATC_RAT_YAW_I", "ATC_RAT_YAW_D",
             "ATC_RAT_YAW_FLTE", "ATC_RAT_YAW_FLTT")


def heading(obs: Observer, seconds: float) -> np.ndarray:
    """(t, yaw rad unwrapped, yaw rate rad/s) from ATTITUDE for ``seconds``."""
    rows = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        msg = obs.m.recv_match(type="ATTITUDE", blocking=True, timeout=0.2)
        if msg is not None:
            rows.append((msg.time_boot_ms * 1e-3, msg.yaw, msg.yawspeed))
    a = np.asarray(rows, float).reshape(-1, 3)
    a[:, 1] = np.unwrap(a[:, 1])
    return a


def yaw_figures(obs: Observer, hold_s: float) -> dict[str, float]:
    obs.mode(GUIDED)
    obs.command(400, 1)
    obs.command(22, 0, 0, 0, 0, 0, 0, 1.0)
    end = time.monotonic() + 20
    while time.monotonic() < end and obs.height() < 0.9:
        pass
    time.sleep(2.0)
    obs.mode(LOITER)
    hold = heading(obs, hold_s)
    obs.mode(GUIDED)
    time.sleep(1.0)
    start = heading(obs, 0.3)
    y0 = float(start[-1, 1])
    obs.command(115, 45.0, 90.0, 1, 1)  # CONDITION_YAW: +45 deg, 90 deg/s, clockwise, relative
    step = heading(obs, 5.0)
    obs.land_and_wait()
    e = np.degrees(step[:, 1] - (y0 + math.radians(45.0)))
    outside = np.flatnonzero(np.abs(e) > 2.0)
    settle = (float(step[outside[-1] + 1, 0] - step[0, 0]) if outside.size and
              outside[-1] + 1 < len(step) else math.nan if outside.size else 0.0)
    return {"heading_p2p_deg": float(np.degrees(np.ptp(hold[:, 1]))),
            "yaw_rate_std_deg_s": float(np.degrees(hold[:, 2].std())),
            "step_overshoot_deg": float(max(0.0, e.max())),
            "step_settle_s": settle, "step_error_end_deg": float(abs(e[-10:]).mean())}


def line(name: str, f: dict[str, float]) -> str:
    return (f"{name:6s} LOITER heading p2p {f['heading_p2p_deg']:.2f} deg, yaw rate std "
            f"{f['yaw_rate_std_deg_s']:.2f} deg/s; 45 deg step overshoot "
            f"{f['step_overshoot_deg']:.1f} deg, within 2 deg after {f['step_settle_s']:.2f} s, "
            f"error at the end {f['step_error_end_deg']:.2f} deg")


_STATES = list(YawState)


class YawTrace:
    """Records every :meth:`YawRelay.step` (the real relay, wrapped while a run flies)."""

    def __init__(self) -> None:
        self.rows: list[tuple[float, ...]] = []
        self._step = YawRelay.step

    def __enter__(self) -> YawTrace:
        step, rows = self._step, self.rows

        def traced(relay: YawRelay, ref: float, y: float, rate: float,
                   t_s: float = math.nan) -> float:
            u = step(relay, ref, y, rate, t_s)
            st = relay.watch.status
            rows.append((time.monotonic(), t_s, wrap_pi(ref - y), rate, u,
                         _STATES.index(relay.state), st.cycles, st.amplitude, st.period_s,
                         relay.h, relay.bias))
            return u

        YawRelay.step = traced  # type: ignore[method-assign]
        return self

    def __exit__(self, *exc: object) -> None:
        YawRelay.step = self._step  # type: ignore[method-assign]

    def save(self, path: Path) -> None:
        np.savez(path, rows=np.asarray(self.rows, float).reshape(-1, 11),
                 columns=np.array(["mono_s", "t_s", "e_rad", "rate_rad_s", "u", "state",
                                   "cycles", "amplitude_rad", "period_s", "h", "bias"]),
                 states=np.array([s.value for s in _STATES]))


class RateProbe:
    """Records, while a run flies, the rate path's sequencing: when roll and pitch were first
    seen identified, when they went onto the onboard cascade (where the code does that before
    yaw's hand-over), when the full hand-over came, and the body rates in between, from which
    the roll/pitch rms during yaw's test (the real classes wrapped, put back after)."""

    def __init__(self) -> None:
        self.rate: ratepath.RatePath | None = None
        self.rows: list[tuple[float, float, float]] = []
        self.t_rp = self.t_ho = math.nan
        self._saved: dict[str, object] = {}

    def __enter__(self) -> RateProbe:
        probe, rp, ch = self, ratepath.RatePath, ratepath.RateChannel
        self._saved = {"init": rp.__init__, "due": rp.inner_due, "ho": rp.hand_over,
                       "see": ch._see_rates}
        init, due, ho, see = (self._saved[k] for k in ("init", "due", "ho", "see"))

        def p_init(rate: ratepath.RatePath, *a: object, **k: object) -> None:
            init(rate, *a, **k)  # type: ignore[operator]
            probe.rate = rate

        def p_due(rate: ratepath.RatePath, tuned: bool) -> bool:
            if tuned and not math.isfinite(probe.t_rp):
                probe.t_rp = time.monotonic()
            return due(rate, tuned)  # type: ignore[operator]

        def p_ho(rate: ratepath.RatePath, *a: object, **k: object) -> object:
            if not math.isfinite(probe.t_ho):
                probe.t_ho = time.monotonic()
            return ho(rate, *a, **k)  # type: ignore[operator]

        def p_see(channel: ratepath.RateChannel, s: object) -> None:
            probe.rows.append((time.monotonic(), s.p_rad_s, s.q_rad_s))  # type: ignore[attr-defined]
            see(channel, s)  # type: ignore[operator]

        rp.__init__ = p_init  # type: ignore[method-assign]
        rp.inner_due = p_due  # type: ignore[method-assign]
        rp.hand_over = p_ho  # type: ignore[method-assign]
        ch._see_rates = p_see  # type: ignore[method-assign]
        return self

    def __exit__(self, *exc: object) -> None:
        rp, ch = ratepath.RatePath, ratepath.RateChannel
        rp.__init__ = self._saved["init"]  # type: ignore[method-assign]
        rp.inner_due = self._saved["due"]  # type: ignore[method-assign]
        rp.hand_over = self._saved["ho"]  # type: ignore[method-assign]
        ch._see_rates = self._saved["see"]  # type: ignore[method-assign]

    def record(self) -> dict[str, object]:
        """Roll/pitch body rates from 0.5 s after both were identified to the full hand-over
        (yaw's test beside them): rms and the largest 0.25 s rms (deg/s); the zero-gain
        windows per axis (s)."""
        out: dict[str, object] = {}
        rate = self.rate
        a = np.asarray(self.rows, float).reshape(-1, 3)
        if math.isfinite(self.t_rp) and math.isfinite(self.t_ho):
            out["yaw_beside_rp_s"] = self.t_ho - self.t_rp
            w = a[(a[:, 0] > self.t_rp + 0.5) & (a[:, 0] < self.t_ho)]
            if len(w) > 5:
                out["rp_rms_deg_s"] = np.degrees(np.sqrt((w[:, 1:] ** 2).mean(0))).tolist()
                win = []
                for t0 in np.arange(w[0, 0], w[-1, 0] - 0.25, 0.05):
                    m = w[(w[:, 0] >= t0) & (w[:, 0] < t0 + 0.25)]
                    if len(m) > 3:
                        win.append(np.sqrt((m[:, 1:] ** 2).mean(0)))
                if win:
                    out["rp_rms_max_025s_deg_s"] = np.degrees(np.max(win, 0)).tolist()
        if rate is not None:
            zg = getattr(rate, "zero_gain_axes_s", None)
            out["zero_gain_s"] = _num(rate.zero_gain_s)
            out["zero_gain_axes_s"] = ({k: _num(v) for k, v in zg.items()} if zg else
                                       {k: _num(rate.zero_gain_s) for k in
                                        ("roll", "pitch", "yaw")})
        return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=1)
    ap.add_argument("--instance", type=int, default=None)
    ap.add_argument("--hold-s", type=float, default=8.0)
    ap.add_argument("--no-before", action="store_true", help="skip the holds before")
    ap.add_argument("--before-once", action="store_true",
                    help="the holds before on the first run only (the same stock gains each run)")
    ap.add_argument("--no-after", action="store_true", help="skip the holds after")
    ap.add_argument("--trace", type=Path, default=None,
                    help="folder for each run's yaw relay trace (.npz) and .tlog")
    ap.add_argument("--json", type=Path, default=None, help="write every run's figures here")
    ap.add_argument("--inair-check-runs", type=int, default=0,
                    help="the last N runs fly the rate path's in-air check of the written "
                         "roll/pitch gains (off in the tool: ratepath.INAIR_CHECK)")
    args = ap.parse_args()
    runs: list[dict[str, object]] = []
    reason = why_not()
    if reason is not None:
        print(reason, file=sys.stderr)
        return 2
    instance = args.instance if args.instance is not None else free_instance(61, 99)
    with tempfile.TemporaryDirectory() as tmp, ArduCopterSitl.start(instance, tmp) as sitl:
        obs = Observer(sitl.serial2)
        for run in range(args.runs):
            rec: dict[str, object] = {"run": run}
            runs.append(rec)
            if not args.no_before and not (args.before_once and run > 0):
                rec["before"] = f = yaw_figures(obs, args.hold_s)
                print(line("before", f), flush=True)
            t = time.monotonic()
            tlog = args.trace / f"yaw-run{run}.tlog" if args.trace else None
            if args.trace:
                args.trace.mkdir(parents=True, exist_ok=True)
            check = args.inair_check_runs > 0 and run >= args.runs - args.inair_check_runs
            api.RATE_INAIR_CHECK = check or ratepath.INAIR_CHECK
            rec["inair_check"] = api.RATE_INAIR_CHECK
            with YawTrace() as trace, RateProbe() as probe:
                try:
                    result = tune(sitl.serial0, "ardupilot", backup_dir=tmp, tlog_path=tlog,
                                  heartbeat_timeout_s=10, actuation="rate")
                    status, error = result.status, ""
                except MrftError as err:
                    result = err.partial_result
                    status, error = result.status, str(err)
            if args.trace:
                trace.save(args.trace / f"yaw-run{run}.npz")
            written = {c.name: f"{c.old:.4g}->{c.new:.4g}" for c in result.parameters
                       if "YAW" in c.name}
            for lp, lr in result.loops.items():
                if lr.verification is not None:
                    print(f"run {run}: {lp.value} {lr.verification.line()}", flush=True)
            print(f"run {run}: tune {status} in {time.monotonic() - t:.1f} s "
                  f"({result.duration_s:.1f} s from take-off, load "
                  f"{os.getloadavg()[0]:.1f}); yaw written {written} {error}", flush=True)
            rec.update(run_record(result, status, error, time.monotonic() - t))
            rec["sequencing"] = sq = probe.record()
            print(f"run {run}: sequencing {sq}", flush=True)
            for note in result.notes:
                if note.startswith(("yaw", "rate path: zero-gain", "rate path: roll written",
                                    "rate path: pitch written", "in-air")):
                    print(f"run {run}: {note}", flush=True)
            obs.land_and_wait()
            if not result.backup:
                continue
            if not args.no_after:
                rec["after"] = f = yaw_figures(obs, args.hold_s)
                print(line("after", f), flush=True)
            with VehicleLink.connect(sitl.serial0, timeout_s=10) as link:
                ParamClient(link).restore(result.backup, tmp)
            if args.json:
                write_json(args.json, runs)
    if args.json:
        write_json(args.json, runs)
    return 0


def _num(x: object) -> float | None:
    return float(x) if isinstance(x, (int, float)) and math.isfinite(x) else None


def run_record(result: object, status: str, error: str, wall_s: float) -> dict[str, object]:
    """One tune's figures: status, times, yaw's identification and written values."""
    r: dict[str, object] = {"status": status, "error": error or None, "wall_s": wall_s,
                            "duration_s": _num(getattr(result, "duration_s", None))}
    loops = getattr(result, "loops", {}) or {}
    r["tuned_after_s"] = {getattr(lp, "value", str(lp)): _num(lr.t_tuned_s)
                          for lp, lr in loops.items()}
    r["verification"] = {getattr(lp, "value", str(lp)): lr.verification.as_dict()
                         for lp, lr in loops.items() if lr.verification is not None}
    y = getattr(result, "yaw", None)
    if y is not None:
        m = y.identification.model if y.identification is not None else None
        r["yaw"] = {"state": y.state, "reason": y.reason, "steady_after_s": _num(y.steady_after_s),
                    "period_s": _num(y.period_s), "h": y.h,
                    "model": None if m is None else {k: float(getattr(m, k)) for k in
                                                     ("K", "T_prop", "T1", "tau")},
                    "written": y.written, "pm_predicted_deg": _num(y.pm_predicted_deg),
                    "max_error_deg": math.degrees(y.max_error_rad)}
    r["zero_gain_note"] = next((n for n in getattr(result, "notes", ())
                                if n.startswith("rate path: zero-gain")), None)
    return r


def write_json(path: Path, runs: list[dict[str, object]]) -> None:
    """The runs and the spread of yaw's identified model and of the time to tune."""
    models = [r["yaw"]["model"] for r in runs if isinstance(r.get("yaw"), dict)
              and r["yaw"]["model"]]  # type: ignore[index]
    spread = {k: [min(m[k] for m in models), max(m[k] for m in models)]
              for k in ("K", "T_prop", "T1", "tau")} if models else {}
    durs = [r["duration_s"] for r in runs if isinstance(r.get("duration_s"), float)]
    out = {"benchmark": "tune_yaw_ardupilot", "runs": runs,
           "yaw_tuned": sum(1 for r in runs if isinstance(r.get("yaw"), dict)
                            and r["yaw"]["state"] == "tuned"),  # type: ignore[index]
           "yaw_model_range": spread,
           "duration_s_range": [min(durs), max(durs)] if durs else None,
           "load_1min": os.getloadavg()[0]}
    path.write_text(json.dumps(out, indent=1, default=str))


if __name__ == "__main__":
    sys.exit(main())
