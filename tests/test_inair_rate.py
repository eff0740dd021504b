"""The in-air check of gains written on ArduCopter's cascade with a rate I (the rate path)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mrft_gcs.flight.inair import OnboardCascade, check_margin, plan_check
from mrft_gcs.flight.onboard import CASCADE_LOOP_HZ, _cascade_pm, cascade_controller
from mrft_gcs.pd_design import frequency_grid
from mrft_gcs.plant import PD, InnerModel, inner_response

MODEL = InnerModel(K=34.0, T_prop=0.0085, T1=0.095, tau=0.006)
GAINS = PD(6.4, 0.21)


def _cascade(wi: float, r: float = 0.0) -> OnboardCascade:
    return OnboardCascade(20.0, integrator_zero_rad_s=wi, d_over_p_s=r,
                          d_filter_hz=20.0 if r > 0 else 0.0)


@pytest.mark.parametrize("r", [0.0, 0.02])
def test_rate_i_zero_above_drag_pole_is_stable(r: float) -> None:
    # the I's zero (15 rad/s) above the drag pole (1/T1 = 10.5 rad/s): two integrators, phase
    # from -180 deg; the closed loop is stable (its poles), so the check must plan, not abort
    wi = 15.0
    plan = plan_check(MODEL, GAINS, 0.035, cascade=_cascade(wi, r))
    # ... and predict what the design's model of the same cascade gives (its half loop period
    # taken out of the delay, which the check's model leaves to the measurement)
    same = InnerModel(MODEL.K, MODEL.T_prop, MODEL.T1, MODEL.tau - 0.5 / CASCADE_LOOP_HZ)
    w = frequency_grid(MODEL.T_prop, MODEL.T1, MODEL.tau)
    pm, wc = _cascade_pm(same, GAINS, 20.0, w, 0.0, wi, r, 20.0 if r > 0 else 0.0)
    assert math.isfinite(pm) and plan.predicted_pm_deg == pytest.approx(pm, abs=0.5)
    assert plan.wc_rad_s == pytest.approx(wc, rel=0.02)


def test_measured_margin_of_stable_rate_i_loop_is_finite() -> None:
    plan = plan_check(MODEL, GAINS, 0.035, cascade=_cascade(15.0))
    w = plan.wc_rad_s * np.array([1.0, 3.0, 5.0])
    cr, cy = plan.cascade.paths(GAINS, w) if plan.cascade else (None, None)
    G = inner_response(MODEL.K, MODEL.T_prop, MODEL.T1, MODEL.tau, w)[0]
    T = cr * G / (1 + cy * G)  # the predicted loop itself, measured exactly
    check = check_margin(plan, w, T, np.full(3, 0.02))
    assert check.measured_pm_deg == pytest.approx(plan.predicted_pm_deg, abs=0.5)
    assert check.agrees and check.k == pytest.approx(1.0, rel=1e-6)


def test_unstable_rate_i_loop_still_refused() -> None:
    # the same cascade with rate P doubled past its gain margin: unstable, no plan
    with pytest.raises(ValueError, match="unstable"):
        plan_check(MODEL, PD(GAINS.Kc * 4, GAINS.Kd * 4), 0.035, cascade=_cascade(15.0))


def test_cascade_feedback_path_is_the_design_model() -> None:
    w = np.logspace(0, 3, 40)
    c = OnboardCascade(20.0, 2.5, integrator_zero_rad_s=8.0, d_over_p_s=0.02, d_filter_hz=30.0)
    _, cy = c.paths(GAINS, w)
    assert np.allclose(cy, cascade_controller(GAINS, w, 20.0, 2.5, 8.0, 0.02, 30.0)[1])
