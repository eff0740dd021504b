"""Optimal PD design: cost, margins, optimality, time-scale property, deterioration."""

from __future__ import annotations

import numpy as np
import pytest

from mrft_gcs.pd_design import (
    PM_MIN_DEG,
    deterioration,
    frequency_grid,
    ise,
    joint_cost,
    margins,
    optimal_pd,
)
from mrft_gcs.plant import inner_response
from mrft_gcs.simulate import simulate_pd_step

PLANTS = [(0.05, 0.5, 0.01), (0.015, 0.2, 0.0005), (0.3, 2.0, 0.03), (0.3, 0.2, 0.15),
          (0.015, 2.0, 0.15)]


def design(Tp, T1, tau, n=600):
    w = frequency_grid(Tp, T1, tau, n=n)
    G = inner_response(1.0, Tp, T1, tau, w)[0]
    return optimal_pd(G, w), G, w


def test_frequency_domain_ise_equals_time_domain_ise():
    Tp, T1, tau = 0.05, 0.5, 0.01
    d, G, w = design(Tp, T1, tau)
    y = simulate_pd_step(1.0, Tp, T1, tau, d.pd.Kc, d.pd.Kd, duration_s=15.0, dt=1e-4)
    assert np.sum((1 - y[0]) ** 2) * 1e-4 == pytest.approx(d.ise, rel=2e-3)


def test_margins_of_integrator_with_delay_are_analytic():
    # L = k e^{-tau s}/s: crossover at w = k, PM = 90 - k tau (deg), GM = pi/(2 k tau).
    k, tau = 2.0, 0.1
    w = np.logspace(-3, 3, 20000)
    L = k * np.exp(-1j * w * tau) / (1j * w)
    m = margins(L, w)
    assert m.stable
    assert m.pm_deg == pytest.approx(90 - np.degrees(k * tau), abs=0.05)
    assert m.gm == pytest.approx(np.pi / (2 * k * tau), rel=1e-3)
    assert m.wc == pytest.approx(k, rel=1e-3)
    unstable = margins(20 * np.exp(-1j * w * tau) / (1j * w), w)  # k tau = 2 > pi/2
    assert not unstable.stable and unstable.pm_deg < 0


@pytest.mark.parametrize("plant", PLANTS)
def test_optimum_is_feasible_and_not_beaten_nearby(plant):
    d, G, w = design(*plant)
    assert d.margins.stable
    assert d.margins.pm_deg >= PM_MIN_DEG - 1e-6
    for fc in (0.98, 1.0, 1.02):
        for fd in (0.98, 1.0, 1.02):
            Kc, Kd = d.pd.Kc * fc, d.pd.Kd * fd
            m = margins((Kc + Kd * 1j * w) * G, w)
            if m.stable and m.pm_deg >= PM_MIN_DEG:
                assert ise(Kc, Kd, G, w) >= d.ise * (1 - 1e-6)


def test_constraint_is_active_for_ise_optimal_pd():
    # The unconstrained ISE optimum has less than 20 deg: the bound must bind.
    d, _, _ = design(0.05, 0.5, 0.01)
    assert d.margins.pm_deg == pytest.approx(PM_MIN_DEG, abs=0.05)


@pytest.mark.parametrize("c", [0.25, 3.0])
def test_time_scale_property(c):
    # Q(C(c s), G(c s)) = alpha Q(C(s), G(s)): stretching time by c stretches the
    # ISE by c and leaves the optimal design's margins unchanged; Kc scales by 1/c.
    Tp, T1, tau = 0.05, 0.5, 0.01
    d1, G1, w1 = design(Tp, T1, tau)
    d2, G2, w2 = design(c * Tp, c * T1, c * tau)
    assert d2.ise == pytest.approx(c * d1.ise, rel=2e-3)
    assert d2.pd.Kc == pytest.approx(d1.pd.Kc / c, rel=5e-3)
    assert d2.pd.Kd == pytest.approx(d1.pd.Kd, rel=5e-3)
    assert d2.margins.pm_deg == pytest.approx(d1.margins.pm_deg, abs=0.05)
    # the ISE of the scaled controller on the scaled plant is exactly c times the original
    q = ise(d1.pd.Kc / c, d1.pd.Kd, inner_response(1.0, c * Tp, c * T1, c * tau, w1 / c)[0], w1 / c)
    assert q == pytest.approx(c * d1.ise, rel=1e-9)


def test_deterioration_is_zero_on_itself_and_asymmetric():
    w = frequency_grid(0.015, 2.0, 0.03, n=1500, extra_T=(0.0005,))
    a = (0.05, 0.5, 0.01)
    b = (0.06, 0.6, 0.012)
    Ga, Gb = (inner_response(1.0, *p, w)[0] for p in (a, b))
    da, db = optimal_pd(Ga, w), optimal_pd(Gb, w)
    assert deterioration(da.pd, Ga, w, da.ise) == pytest.approx(0.0, abs=1e-9)
    jab = deterioration(da.pd, Gb, w, db.ise)
    jba = deterioration(db.pd, Ga, w, da.ise)
    # J is not symmetric; it can be negative when the foreign controller is more
    # aggressive than the 20 deg constraint allows, so the joint cost takes the max.
    assert jab != pytest.approx(jba)
    assert max(jab, jba) > 0
    jc = joint_cost(da, Ga, db, Gb, w)
    assert jc == pytest.approx(max(jab, jba))
    slower_ctrl_pm = margins((da.pd.Kc + da.pd.Kd * 1j * w) * Gb, w).pm_deg
    if jab < 0:
        assert slower_ctrl_pm < PM_MIN_DEG


def test_destabilising_controller_has_infinite_cost():
    w = frequency_grid(0.05, 0.5, 0.01)
    G = inner_response(1.0, 0.05, 0.5, 0.01, w)[0]
    d = optimal_pd(G, w)
    from mrft_gcs.plant import PD

    assert deterioration(PD(d.pd.Kc * 20, d.pd.Kd * 20), G, w, d.ise) == np.inf
