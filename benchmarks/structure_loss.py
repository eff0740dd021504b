"""Where the J of written gains goes: structure, robust hold-back, cap, identification.

For the written loops of a lockstep population record (``benchmarks/tune_population.py``),
in-process and without flying, each loop's written parameters are scored on the vehicle's
true onboard loop (:func:`mrft_gcs.flight.scoring.score_written`) beside the same write-back
re-run from the record's identification with one of its cautions lifted at a time:

* ``floor``: the best two written numbers on the true onboard loop and the autopilot's own
  structure (PM >= 20 deg there, :func:`mrft_gcs.flight.scoring.structure_floor`): what the
  structure itself costs against the ideal PD;
* ``no range``: the plausible GCS delay narrowed to the estimate (no hold-back for the least
  plausible delay);
* ``no cap``: no cap on the share of the identified delay a re-target may take (the range
  kept; narrowing the range lifts the cap too, as the least plausible delay is certain);
* ``at d*``: the identified model with the GCS delay the benchmark's vehicle really added
  (the link both ways, half a telemetry, a setpoint and an onboard loop period), designed as
  the tool designs it, without any robust check (roll, pitch, altitude);
* side loops: ``share 1``: the whole move to the onboard cascade (no hold-back over the
  plausible attitude delay, an unseen filter or the position loop's rate); ``gcs``: the
  identified PD on its own ground-station-side truth (the identification's error).

Each figure is ``J % / PM deg`` on the onboard truth. The cause named is the first of
structure floor (the floor itself over 8 %, the written gains within 2 % of it), robust
hold-back, cap, the GCS delay measured short of ``d*`` (at ``d*`` within the bars),
identification (what is left: even at ``d*`` over 10 % or under 15 deg) that explains J over
10 %; side loops: the side hold-back (``share 1`` within the bars), the side identification
(its own GCS-side J over 5 %), else the side re-design.

    .venv/bin/python benchmarks/structure_loss.py [--json RECORDS] [--all] [SEED ...]
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import json
import math
from pathlib import Path

from mrft_gcs.flight.onboard import (
    POSITION_LOOP_MIN_HZ,
    GcsDelay,
    Retarget,
    onboard_extra_delay_s,
    onboard_side_gains,
    robust_onboard_gains,
)
from mrft_gcs.flight.scoring import score_written
from mrft_gcs.flight.structure import (
    D_FILTER_PARAMS,
    TARGET_FILTER_PARAMS,
    OnboardStructure,
    rate_d_values,
    read_structure,
    structured_retarget,
)
from mrft_gcs.identify import Identification
from mrft_gcs.loops import SIDE_INNER, Loop, LoopKind
from mrft_gcs.plant import PD, InnerModel, SideModel
from mrft_gcs.profiles import PDGains, load_profile, params_in_range
from mrft_gcs.sitl import random_airframe
from mrft_gcs.sitl.onboard import ParamStore

DEFAULT = Path(__file__).resolve().parent / "results" / "population_lockstep.json"
RATE_HZ = 250.0
_KIND = {Loop.ROLL: LoopKind.ATTITUDE, Loop.PITCH: LoopKind.ATTITUDE,
         Loop.ALTITUDE: LoopKind.ALTITUDE, Loop.X: LoopKind.SIDE, Loop.Y: LoopKind.SIDE}


def _ident(rec: dict, loop: Loop) -> Identification:
    i = rec["identified"][loop.value]
    m = (SideModel(**i["model"]) if loop in SIDE_INNER else InnerModel(**i["model"]))
    return Identification(_KIND[loop], m, i["class"], 1.0, -0.8, 0.1, 0.25, 0.03,
                          PD(i["Kc"], i["Kd"]))


def _params(af, rec: dict, gains: dict[Loop, PD] | None = None) -> dict:
    p = dict(ParamStore(af.hover_thrust * af.hover_estimate_factor, af.onboard).values)
    p.update(rec["written"])
    if gains:
        prof = load_profile("sitl")
        ranged = params_in_range(prof, {lp: PDGains(g.Kc, g.Kd) for lp, g in gains.items()},
                                 p["MPC_THR_HOVER"])
        p.update(ranged.values)
        # rate D as the tool writes it beside re-designed attitude gains
        p.update(rate_d_values(prof, ranged.gains, {lp: _structure(af, lp).d_over_p_s
                                                    for lp in gains}))
    return p


def true_gcs_delay_s(af) -> float:
    """The GCS delay the benchmark's vehicle adds (as ``tune_population.gcs_delay_s``)."""
    tel = min(RATE_HZ, af.telemetry_max_hz)
    return 2 * af.link_delay_s + 0.5 / tel + 0.5 / RATE_HZ + 0.5 / af.onboard.loop_hz


def _structure(af, loop: Loop) -> OnboardStructure:
    if loop in (Loop.ROLL, Loop.PITCH) and af.onboard.style == "ardupilot":
        return read_structure(loop, {TARGET_FILTER_PARAMS[loop]: af.onboard.target_cutoff_hz,
                                     D_FILTER_PARAMS[loop]: af.onboard.dgyro_cutoff_hz})
    return OnboardStructure()


def _inner_rt(rec: dict, af, loop: Loop, *, narrow: bool = False, nocap: bool = False,
              at_s: float | None = None) -> Retarget:
    """The write-back of ``loop`` as the tool does it, from the record; ``narrow``: the
    plausible range narrowed to the estimate (the cap follows); ``nocap``: no cap, the
    range kept; ``at_s``: the
    estimate replaced by that delay, no robust check."""
    ident = _ident(rec, loop)
    g = rec["gcs_delay_measured_ms"][loop.value]
    gcs = GcsDelay(g["estimate"] * 1e-3, g["lo"] * 1e-3, g["hi"] * 1e-3, math.nan,
                   g["measured"], "", g["round_trip"] * 1e-3)
    # the position loop's rate the benchmark read from the vehicle (older records: none)
    extra = onboard_extra_delay_s(loop, (rec.get("position_loop_read") or {}).get(
        "hz", POSITION_LOOP_MIN_HZ))
    kw: dict = {}
    if at_s is not None:
        gcs = dataclasses.replace(gcs, estimate_s=at_s, lo_s=at_s)
        kw = {"pm_min_deg": -math.inf, "cap_share": 1.0, "certain_share": 1.0}
        extra = 0.0
    elif narrow:
        gcs = dataclasses.replace(gcs, lo_s=gcs.estimate_s)
    elif nocap:
        kw = {"cap_share": 1.0, "certain_share": 1.0}
    rt = robust_onboard_gains(ident, gcs, onboard_extra_s=extra, **kw)
    return structured_retarget(ident, rt, _structure(af, loop))


def _fig(af, rec: dict, loop: Loop, gains: dict[Loop, PD] | None = None) -> tuple[float, float]:
    s = score_written(af, _params(af, rec, gains), [loop])[loop].onboard
    return (s.J_pct if s.stable else math.inf), s.pm_deg


def breakdown(rec: dict, loop: Loop) -> dict:
    """The figures of one written loop (``J %, PM deg`` each) and the cause named."""
    af = random_airframe(rec["seed"])
    sc = score_written(af, _params(af, rec), [loop], floor=True)[loop]
    out: dict = {"written": (sc.onboard.J_pct, sc.onboard.pm_deg),
                 "floor": (sc.floor.J_pct, sc.floor.pm_deg) if sc.floor else None}
    if loop in SIDE_INNER:
        inner = SIDE_INNER[loop]
        irt = _inner_rt(rec, af, inner)
        side = onboard_side_gains(_ident(rec, loop), _ident(rec, inner), irt,
                                  pm_min_deg=-math.inf,
                                  target_hz=_structure(af, inner).target_hz)
        out["share 1"] = _fig(af, rec, loop, {loop: side.gains})
        lp = rec["loops"][loop.value]
        out["gcs"] = (lp["gcs_J_pct"] if lp["gcs_J_pct"] is not None else math.inf,
                      lp["gcs_pm_deg"])
    else:
        for name, kw in (("no range", {"narrow": True}), ("no cap", {"nocap": True}),
                         ("at d*", {"at_s": true_gcs_delay_s(af)})):
            out[name] = _fig(af, rec, loop, {loop: _inner_rt(rec, af, loop, **kw).gains})
    out["cause"] = _cause(out)
    return out


def _cause(f: dict) -> str:
    j = f["written"][0]
    if not j > 10:
        return ""
    fl = f["floor"]
    if fl is not None and fl[0] > 8 and (1 + j / 100) / (1 + fl[0] / 100) < 1.02:
        return "structure floor"
    if "share 1" in f:
        if f["share 1"][0] <= 10 and f["share 1"][1] >= 15:
            return "side hold-back"
        return "side identification" if f["gcs"][0] > 5 else "side re-design"
    if f["no range"][0] <= 10 and f["no range"][1] >= 15:
        return "robust hold-back (plausible range)"
    if f["no cap"][0] <= 10 and f["no cap"][1] >= 15:
        return "cap on the re-target"
    if f["at d*"][0] <= 10 and f["at d*"][1] >= 15:
        return "GCS delay measured short"
    if fl is not None and fl[0] > 8:
        return "structure floor + identification"
    return "identification"


def _fmt(x) -> str:
    if x is None:
        return "-"
    j, pm = x
    return f"{j:5.1f}/{pm:4.1f}" if math.isfinite(j) else f"unst/{pm:4.1f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seeds", type=int, nargs="*", help="default: every seed in the record")
    ap.add_argument("--json", type=Path, default=DEFAULT)
    ap.add_argument("--all", action="store_true", help="every written loop, not only J > 10 %")
    args = ap.parse_args()
    recs = {r["seed"]: r for r in json.loads(args.json.read_text())["runs"]}
    if any("gcs_delay_measured_ms" not in r for r in recs.values() if "written" in r):
        ap.error(f"{args.json} has no measured GCS delays: re-run tune_population.py")
    causes: collections.Counter = collections.Counter()
    for seed in args.seeds or sorted(recs):
        rec = recs.get(seed)
        if rec is None or "written" not in rec:
            if args.seeds:
                print(f"seed {seed}: no written gains in {args.json}")
            continue
        for key, v in rec.get("loops", {}).items():
            j = v["onboard_J_pct"]
            if not args.all and j is not None and j <= 10:
                continue
            f = breakdown(rec, Loop(key))
            causes[(rec["category"], f["cause"])] += bool(f["cause"])
            rest = "  ".join(f"{k} {_fmt(x)}" for k, x in f.items()
                             if k not in ("written", "floor", "cause"))
            print(f"seed {seed:2d} {rec['category'][:13]:13s} {rec['onboard']['style'][:4]} "
                  f"link {rec['link_delay_ms']:4.1f} ms {key:8s} written {_fmt(f['written'])}  "
                  f"floor {_fmt(f['floor'])}  {rest}  -> {f['cause'] or 'ok'}")
    print("causes of J over 10 %: " + ", ".join(
        f"{n} {cause} ({cat})" for (cat, cause), n in sorted(causes.items()) if n))


if __name__ == "__main__":
    main()
