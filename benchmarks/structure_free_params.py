"""What the ArduPilot-like structure could reach with more of its own parameters free.

The tool writes two numbers per attitude loop (angle P, rate P; rate I = D = FF = 0). The
structure floor (:func:`mrft_gcs.flight.scoring.structure_floor`) searches those two on the
vehicle's true onboard loop under phase margin 20 deg. This diagnostic searches, for the
ArduPilot-style roll and pitch loops of a lockstep population record
(``benchmarks/tune_population.py``), the same two numbers with the rate loop's D and/or FF
free too, under phase margin 20 and 15 deg, and prints each optimum as ``J % / PM deg``
against the ideal PD (PM 20) of the same truth: whether the floor is the structure's or the
tool's choice of parameters. Linear and noise-free: D's gain on gyro noise is not weighed.

    .venv/bin/python benchmarks/structure_free_params.py [--json RECORDS] [SEED ...]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from scipy.optimize import minimize

from mrft_gcs.flight import scoring
from mrft_gcs.loops import Loop
from mrft_gcs.pd_design import margins, optimal_pd
from mrft_gcs.sitl import SimVehicle, random_airframe

DEFAULT_JSON = Path(__file__).resolve().parent / "results" / "population_lockstep.json"
FREE_SETS: tuple[tuple[str, ...], ...] = ((), ("D/P",), ("D",), ("FF",), ("D", "FF"))
#: ArduCopter's default rate D over rate P (ATC_RAT_RLL_D / ATC_RAT_RLL_P, s): ``D/P`` holds
#: D at that share of the searched rate P, a D that default tunes fly with their noise
DEFAULT_D_OVER_P_S = 0.0036 / 0.135


def search(af, loop: Loop, params: dict, pm_min_deg: float, free: tuple[str, ...]
           ) -> tuple[float, float, dict[str, float]]:
    """``(J %, PM deg, free values)`` of the ISE-optimal angle P, rate P and ``free``."""
    axis = scoring._AXIS[loop]
    pre = f"MC_{axis}RATE"
    G, w = scoring.onboard_process(af, loop, params)
    best = optimal_pd(G, w)

    def unpack(x: np.ndarray) -> dict[str, float]:
        p = dict(params)
        p[f"MC_{axis}_P"], p[f"{pre}_P"] = float(np.exp(x[0])), float(np.exp(x[1]))
        for i, k in enumerate(k for k in free if k != "D/P"):  # D > 0 (log), FF either sign
            p[f"{pre}_{k}"] = float(np.exp(x[2 + i])) if k == "D" else float(x[2 + i])
        if "D/P" in free:
            p[f"{pre}_D"] = DEFAULT_D_OVER_P_S * p[f"{pre}_P"]
        return p

    def figures(x: np.ndarray) -> tuple[float, float]:
        Cr, Cy = scoring.onboard_controller(af, loop, unpack(x), w)
        m = margins(Cy * G, w)
        return (scoring.general_ise(Cr, Cy, G, w), float(m.pm_deg)) if m.stable else \
            (np.inf, -np.inf)

    def cost(x: np.ndarray) -> float:
        q, pm = figures(x)
        short = max(0.0, pm_min_deg - pm)
        return q * (1 + 0.05 * short + 0.02 * short ** 2 + 0.5 * short ** 3) \
            if np.isfinite(q) else 1e12

    starts = []
    for kc, kd in ((best.pd.Kc, best.pd.Kd), (0.8 * best.pd.Kc, best.pd.Kd)):
        starts.append([np.log(kc / kd), np.log(kd)]
                      + [np.log(1e-3 * kd) if k == "D" else 0.0 for k in free if k != "D/P"])
    res = min((minimize(cost, np.array(x0), method="Nelder-Mead",
                        options={"maxiter": 3000, "xatol": 1e-5, "fatol": 1e-10})
               for x0 in starts), key=lambda r: r.fun)
    q, pm = figures(res.x)
    p = unpack(res.x)
    return (q - best.ise) / best.ise * 100.0, pm, {k: p[f"{pre}_{k.split('/')[0]}"] for k in free}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", type=Path, default=DEFAULT_JSON, help="population record")
    ap.add_argument("seeds", type=int, nargs="*", help="seeds (default: every ArduPilot one)")
    args = ap.parse_args()
    runs = {r["seed"]: r for r in json.loads(args.json.read_text())["runs"]}
    for seed in args.seeds or sorted(runs):
        r = runs[seed]
        af = random_airframe(seed)
        if af.onboard.style != "ardupilot" or "written" not in r or "loops" not in r:
            continue
        params = dict(SimVehicle(af, seed=seed).autopilot.params.values)
        params.update(r["written"])
        for loop in (Loop.ROLL, Loop.PITCH):
            got = r["loops"].get(loop.value)
            if not got or got.get("onboard_J_pct") is None:
                continue
            cells = []
            for pm_min in (20.0, 15.0):
                for free in FREE_SETS:
                    J, pm, vals = search(af, loop, params, pm_min, free)
                    what = "+".join(free) or "2 numbers"
                    extra = " ".join(f"{k} {v:.4g}" for k, v in vals.items())
                    cells.append(f"PM>={pm_min:.0f} {what}: {J:6.1f}/{pm:4.1f} {extra}".rstrip())
            print(f"seed {seed:2d} {r.get('category', ''):13s} {loop.value:5s} written "
                  f"{got['onboard_J_pct']:5.1f}/{got['onboard_pm_deg']:4.1f} "
                  f"FLTT {af.onboard.target_cutoff_hz:4.1f} Hz", flush=True)
            for c in cells:
                print("    " + c, flush=True)


if __name__ == "__main__":
    main()
