"""Benchmark: tune a population of random vehicles and score what was written on each
vehicle's true onboard loop.

Each vehicle is :func:`mrft_gcs.sitl.random_airframe` of its seed (airframe, delay split,
link, telemetry cap, PX4- or ArduPilot-like onboard cascade and rates, hover misestimate,
CoM bias, sometimes an undeclared effect) and is counted in-domain, hidden-effect or
out-of-domain by :func:`mrft_gcs.sitl.domain_check` (Table I, and a link fast enough for a
relay test). Outcomes: ``completed`` (all loops written, the hand-over hover held),
``refused`` (the tool stopped with an explanation: link check, identification that never
settled, a numerical failure; no safety limit crossed) or ``aborted`` (a safety limit, or
the hover on the written gains failed).

Two ways to run it (the output says which):

* ``--mode lockstep`` (default, the fastest honest one): the tool's own sequence
  (:class:`TuningSequence`) run by the tool's own driver
  (:class:`~mrft_gcs.flight.driver.SequenceDriver`: safety limits, the bundled classifiers,
  the retry rules), the GCS-delay re-targeting and the parameter write-back
  (``params_in_range`` on the ``sitl`` profile) drive the in-process vehicle
  (:class:`~mrft_gcs.sitl.lockstep.LockstepVehicle`) in simulated time, 1 ms physics
  steps. The link is the vehicle's: telemetry at its cap (at most the 250 Hz asked), each frame held
  ``link_delay_s`` each way, commands every 4 ms; the link check is the tool's own
  (``require_relay_capable``) on those figures, not a measurement. Not run: the tool's
  in-air check of written gains and anything that depends on host timing (a CPU hog then
  changes only the wall time); ``--stalls MS,EVERY_S`` models the ground station missing
  ticks (:class:`~mrft_gcs.sitl.lockstep.PeriodicStalls`), which the tool's timeliness check
  (:mod:`mrft_gcs.flight.timeliness`) sees as in a live tune.
* ``--mode live``: the real ``tune()`` over loopback UDP against ``python -m mrft_gcs.sitl
  --random SEED`` in real time (about a minute a vehicle; host load matters).

Scores: for every written loop, J (%) and phase margin of the written parameters on the
onboard truth (:func:`mrft_gcs.flight.scoring.score_written`: onboard delays, loop rates as
sample-and-hold, the cascade's structure), beside the GCS-side figures (the identified PD
on the model with the ground station's delay: 2 x link + half a telemetry period + half a
setpoint period + half an onboard loop period).

    .venv/bin/python benchmarks/tune_population.py [--seeds 40] [--first-seed 0] \
        [--mode lockstep|live] [--with-hog] [--hog-procs 2] [--hog-nice 10] \
        [--in-domain-only] [--stalls MS,EVERY_S] \
        [--json benchmarks/results/population.json]
"""

from __future__ import annotations

import argparse
import collections
import functools
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from mrft_gcs.errors import IdentificationError, LinkError, MrftError, SafetyAbort
from mrft_gcs.flight.driver import SequenceDriver
from mrft_gcs.flight.onboard import (
    SideLoop,
    measure_gcs_delay,
    onboard_extra_delay_s,
    pooled_attitude,
    robust_onboard_gains,
    shared_side_gains,
    vehicle_position_rate,
)
from mrft_gcs.flight.safety import LimitExceeded
from mrft_gcs.flight.scoring import score_written
from mrft_gcs.flight.sequence import LoopState, Phase, SequenceConfig, TuningSequence
from mrft_gcs.flight.source import VehicleMode
from mrft_gcs.flight.structure import (
    D_FILTER_PARAMS,
    TARGET_FILTER_PARAMS,
    rate_d_values,
    read_structure,
    structured_retarget,
)
from mrft_gcs.flight.timeliness import HostTooSlow, TimelinessMonitor
from mrft_gcs.identify import relay_settings
from mrft_gcs.identify.live import bundled_identifier
from mrft_gcs.link.quality import LinkQuality, require_relay_capable
from mrft_gcs.loops import INNER_LOOPS, SIDE_INNER, SIDE_LOOPS, Loop, LoopKind
from mrft_gcs.profiles import PDGains, load_profile, params_in_range
from mrft_gcs.sitl import SimVehicle, domain_check, random_airframe
from mrft_gcs.sitl.lockstep import GcsLink, LockstepVehicle, PeriodicStalls
from mrft_gcs.sitl.onboard import ParamStore

RATE_HZ = 250.0          # the tool's setpoint stream and the telemetry rate it asks
MAX_RELAY_S = 30.0       # tune(max_relay_s=...) default
HOVER_CHECK_S = 2.0      # tune(hover_check_s=...) default
DEFAULT_JSON = Path(__file__).resolve().parent / "results" / "population.json"


def _num(x) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None


def _probs(ident) -> list[float]:
    """The classifier's three largest probabilities, where a classifier ran."""
    vote = ident.diagnostics.classifier
    return [float(p) for p in vote.probs] if vote is not None else []


def gcs_delay_s(af) -> float:
    """The ground station's extra delay on the inner loops of ``af`` (see the docstring)."""
    tel = min(RATE_HZ, af.telemetry_max_hz)
    return 2 * af.link_delay_s + 0.5 / tel + 0.5 / RATE_HZ + 0.5 / af.onboard.loop_hz


def _phase_times(seq: TuningSequence, drv: SequenceDriver) -> dict:
    """Where the tune's time went (s from the take-off command; None: did not happen).

    ``takeoff``: to the altitude relay's first switch (the climb); ``liftoff``: to the
    attitude relays' start; per loop: its relay's start, the first and last sample of the
    cycles identified, its PD applied, and the retries, amplitude raises and re-sizings it
    took; ``inner``: to altitude, roll and pitch all done; ``side``: from then to x and y
    done."""
    t0 = seq.t_start_s

    def rel(t: float) -> float | None:
        return _num(t - t0) if math.isfinite(t) else None

    loops = {}
    for lp, t in seq.loops.items():
        snap = t.snapshot
        have = snap is not None and len(snap.t_s) > 0
        loops[lp.value] = {
            "start": rel(seq.takeoff.t_switch if lp is Loop.ALTITUDE else t.t_relay_start_s),
            "cycles_from": rel(float(snap.t_s[0])) if have else None,
            "cycles_to": rel(float(snap.t_s[-1])) if have else None,
            "tuned": rel(t.t_tuned_s),
            "retries": sum(1 for rl, _ in drv.retries if rl is lp),
            "raises": t.raises, "resizes": t.resizes}
    inner = [seq.loops[lp].t_tuned_s for lp in INNER_LOOPS]
    side = [seq.loops[lp].t_tuned_s for lp in SIDE_LOOPS]
    t_inner = max(inner) if all(math.isfinite(x) for x in inner) else math.nan
    t_side = max(side) if all(math.isfinite(x) for x in side) else math.nan
    return {"takeoff": rel(seq.takeoff.t_switch),
            "liftoff": rel(seq.loops[Loop.ROLL].t_relay_start_s),
            "inner": rel(t_inner),
            "side": _num(t_side - t_inner) if math.isfinite(t_side - t_inner) else None,
            "loops": loops}


def run_lockstep(seed: int, max_s: float = 70.0,
                 stalls: tuple[float, float] | None = None, timeliness: bool = True) -> dict:
    """One tune of the random vehicle of ``seed`` in simulated time; a JSON-able record.

    ``stalls``: (ms, every_s) of :class:`~mrft_gcs.sitl.lockstep.PeriodicStalls` (the
    ground station misses ticks now and then; the vehicle keeps the last set point).
    ``timeliness``: stalls stop the tests as in a live tune (False: the tool without that
    check, for comparison)."""
    af = random_airframe(seed)
    rec = _head(af, seed, "lockstep")
    prof = load_profile("sitl")
    lim = prof.safety
    # the link check, as the tool does it, on this vehicle's link figures
    tel = min(RATE_HZ, af.telemetry_max_hz)
    rtt = 2e3 * af.link_delay_s
    try:
        require_relay_capable(LinkQuality(RATE_HZ, tel, tel, rtt, rtt, 0, 10, 2.0))
    except LinkError as err:
        return _end(rec, "refused", f"link: {err}")
    rng = np.random.default_rng([7, seed])
    phase = float(rng.uniform(0.0, 1.0 / RATE_HZ))  # the session's phase
    v = SimVehicle(af, seed=seed)
    stall = (PeriodicStalls(stalls[0], stalls[1], np.random.default_rng([11, seed]))
             if stalls else None)
    src = LockstepVehicle(v, RATE_HZ, link=GcsLink(af.link_delay_s, tel, phase), stalls=stall)
    ap = v.autopilot
    hover = ap.params["MPC_THR_HOVER"]  # what the tool reads: the autopilot's estimate
    cfg = SequenceConfig(actuation=prof.actuation, z_ref_m=1.0, hover_thrust_guess=hover,
                         max_tilt_cmd_rad=0.6 * math.radians(lim.max_tilt_deg))
    seq = TuningSequence(cfg, relay_settings(LoopKind.ATTITUDE),
                         relay_settings(LoopKind.ALTITUDE))
    drv = SequenceDriver(seq, bundled_identifier, limits=lim, max_relay_s=MAX_RELAY_S,
                         timeliness=TimelinessMonitor() if timeliness else None)
    drv.guard_lead_s = rtt * 1e-3 + 1.0 / tel  # as the tool sets it from the TIMESYNC round trip
    src.send(drv.idle)  # as the tool does: set points first, then offboard, then arm
    src.set_mode(VehicleMode.OFFBOARD)
    src.arm()
    ages: dict[bool, list[tuple[float, float]]] = {False: [], True: []}  # (t, age) att / pos

    def age(s, _sp) -> None:
        a = v.time_s - src.latest_arrival
        ages[False].append((s.t_att_s, a))
        ages[True].append((s.t_pos_s, a))

    outcome = reason = None
    try:
        # on the ground for 0.4 s: the noise that sets the relays' bands
        drv.run(src, ground_until_s=0.4, on_tick=age,
                stop=lambda _s: seq.phase is Phase.HOVER or v.time_s > max_s)
        if seq.phase is not Phase.HOVER:
            outcome, reason = "aborted", f"not done after {max_s:.0f} s of simulated time"
    except LimitExceeded as err:
        outcome, reason = "aborted", str(err)
    except (IdentificationError, HostTooSlow) as err:
        outcome, reason = "refused", str(err)
    monitor = drv.monitor
    notes = drv.notes
    rec["time_to_tune_s"] = _num(seq.duration_s) if seq.phase is Phase.HOVER else None
    rec["phase_times_s"] = _phase_times(seq, drv)
    rec["notes"] = notes
    rec["max_tilt_by_phase"] = {k: _num(d) for k, d in seq.max_tilt_by_phase.items()}
    identified = {lp: t.identification for lp, t in seq.loops.items()
                  if t.state is LoopState.TUNED and t.identification is not None}
    rec["identified"] = {lp.value: {"class": i.class_index, "model": i.model.as_dict(),
                                    "Kc": i.gains.Kc, "Kd": i.gains.Kd, "probs": _probs(i)}
                         for lp, i in identified.items()}
    if outcome is not None:
        rec["max_tilt_deg"] = src.max_tilt
        return _end(rec, outcome, reason)
    assert monitor is not None
    # write-back, as the tool does: re-target the GCS delay measured from the ages and the
    # link's round trip (what TIMESYNC times here), robustly; side loops behind the written
    # attitude gains; clamp
    written, delays, rts = {}, {}, {}
    # the structure's filters as the tool reads them: the names the vehicle has
    read = {n: ap.params[n] for n in (*TARGET_FILTER_PARAMS.values(), *D_FILTER_PARAMS.values())
            if n in ap.params}
    structure = {lp: read_structure(lp, read, prof.family.value) for lp in identified}
    # the position loop's rate as the tool reads it (flight/onboard.vehicle_position_rate)
    pos_rate = vehicle_position_rate(
        lambda n: ap.params[n] if n in ap.params else None, prof.family.value)
    rec["position_loop_read"] = pos_rate.as_dict()
    # the models the written gains are designed on: roll and pitch with their fast lags pooled
    design = dict(identified)
    if Loop.ROLL in design and Loop.PITCH in design:
        design[Loop.ROLL], design[Loop.PITCH] = pooled_attitude(design[Loop.ROLL],
                                                                design[Loop.PITCH])
    for lp, ident in design.items():
        snap = seq.loops[lp].snapshot
        t0, t1 = (float(snap.t_s[0]), float(snap.t_s[-1])) if snap is not None and len(
            snap.t_s) else (math.inf, -math.inf)
        ta = [(t, age) for t, age in ages[lp is Loop.ALTITUDE] if t0 <= t <= t1]
        gcs = measure_gcs_delay([a for _, a in ta], 1.0 / RATE_HZ,
                                sample_t_s=[t for t, _ in ta], round_trip_s=rtt * 1e-3)
        rts[lp] = structured_retarget(ident, robust_onboard_gains(
            ident, gcs, onboard_extra_s=onboard_extra_delay_s(lp, pos_rate.hz)), structure[lp])
        delays[lp], written[lp] = rts[lp].delay_s, rts[lp].gains
    side = [lp for lp, inner_lp in SIDE_INNER.items() if lp in identified and inner_lp in rts]
    shared = shared_side_gains(
        [SideLoop(identified[lp], design[SIDE_INNER[lp]], rts[SIDE_INNER[lp]],
                  structure[SIDE_INNER[lp]].target_hz, structure[SIDE_INNER[lp]].d_hz)
         for lp in side], onboard_extra_s=onboard_extra_delay_s(Loop.X, pos_rate.hz))
    for i, lp in enumerate(side):
        written[lp] = shared[i].gains
    rec["retarget_delay_ms"] = {lp.value: d * 1e3 for lp, d in delays.items()}
    # what the re-target was measured as (benchmarks/structure_loss.py re-designs from these)
    rec["gcs_delay_measured_ms"] = {lp.value: {
        "estimate": rt.gcs.estimate_s * 1e3, "lo": rt.gcs.lo_s * 1e3, "hi": rt.gcs.hi_s * 1e3,
        "measured": rt.gcs.measured, "round_trip": rt.gcs.round_trip_s * 1e3}
        for lp, rt in rts.items()}
    ranged = params_in_range(prof, {lp: PDGains(g.Kc, g.Kd) for lp, g in written.items()}, hover)
    rec["notes"] += list(ranged.notes)
    values = {**ranged.values, **rate_d_values(
        prof, ranged.gains, {lp: rt.d_over_p_s for lp, rt in rts.items()})}
    refused = [n for n, val in values.items() if not ap.params.set(n, val)]
    if refused:
        return _end(rec, "refused", f"parameters did not stick: {refused}")
    rec["written"] = dict(values)
    # hand-over: position mode on the written gains, the stream stops, a short hover check
    src.set_mode(VehicleMode.POSITION)
    held = None
    worst = 0.0
    t_end = v.time_s + HOVER_CHECK_S
    while v.time_s < t_end:
        s = src.next_state()
        why = monitor.violation(s, duration=False)
        if why is not None:
            outcome, reason = "aborted", f"on the written gains in POSCTL: {why}"
            break
        here = (s.x_m, s.y_m, s.z_up_m)
        held = held or here
        worst = max(worst, math.dist(here, held))
    rec["hover_error_m"] = worst
    rec["max_tilt_deg"] = src.max_tilt
    _score(rec, af, dict(ap.params.values), {lp: i.gains for lp, i in identified.items()},
           list(identified))
    return _end(rec, outcome or "completed", reason)


def run_live(seed: int) -> dict:
    """One tune of the random vehicle of ``seed`` by the real tool over loopback UDP."""
    from mrft_gcs.flight import tune
    from mrft_gcs.sitl import SitlProcess

    af = random_airframe(seed)
    rec = _head(af, seed, "live")
    r = None
    with tempfile.TemporaryDirectory() as d, SitlProcess(random_seed=seed, port=None) as sitl:
        try:
            r = tune(sitl.connection_string, "sitl", backup_dir=d)
            outcome, reason = ("completed", None) if r.status == "ok" else ("aborted", r.status)
        except SafetyAbort as err:
            r, outcome, reason = err.partial_result, "aborted", str(err)
        except MrftError as err:
            r, outcome, reason = err.partial_result, "refused", str(err)
    if r is None:
        return _end(rec, outcome, reason)
    rec["time_to_tune_s"] = _num(r.duration_s)
    rec["max_tilt_deg"] = _num(r.max_tilt_deg)
    rec["max_tilt_by_phase"] = {k: _num(x) for k, x in r.max_tilt_by_phase.items()}
    rec["notes"] = list(r.notes)
    if r.position_loop is not None:
        rec["position_loop_read"] = r.position_loop.as_dict()
    rec["stream"] = r.stream.line() if r.stream is not None else None
    rec["hover_error_m"] = _num(r.hover_error_m)
    rec["verification"] = {
        lp.value: {"passed": v.passed, "predicted_pm_deg": _num(v.predicted_pm_deg),
                   "measured_pm_deg": _num(v.measured_pm_deg), "action": v.action}
        for lp, lr in r.loops.items() if (v := lr.verification) is not None}
    identified = {lp: lr.identification for lp, lr in r.loops.items()
                  if lr.identification is not None}
    rec["identified"] = {lp.value: {"class": i.class_index, "model": i.model.as_dict(),
                                    "Kc": i.gains.Kc, "Kd": i.gains.Kd, "probs": _probs(i)}
                         for lp, i in identified.items()}
    if r.parameters:
        params = dict(ParamStore(af.hover_thrust * af.hover_estimate_factor, af.onboard).values)
        params.update({c.name: c.new for c in r.parameters})
        rec["written"] = {c.name: c.new for c in r.parameters}
        loops = [lp for lp in identified if lp in (Loop.ROLL, Loop.PITCH, Loop.ALTITUDE)
                 or lp in SIDE_INNER]
        _score(rec, af, params, {lp: i.gains for lp, i in identified.items()}, loops)
    return _end(rec, outcome, reason)


def _head(af, seed: int, mode: str) -> dict:
    check = domain_check(af)
    return {"seed": seed, "mode": mode, "vehicle": af.name, "description": af.description,
            "category": check.category, "domain_reasons": list(check.reasons),
            "effects": af.effects.active(), "mass_kg": af.mass_kg,
            "onboard": {"style": af.onboard.style, "loop_hz": af.onboard.loop_hz,
                        "position_loop_hz": af.onboard.position_loop_hz},
            "link_delay_ms": af.link_delay_s * 1e3, "telemetry_hz": af.telemetry_max_hz,
            "gcs_delay_ms": gcs_delay_s(af) * 1e3, "load_1min": os.getloadavg()[0]}


def _end(rec: dict, outcome: str, reason: str | None) -> dict:
    rec["outcome"], rec["reason"] = outcome, reason
    return rec


def _score(rec: dict, af, params: dict, identified_pd: dict, loops) -> None:
    """J and PM of every written loop on the onboard truth, GCS-side figures beside."""
    wanted = [lp for lp in (Loop.ROLL, Loop.PITCH, Loop.ALTITUDE, Loop.X, Loop.Y)
              if lp in loops and (lp not in SIDE_INNER or SIDE_INNER[lp] in identified_pd)]
    sc = score_written(af, params, wanted, identified=identified_pd,
                       gcs_delay_s=gcs_delay_s(af), floor=True)
    rec["loops"] = {lp.value: {
        "onboard_J_pct": _num(s.onboard.J_pct) if s.onboard.stable else None,
        "onboard_pm_deg": _num(s.onboard.pm_deg), "onboard_stable": s.onboard.stable,
        # the best the autopilot's own structure allows (J vs the ideal PD), and the written
        # gains against it (mrft_gcs.flight.scoring.structure_floor)
        "structure_floor_J_pct": _num(s.floor.J_pct) if s.floor else None,
        "onboard_J_vs_structure_pct": _num(s.J_vs_floor_pct) if s.onboard.stable else None,
        "gcs_J_pct": _num(s.gcs.J_pct) if s.gcs and s.gcs.stable else None,
        "gcs_pm_deg": _num(s.gcs.pm_deg) if s.gcs else None}
        for lp, s in sc.items()}


def line(r: dict) -> str:
    head = (f"seed {r['seed']:3d} {r['category']:13s} {r['outcome']:9s} "
            f"{r['onboard']['style']:9s} {r['onboard']['loop_hz']:4.0f} Hz, "
            f"{r['mass_kg'] * 1e3:5.0f} g")
    if r["outcome"] != "completed" and "loops" not in r:
        tilt = r.get("max_tilt_deg")
        return f"{head}: {r['reason']}" + (f" (tilt {tilt:.1f} deg)" if tilt else "")
    loops = " ".join(
        f"{k} {_f(v['onboard_J_pct'], '5.1f')}%/{_f(v['onboard_pm_deg'], '4.1f')}deg"
        f" (gcs {_f(v['gcs_J_pct'], '.1f')}/{_f(v['gcs_pm_deg'], '.1f')})"
        for k, v in r.get("loops", {}).items())
    t = r.get("time_to_tune_s")
    return (f"{head}: {_f(t, '5.2f')} s, tilt {_f(r.get('max_tilt_deg'), '4.1f')} deg; "
            f"onboard J/PM {loops}" + (f"  [{r['reason']}]" if r.get("reason") else ""))


def _f(x, fmt: str) -> str:
    return "unst" if x is None else format(x, fmt)


def summary(recs: list[dict]) -> list[str]:
    out = []
    by = collections.Counter((r["category"], r["outcome"]) for r in recs)
    for cat in ("in-domain", "hidden-effect", "out-of-domain"):
        n = sum(v for (c, _), v in by.items() if c == cat)
        if n:
            out.append(f"{cat}: {n} vehicles: " + ", ".join(
                f"{by[(cat, o)]} {o}" for o in ("completed", "refused", "aborted")))
    done = [r for r in recs if r["outcome"] == "completed"]
    tt = [r["time_to_tune_s"] for r in done if r.get("time_to_tune_s") is not None]
    if tt:
        out.append(f"time from take-off to all loops tuned: mean {np.mean(tt):.1f} s, "
                   f"max {max(tt):.1f} s, {sum(t <= 15 for t in tt)}/{len(tt)} within 15 s")
    pt = [r["phase_times_s"] for r in done if r.get("phase_times_s")
          and all(r["phase_times_s"].get(k) is not None for k in ("takeoff", "inner", "side"))]
    if pt:
        # where it went: the climb, the rest of the inner tests after it, the side tests
        parts = {"take-off": [p["takeoff"] for p in pt],
                 "inner after take-off": [p["inner"] - p["takeoff"] for p in pt],
                 "side": [p["side"] for p in pt]}
        out.append("time by phase (mean/max s): " + ", ".join(
            f"{k} {np.mean(v):.1f}/{max(v):.1f}" for k, v in parts.items()))
    loops = [(r["seed"], k, v) for r in recs for k, v in r.get("loops", {}).items()]
    if loops:
        pm = [v["onboard_pm_deg"] for _, _, v in loops if v["onboard_pm_deg"] is not None]
        js = [v["onboard_J_pct"] for _, _, v in loops]
        unst = sum(j is None for j in js)
        ok = [j for j in js if j is not None]
        out.append(f"written loops on the onboard truth: {len(loops)}; PM min {min(pm):.1f} "
                   f"deg, {sum(p < 15 for p in pm)} under 15 deg; J max "
                   f"{max(ok, default=math.nan):.1f} %, {sum(j > 10 for j in ok)} over 10 %, "
                   f"{unst} unstable")
        fl = [v.get("structure_floor_J_pct") for _, _, v in loops]
        js = [v.get("onboard_J_vs_structure_pct") for _, _, v in loops]
        if any(f is not None for f in fl):
            fs = [f for f in fl if f is not None]
            ok = [j for j in js if j is not None]
            out.append(f"against the best of each autopilot's own structure (its floor: J "
                       f"0-{max(fs):.1f} % vs the ideal PD, {sum(f > 0 for f in fs)} loops with "
                       f"a floor above 0): J max {max(ok, default=math.nan):.1f} %, "
                       f"{sum(j > 10 for j in ok)} over 10 %")
        gp = [v["gcs_pm_deg"] for _, _, v in loops if v["gcs_pm_deg"] is not None]
        gj = [v["gcs_J_pct"] for _, _, v in loops if v["gcs_pm_deg"] is not None]
        if gp:
            out.append(f"the same loops GCS-side (identified PD, GCS delay): PM min "
                       f"{min(gp):.1f} deg, {sum(p < 15 for p in gp)} under 15 deg; J max "
                       f"{max((j for j in gj if j is not None), default=math.nan):.1f} %")
    pairs = [(v["measured_pm_deg"], r["loops"][k]["onboard_pm_deg"]) for r in recs
             for k, v in r.get("verification", {}).items()
             if v["measured_pm_deg"] is not None and k in r.get("loops", {})
             and r["loops"][k]["onboard_pm_deg"] is not None]
    if pairs:
        err = [abs(m - t) for m, t in pairs]
        redone = sum("re-designed" in v["action"] for r in recs
                     for v in r.get("verification", {}).values())
        out.append(f"in-air check: {len(pairs)} loops measured, |measured - onboard truth| PM "
                   f"mean {np.mean(err):.1f} deg, max {max(err):.1f} deg, "
                   f"{sum(e <= 3 for e in err)}/{len(err)} within 3 deg; {redone} re-designed")
        pred = [abs(v["measured_pm_deg"] - v["predicted_pm_deg"]) for r in recs
                for v in r.get("verification", {}).values()
                if v["measured_pm_deg"] is not None and v["predicted_pm_deg"] is not None]
        if pred:
            out.append(f"in-air check, measured vs predicted PM (the gains kept): |difference| "
                       f"mean {np.mean(pred):.1f} deg, max {max(pred):.1f} deg, "
                       f"{sum(e <= 3 for e in pred)}/{len(pred)} within 3 deg")
    tilts = [r["max_tilt_deg"] for r in recs if r.get("max_tilt_deg") is not None]
    if tilts:
        out.append(f"largest tilt {max(tilts):.1f} deg; {sum(t > 35 for t in tilts)} vehicles "
                   f"over 35 deg")
    ind = [r for r in recs if r["category"] == "in-domain"]
    ood = [r for r in recs if r["category"] == "out-of-domain"]
    out.append(f"in-domain tuned: {sum(r['outcome'] == 'completed' for r in ind)}/{len(ind)}; "
               f"out-of-domain refused cleanly: {sum(r['outcome'] == 'refused' for r in ood)}"
               f"/{len(ood)}")
    return out


class CpuHog:
    """Busy-looping processes beside the benchmark, each ending by itself after
    ``limit_s`` and killed (by their own pids) when the block ends; ``nice`` as a build job
    started with ``nice`` would be (10), 0 for an equal share."""

    def __init__(self, procs: int, limit_s: float, nice: int = 10) -> None:
        self.procs, self.limit_s, self.nice = procs, limit_s, nice
        self._p: list[subprocess.Popen] = []

    def __enter__(self) -> CpuHog:
        code = f"import time\nend = time.monotonic() + {self.limit_s!r}\n" \
               "while time.monotonic() < end:\n    sum(range(1000))\n"
        self._p = [subprocess.Popen(["nice", "-n", str(self.nice), sys.executable, "-c", code])
                   for _ in range(self.procs)]
        return self

    def __exit__(self, *exc: object) -> None:
        for p in self._p:
            if p.poll() is None:
                p.kill()
            p.wait()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=40)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--mode", choices=("lockstep", "live"), default="lockstep")
    ap.add_argument("--with-hog", action="store_true",
                    help="run busy-looping processes beside the tunes (killed at the end)")
    ap.add_argument("--hog-procs", type=int, default=2)
    ap.add_argument("--hog-nice", type=int, default=10,
                    help="niceness of the hog (10: a build started with nice; 0: equal share)")
    ap.add_argument("--in-domain-only", action="store_true",
                    help="tune only the seeds whose vehicle is in Table I's domain")
    ap.add_argument("--stalls", default=None, metavar="MS,EVERY_S",
                    help="lockstep: ground-station stalls of up to MS ms about every EVERY_S s "
                         "(PeriodicStalls; the vehicle keeps the last set point)")
    ap.add_argument("--json", type=Path, default=DEFAULT_JSON)
    args = ap.parse_args()
    if args.seeds < 1 or args.first_seed < 0 or args.hog_procs < 1:
        ap.error("--seeds and --hog-procs must be >= 1, --first-seed >= 0")
    stalls = tuple(float(x) for x in args.stalls.split(",")) if args.stalls else None
    if stalls is not None and (args.mode != "lockstep" or len(stalls) != 2):
        ap.error("--stalls MS,EVERY_S is for --mode lockstep")
    how = ("lockstep: the tool's sequence, classifiers and write-back on the in-process "
           "vehicle in simulated time" if args.mode == "lockstep" else
           "live: the real tune() over loopback UDP against the SITL process, real time")
    print(f"population of {args.seeds} random vehicles (seeds {args.first_seed}-"
          f"{args.first_seed + args.seeds - 1}), {how}; CPU hog: "
          f"{f'{args.hog_procs} processes at nice {args.hog_nice}' if args.with_hog else 'none'}; "
          f"{f'stalls up to {stalls[0]:g} ms about every {stalls[1]:g} s; ' if stalls else ''}"
          f"{platform.machine()}, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f}",
          flush=True)
    run = (functools.partial(run_lockstep, stalls=stalls) if args.mode == "lockstep"
           else run_live)
    recs = []
    wall0 = time.monotonic()
    hog = (CpuHog(args.hog_procs, limit_s=120.0 * args.seeds, nice=args.hog_nice)
           if args.with_hog else None)
    try:
        if hog is not None:
            hog.__enter__()
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            if args.in_domain_only and domain_check(random_airframe(seed)).category != (
                    "in-domain"):
                continue
            t0 = time.monotonic()
            r = run(seed)
            r["wall_s"] = time.monotonic() - t0
            r["hog"] = args.with_hog
            recs.append(r)
            print(line(r), flush=True)
    finally:
        if hog is not None:
            hog.__exit__()
    for s in summary(recs):
        print(s)
    print(f"wall time {time.monotonic() - wall0:.0f} s")
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps({"mode": args.mode, "hog": args.with_hog,
                                     "hog_nice": args.hog_nice if args.with_hog else None,
                                     "seeds": [args.first_seed, args.seeds],
                                     "in_domain_only": args.in_domain_only,
                                     "stalls": args.stalls, "runs": recs},
                                    indent=1))
    print(f"records: {args.json}")


if __name__ == "__main__":
    main()
