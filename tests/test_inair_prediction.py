"""The in-air check's prediction for roll/pitch written with rate D (mrft_gcs.flight.inair).

The check compares the margin it measures with the one predicted from the identified model
and the written structure. The identified model is pinned at the relay cycle's frequency; a
crossover that D's lead carries far above it is where the model, and with it the prediction,
leaves the vehicle's loop (mrft_gcs.flight.structure.D_WC_MAX_RATIO).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import tune_population as tp  # noqa: E402

from mrft_gcs.flight.inair import (  # noqa: E402
    AGREE_DEG,
    CHECK_AMPLITUDE_RAD,
    OnboardCascade,
    plan_check,
)
from mrft_gcs.flight.structure import (  # noqa: E402
    D_WC_MAX_RATIO,
    RATE_D_OVER_P_S,
    OnboardStructure,
    relay_frequency,
    structure_controller,
    structured_pd,
)
from mrft_gcs.identify.runtime import relay_settings  # noqa: E402
from mrft_gcs.loops import LoopKind  # noqa: E402
from mrft_gcs.pd_design import frequency_grid, margins  # noqa: E402
from mrft_gcs.plant import PD, InnerModel, inner_response  # noqa: E402
from mrft_gcs.sitl import domain_check, random_airframe  # noqa: E402

_AXES = {"roll": "ROLL", "pitch": "PITCH"}


def test_rate_d_loops_are_predicted_as_the_vehicle_closes_them():
    # an in-domain ArduPilot-like vehicle tuned in simulated time; each loop's margin
    # predicted as the in-air check predicts it (api._verify_written: the identified model
    # less the re-targeted delay, the written gains, rate D and filters) against the margin
    # the vehicle's own loop has with what was written (the onboard truth)
    seed = 5
    af = random_airframe(seed)
    assert domain_check(af).category == "in-domain" and af.onboard.style == "ardupilot"
    r = tp.run_lockstep(seed)
    assert r["outcome"] == "completed", r.get("reason")
    beta = relay_settings(LoopKind.ATTITUDE).beta
    for lp, ax in _AXES.items():
        w_ = r["written"]
        kd = w_[f"MC_{ax}RATE_P"]
        assert w_[f"MC_{ax}RATE_D"] == pytest.approx(RATE_D_OVER_P_S * kd, rel=1e-3)
        gains = PD(w_[f"MC_{ax}_P"] * kd, kd)
        m = r["identified"][lp]["model"]
        ident = InnerModel(m["K"], m["T_prop"], m["T1"], m["tau"])
        onboard = InnerModel(ident.K, ident.T_prop, ident.T1,
                             max(ident.tau - r["retarget_delay_ms"][lp] * 1e-3, 1e-4))
        cascade = OnboardCascade(af.onboard.target_cutoff_hz, target_rate_ff=False,
                                 d_over_p_s=RATE_D_OVER_P_S,
                                 d_filter_hz=af.onboard.dgyro_cutoff_hz)
        plan = plan_check(onboard, gains, CHECK_AMPLITUDE_RAD, cascade=cascade)
        truth = r["loops"][lp]
        # the crossover stays where the relay cycle pinned the model ...
        assert plan.wc_rad_s <= D_WC_MAX_RATIO * relay_frequency(ident, beta) * 1.02, lp
        # ... so the prediction is the vehicle's margin, within what the check calls agreement
        assert abs(plan.predicted_pm_deg - truth["onboard_pm_deg"]) <= AGREE_DEG, (lp, truth)
        assert truth["onboard_pm_deg"] >= 15.0 and truth["onboard_J_pct"] <= 10.0, (lp, truth)


def test_structured_pd_keeps_the_crossover_asked_for():
    # the same D design with and without a cap: the cap holds, at a cost in ISE only
    m = InnerModel(150.0, 0.02, 0.6, 0.008)
    w = frequency_grid(m.T_prop, m.T1, m.tau)
    G = inner_response(m.K, m.T_prop, m.T1, m.tau, w)[0]
    st = OnboardStructure(20.0, "", RATE_D_OVER_P_S, 20.0)
    free = structured_pd(G, w, st, gm_min=2.0)
    wc_free = margins(structure_controller(free.gains, st, w)[1] * G, w).wc
    cap = 0.7 * wc_free
    held = structured_pd(G, w, st, gm_min=2.0, wc_max=cap)
    mh = margins(structure_controller(held.gains, st, w)[1] * G, w)
    assert mh.wc <= cap * 1.0001 and mh.pm_deg >= 20.0 - 1e-6 and mh.gm >= 2.0
    assert held.ise >= free.ise


def test_relay_frequency_is_where_the_mrft_phase_is():
    m = InnerModel(80.0, 0.03, 0.4, 0.015)
    wr = relay_frequency(m, -0.7)
    ph = np.angle(inner_response(m.K, m.T_prop, m.T1, m.tau, [wr])[0][0]) - 2 * math.pi
    assert math.degrees(ph) == pytest.approx(-180.0 + math.degrees(math.asin(-0.7)), abs=0.5)


def _truth_at(G: np.ndarray, wg: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``G`` (on the grid ``wg``) at ``w``: log-magnitude and unwrapped phase interpolated."""
    lw = np.log(wg)
    mag = np.interp(np.log(w), lw, np.log(np.abs(G)))
    ph = np.interp(np.log(w), lw, np.unwrap(np.angle(G)))
    return np.exp(mag + 1j * ph)


@pytest.mark.parametrize("seed,lp", [(3, "roll"), (19, "pitch")])
def test_the_check_measures_the_vehicles_margin_from_its_exact_points(seed, lp):
    # noise-free closed-loop points of the vehicle's own loop (the onboard truth) at the
    # check's harmonics: the margin the check reads from them is the truth's, though the
    # identified model it corrects is off the vehicle's by more than a gain and a delay
    from mrft_gcs.flight.inair import CHECK_HARMONICS, check_margin
    from mrft_gcs.flight.scoring import onboard_controller, onboard_process
    from mrft_gcs.loops import Loop
    from mrft_gcs.sitl.onboard import ParamStore

    af = random_airframe(seed)
    assert domain_check(af).category == "in-domain"
    r = tp.run_lockstep(seed)
    assert r["outcome"] == "completed", r.get("reason")
    loop = Loop(lp)
    prm = dict(ParamStore(af.hover_thrust * af.hover_estimate_factor, af.onboard).values)
    prm.update(r["written"])
    ax = _AXES[lp]
    kd = prm[f"MC_{ax}RATE_P"]
    gains = PD(prm[f"MC_{ax}_P"] * kd, kd)
    m = r["identified"][lp]["model"]
    onboard = InnerModel(m["K"], m["T_prop"], m["T1"],
                         max(m["tau"] - r["retarget_delay_ms"][lp] * 1e-3, 1e-4))
    d = prm[f"MC_{ax}RATE_D"]
    cascade = (OnboardCascade(af.onboard.target_cutoff_hz, target_rate_ff=False,
                              d_over_p_s=d / kd if d > 0 else 0.0,
                              d_filter_hz=af.onboard.dgyro_cutoff_hz)
               if af.onboard.style == "ardupilot" else None)
    plan = plan_check(onboard, gains, CHECK_AMPLITUDE_RAD, cascade=cascade)
    G, wg = onboard_process(af, loop, prm)
    truth = margins(onboard_controller(af, loop, prm, wg)[1] * G, wg)
    w = plan.wc_rad_s * np.asarray(CHECK_HARMONICS, float)
    Gw = _truth_at(G, wg, w)
    cr, cy = onboard_controller(af, loop, prm, w)
    T = cr * Gw / (1.0 + cy * Gw)
    check = check_margin(plan, w, T, np.full(w.size, 0.05))
    assert check.measured_pm_deg == pytest.approx(truth.pm_deg, abs=1.0), (plan, truth)
