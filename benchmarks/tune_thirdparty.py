"""Benchmark: tune vehicles whose physics comes from a third-party simulator (RotorPy).

Each vehicle is ``python -m mrft_gcs.sitl --physics rotorpy`` as a real process: RotorPy
3.0.0's rigid body, rotors, motor lag, rotor drag and ground contact
(:mod:`mrft_gcs.sitl.rotorpy_physics`), the project's onboard autopilot, sensors and
MAVLink. The real ``tune()`` flies it over loopback UDP in real time with
``--actuation torque`` (the ``sitl`` profile). Vehicles: RotorPy's own parameter sets as
shipped (``--sets``), then ``--seeds`` drawn ones (:func:`rotorpy_airframe` of the seed:
the sets scaled a little, the project's delays, link and onboard loops drawn).

``--mode lockstep`` runs the same vehicles through ``tune_population.py``'s lockstep driver
instead (the tool's sequence, bundled classifiers and write-back in simulated time; no host
timing, no in-air check), with the RotorPy vehicle swapped in for its random airframe: the
figures then do not depend on how busy the host is.

Outcomes as in ``tune_population.py``: ``completed`` (status ok: loops written, hover on
them held), ``refused`` (the tool stopped with an explanation), ``aborted`` (a safety limit or
the hover failed). Scores: every written loop's J (%) and phase margin on the onboard truth
(:func:`mrft_gcs.flight.scoring.score_written` on the vehicle's parameters read back over
MAVLink after the tune), where the truth is RotorPy's dynamics linearised at hover; the
GCS-side figures of the identified PD beside them; the in-air check's measured margin.

    .venv/bin/python benchmarks/tune_thirdparty.py [--sets crazyfliebrushless,...] \
        [--seeds 4] [--first-seed 0] [--mode live|lockstep] \
        [--json benchmarks/results/thirdparty.json]
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import json
import math
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

DEFAULT_JSON = Path(__file__).resolve().parent / "results" / "thirdparty.json"
RATE_HZ = 250.0  # tune()'s setpoint stream and the telemetry it asks


def gcs_delay_s(af) -> float:
    """The ground station's extra delay on the inner loops (as ``tune_population.py``)."""
    tel = min(RATE_HZ, af.telemetry_max_hz)
    return 2 * af.link_delay_s + 0.5 / tel + 0.5 / RATE_HZ + 0.5 / af.onboard.loop_hz


def _num(x) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None


def realised(af):
    """``af`` with the delays its RotorPy vehicle realises: whole physics steps (one onboard
    loop period; a delay rounded as :class:`~mrft_gcs.sitl.rotorpy_physics.RotorpyMultirotor`
    rounds it). The truth scored on must be the vehicle flown: the shipped sets' 2 ms sensor
    delay is 0 steps at 250 Hz, and scored with it the written loops read 2-3 deg less margin
    than they have (the in-air check measured them 3-5 deg above that truth in-process, 1-2
    deg above the realised one)."""
    import dataclasses

    dt = 1.0 / af.onboard.loop_hz

    def steps(s: float) -> float:
        return max(0, int(round(s / dt))) * dt

    return dataclasses.replace(
        af, actuator_delay_s=steps(af.actuator_delay_s),
        attitude_sensor_delay_s=steps(af.attitude_sensor_delay_s),
        position_sensor_delay_s=steps(af.position_sensor_delay_s))


def score(af, params: dict, identified: dict) -> dict:
    """J and PM of every written loop on the onboard truth (the delays as realised,
    :func:`realised`), GCS-side figures beside."""
    from mrft_gcs.flight.scoring import score_written
    from mrft_gcs.loops import SIDE_INNER as inner
    from mrft_gcs.loops import Loop

    loops = [lp for lp in (Loop.ROLL, Loop.PITCH, Loop.ALTITUDE, Loop.X, Loop.Y)
             if lp in identified and (lp not in inner or inner[lp] in identified)]
    sc = score_written(realised(af), params, loops, identified=identified,
                       gcs_delay_s=gcs_delay_s(af), floor=True)
    return {lp.value: {
        "onboard_J_pct": _num(s.onboard.J_pct) if s.onboard.stable else None,
        "onboard_pm_deg": _num(s.onboard.pm_deg), "onboard_stable": s.onboard.stable,
        "structure_floor_J_pct": _num(s.floor.J_pct) if s.floor else None,
        "onboard_J_vs_structure_pct": _num(s.J_vs_floor_pct) if s.onboard.stable else None,
        "gcs_J_pct": _num(s.gcs.J_pct) if s.gcs and s.gcs.stable else None,
        "gcs_pm_deg": _num(s.gcs.pm_deg) if s.gcs else None} for lp, s in sc.items()}


def run(name: str | None, seed: int | None) -> dict:
    """One live tune of a RotorPy vehicle; a JSON-able record."""
    from mrft_gcs.errors import MrftError, SafetyAbort
    from mrft_gcs.flight import tune
    from mrft_gcs.link import VehicleLink
    from mrft_gcs.params import ParamClient
    from mrft_gcs.sitl import SitlProcess, domain_check
    from mrft_gcs.sitl.rotorpy_physics import rotorpy_airframe

    spec = rotorpy_airframe(name, seed)
    af = spec.airframe
    check = domain_check(af)
    rec: dict = {"vehicle": af.name, "set": spec.name, "seed": seed,
                 "description": af.description, "category": check.category,
                 "domain_reasons": list(check.reasons), "load_1min": os.getloadavg()[0]}
    r = None
    with tempfile.TemporaryDirectory() as d, SitlProcess(
            vehicle=name, random_seed=seed, physics="rotorpy", port=None) as sitl:
        try:
            r = tune(sitl.connection_string, "sitl", actuation="torque", backup_dir=d)
            outcome, reason = ("completed", None) if r.status == "ok" else ("aborted", r.status)
        except SafetyAbort as err:
            r, outcome, reason = err.partial_result, "aborted", str(err)
        except MrftError as err:
            r, outcome, reason = err.partial_result, "refused", str(err)
        params = None
        if r is not None and r.parameters:
            with VehicleLink.connect(sitl.connection_string) as link:
                params = {n: p.value for n, p in ParamClient(link).read_all().items()}
    rec["outcome"], rec["reason"] = outcome, reason
    if r is None:
        return rec
    rec["time_to_tune_s"] = _num(r.duration_s)
    rec["max_tilt_deg"] = _num(r.max_tilt_deg)
    rec["max_tilt_by_phase"] = {k: _num(x) for k, x in r.max_tilt_by_phase.items()}
    rec["hover_error_m"] = _num(r.hover_error_m)
    rec["notes"] = list(r.notes)
    rec["verification"] = {
        lp.value: {"passed": v.passed, "predicted_pm_deg": _num(v.predicted_pm_deg),
                   "measured_pm_deg": _num(v.measured_pm_deg), "action": v.action}
        for lp, lr in r.loops.items() if (v := lr.verification) is not None}
    identified = {lp: lr.identification.gains for lp, lr in r.loops.items()
                  if lr.identification is not None}
    rec["identified"] = {lp.value: {"class": i.class_index, "model": i.model.as_dict(),
                                    "Kc": i.gains.Kc, "Kd": i.gains.Kd}
                         for lp, lr in r.loops.items() if (i := lr.identification) is not None}
    if params is not None:
        rec["written"] = {c.name: c.new for c in r.parameters}
        rec["loops"] = score(af, params, identified)
    return rec


@contextlib.contextmanager
def _lockstep_driver(spec):
    """``tune_population``'s lockstep driver with ``spec``'s RotorPy vehicle in place of the
    random airframe of a seed (its vehicle factory and airframe draw swapped, then put back)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import tune_population as tp

    from mrft_gcs.sitl.rotorpy_physics import rotorpy_vehicle

    saved = tp.random_airframe, tp.SimVehicle
    tp.random_airframe = lambda seed: realised(spec.airframe)  # scored as flown
    tp.SimVehicle = lambda af, seed=0: rotorpy_vehicle(spec, seed=seed)
    try:
        yield tp
    finally:
        tp.random_airframe, tp.SimVehicle = saved


def run_lockstep(name: str | None, seed: int | None) -> dict:
    """One tune of a RotorPy vehicle in simulated time; a JSON-able record."""
    from mrft_gcs.sitl.rotorpy_physics import rotorpy_airframe

    spec = rotorpy_airframe(name, seed)
    with _lockstep_driver(spec) as tp:
        r = tp.run_lockstep(0 if seed is None else seed)
    r.update(vehicle=spec.airframe.name, set=spec.name, seed=seed,
             description=spec.airframe.description, verification={})
    return r


def line(r: dict) -> str:
    head = f"{r['vehicle']:26s} {r['category']:13s} {r['outcome']:9s}"
    if "loops" not in r:
        tilt = r.get("max_tilt_deg")
        return f"{head}: {r['reason']}" + (f" (tilt {tilt:.1f} deg)" if tilt else "")
    loops = " ".join(f"{k} {_f(v['onboard_J_pct'], '5.1f')}%/{_f(v['onboard_pm_deg'], '4.1f')}"
                     f"deg" for k, v in r["loops"].items())
    ver = " ".join(f"{k} {v['measured_pm_deg']:.1f}" for k, v in r["verification"].items()
                   if v["measured_pm_deg"] is not None)
    return (f"{head}: {_f(r.get('time_to_tune_s'), '5.2f')} s, tilt "
            f"{_f(r.get('max_tilt_deg'), '4.1f')} deg; onboard J/PM {loops}"
            + (f"; in-air PM {ver}" if ver else "")
            + (f"  [{r['reason']}]" if r.get("reason") else ""))


def _f(x, fmt: str) -> str:
    return "unst" if x is None else format(x, fmt)


def summary(recs: list[dict]) -> list[str]:
    by = collections.Counter((r["category"], r["outcome"]) for r in recs)
    out = [f"{cat}: {n} vehicles: " + ", ".join(f"{by[(cat, o)]} {o}"
                                                for o in ("completed", "refused", "aborted"))
           for cat in ("in-domain", "out-of-domain")
           if (n := sum(v for (c, _), v in by.items() if c == cat))]
    tt = [r["time_to_tune_s"] for r in recs
          if r["outcome"] == "completed" and r.get("time_to_tune_s") is not None]
    if tt:
        out.append(f"time from take-off to all loops tuned: mean {sum(tt) / len(tt):.1f} s, "
                   f"max {max(tt):.1f} s")
    figs = [v for r in recs for v in r.get("loops", {}).values()]
    if figs:
        pm = [v["onboard_pm_deg"] for v in figs if v["onboard_pm_deg"] is not None]
        js = [v["onboard_J_pct"] for v in figs if v["onboard_J_pct"] is not None]
        out.append(f"written loops on the onboard truth: {len(figs)}; PM min {min(pm):.1f} deg, "
                   f"{sum(p < 15 for p in pm)} under 15 deg; J max {max(js):.1f} %, "
                   f"{sum(j > 10 for j in js)} over 10 %, "
                   f"{sum(not v['onboard_stable'] for v in figs)} unstable")
    tilts = [r["max_tilt_deg"] for r in recs if r.get("max_tilt_deg") is not None]
    if tilts:
        out.append(f"largest tilt {max(tilts):.1f} deg; {sum(t > 35 for t in tilts)} over 35")
    return out


def main() -> None:
    from mrft_gcs.sitl.rotorpy_physics import ROTORPY_PIN, ROTORPY_VEHICLES

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sets", default=",".join(ROTORPY_VEHICLES),
                    help="RotorPy parameter sets flown as shipped (comma-separated, or '')")
    ap.add_argument("--seeds", type=int, default=4, help="drawn vehicles after the sets")
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--mode", choices=("live", "lockstep"), default="live")
    ap.add_argument("--json", type=Path, default=DEFAULT_JSON)
    args = ap.parse_args()
    sets = [s for s in args.sets.split(",") if s]
    if args.seeds < 0 or args.first_seed < 0:
        ap.error("--seeds and --first-seed must be >= 0")
    runs = [(s, None) for s in sets] + [
        (None, k) for k in range(args.first_seed, args.first_seed + args.seeds)]
    import numpy
    import scipy

    print(f"{len(runs)} RotorPy vehicles (rotorpy {ROTORPY_PIN}, numpy {numpy.__version__}, "
          f"scipy {scipy.__version__}), "
          + ("live over loopback UDP in real time" if args.mode == "live" else
             "lockstep (tune_population's driver, simulated time)")
          + f", --actuation torque; {platform.machine()}, {os.cpu_count()} CPUs, load "
          f"{os.getloadavg()[0]:.2f}", flush=True)
    recs = []
    wall0 = time.monotonic()
    for name, seed in runs:
        t0 = time.monotonic()
        r = (run if args.mode == "live" else run_lockstep)(name, seed)
        r["wall_s"] = time.monotonic() - t0
        recs.append(r)
        print(line(r), flush=True)
    for s in summary(recs):
        print(s)
    print(f"wall time {time.monotonic() - wall0:.0f} s")
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps({"mode": args.mode, "runs": recs}, indent=1))
    print(f"records: {args.json}")


if __name__ == "__main__":
    main()
