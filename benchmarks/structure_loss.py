"""Where the J of written roll/pitch gains goes: structure, delay left in, identification.

For each seed of a population record (``benchmarks/tune_population.py``), in-process and
without flying: the loop's identified model and the written gains from the record, scored on
the vehicle's true onboard loop (:func:`mrft_gcs.flight.scoring.score_written`) beside

* ``floor``: the best two written gains on the true onboard loop (PM >= 20 deg there): what the
  controller structure itself allows;
* ``true PD``: the optimal PD of the true onboard process, written as a PD (structure ignored);
* ``id+st@d``: designed on the identified model with the written re-target ``d`` and the
  structure (:func:`mrft_gcs.flight.structure.structured_pd`);
* ``id+st@d*``: the same with the GCS delay the benchmark's vehicle really added (``d*``: the
  link both ways, half a telemetry and a setpoint period, the physics step).

Each is ``J % / PM deg`` on the onboard truth.

    .venv/bin/python benchmarks/structure_loss.py [--json RECORDS] SEED [SEED ...]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from mrft_gcs.flight.scoring import onboard_process, score_written
from mrft_gcs.flight.structure import OnboardStructure, structured_pd
from mrft_gcs.loops import Loop
from mrft_gcs.pd_design import frequency_grid, optimal_pd
from mrft_gcs.plant import PD, InnerModel, inner_response
from mrft_gcs.profiles import PDGains, load_profile, params_in_range
from mrft_gcs.sitl import random_airframe
from mrft_gcs.sitl.onboard import ParamStore

DEFAULT = Path(__file__).resolve().parent / "results" / "population_lockstep.json"
RATE_HZ = 250.0


def _params(af, rec: dict, loop: Loop | None = None, g: PD | None = None) -> dict:
    p = dict(ParamStore(af.hover_thrust * af.hover_estimate_factor, af.onboard).values)
    p.update(rec["written"])
    if loop is not None and g is not None:
        p.update(params_in_range(load_profile("sitl"), {loop: PDGains(g.Kc, g.Kd)},
                                 p["MPC_THR_HOVER"]).values)
    return p


def _on_truth(af, rec: dict, loop: Loop, g: PD | None = None) -> str:
    s = score_written(af, _params(af, rec, loop, g), [loop])[loop].onboard
    return f"{s.J_pct:5.1f}/{s.pm_deg:4.1f}"


def decompose(rec: dict, loop: Loop) -> str:
    af = random_airframe(rec["seed"])
    st = OnboardStructure(af.onboard.target_cutoff_hz if af.onboard.style == "ardupilot"
                          else 0.0)
    G, w = onboard_process(af, loop, _params(af, rec))
    floor = structured_pd(G, w, st, worst=()).gains
    m = InnerModel(**rec["identified"][loop.value]["model"])
    tel = min(RATE_HZ, af.telemetry_max_hz)
    d_true = 2 * af.link_delay_s + 0.5 / tel + 0.5 / RATE_HZ + 0.0005
    d_w = rec["retarget_delay_ms"][loop.value] * 1e-3

    def on_id(d: float) -> PD:
        tau = max(m.tau - d, 1e-4)
        wi = frequency_grid(m.T_prop, m.T1, tau)
        return structured_pd(inner_response(m.K, m.T_prop, m.T1, tau, wi)[0], wi, st).gains

    return (f"written {_on_truth(af, rec, loop)}  floor {_on_truth(af, rec, loop, floor)}  "
            f"true PD {_on_truth(af, rec, loop, optimal_pd(G, w).pd)}  "
            f"id+st@d {_on_truth(af, rec, loop, on_id(d_w))} (d {d_w * 1e3:.1f} ms)  "
            f"id+st@d* {_on_truth(af, rec, loop, on_id(d_true))} (d* {d_true * 1e3:.1f} ms; "
            f"tau identified {m.tau * 1e3:.1f} ms)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seeds", type=int, nargs="+")
    ap.add_argument("--json", type=Path, default=DEFAULT)
    args = ap.parse_args()
    recs = {r["seed"]: r for r in json.loads(args.json.read_text())["runs"]}
    for seed in args.seeds:
        rec = recs.get(seed)
        if rec is None or "written" not in rec:
            print(f"seed {seed}: no written gains in {args.json}")
            continue
        ob = rec["onboard"]
        print(f"seed {seed} ({rec['category']}, {ob['style']}-like, link "
              f"{rec['link_delay_ms']:.1f} ms): J %/PM deg on the onboard truth")
        for loop in (Loop.ROLL, Loop.PITCH):
            if loop.value in rec.get("loops", {}):
                print(f"  {loop.value:5s} {decompose(rec, loop)}")


if __name__ == "__main__":
    main()
