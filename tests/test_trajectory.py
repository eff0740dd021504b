"""Minimum-snap periodic paths and the figure-eight (mrft_gcs.trajectory)."""

from __future__ import annotations

import doctest

import numpy as np
import pytest

from mrft_gcs import trajectory
from mrft_gcs.errors import UsageError
from mrft_gcs.trajectory import (
    PiecewisePoly,
    continuity_gaps,
    evaluate,
    figure_eight,
    min_snap_periodic,
    ramp_in,
    sample,
    snap_cost,
)


@pytest.fixture(scope="module")
def fig8() -> PiecewisePoly:
    return figure_eight((2.0, 1.0), 5.5)


def test_doctests():
    assert doctest.testmod(trajectory).failed == 0


def test_size_period_and_waypoints(fig8):
    t = np.linspace(0.0, 5.5, 200_001)
    p = sample(fig8, t).pos_m
    assert np.ptp(p[:, 0]) == pytest.approx(2.0, abs=1e-6)
    assert np.ptp(p[:, 1]) == pytest.approx(1.0, abs=1e-6)
    # symmetric about the centre, which is where it starts
    assert np.allclose(p[0], 0.0, atol=1e-12)
    assert p[:, 0].max() == pytest.approx(-p[:, 0].min(), abs=1e-9)
    # passes through its waypoints at the break times
    assert np.allclose(evaluate(fig8, fig8.breaks_s[:-1]), fig8.waypoints_m, atol=1e-9)
    # one lap per period, for every derivative
    for k in range(5):
        a, b = evaluate(fig8, t[:100], k), evaluate(fig8, t[:100] + 5.5, k)
        assert np.allclose(a, b, atol=1e-9)


def test_speed_and_acceleration_are_the_benchmarks():
    # a 2 x 1 m figure-eight in 5.5 s: about 1.6 m/s at the crossing, under 3 m/s^2
    s = sample(figure_eight(), np.linspace(0, 5.5, 5501))
    assert np.linalg.norm(s.vel_m_s, axis=1).max() == pytest.approx(1.6, abs=0.1)
    assert np.linalg.norm(s.acc_m_s2, axis=1).max() < 3.0


def test_optimum_is_c6_but_not_c7(fig8):
    gaps = continuity_gaps(fig8, max_order=7)
    scale = [np.abs(evaluate(fig8, np.linspace(0, 5.5, 2001), k)).max() for k in range(8)]
    rel = gaps / np.array(scale)
    assert np.all(rel[:7] < 1e-8), rel  # only C^4 was imposed: 5 and 6 come from optimality
    assert rel[7] > 1e-3  # a degree-7 spline, not a single polynomial


@pytest.mark.parametrize("continuity", [3, 5, 6])
def test_imposed_continuity_does_not_change_the_optimum(fig8, continuity):
    other = min_snap_periodic(fig8.waypoints_m, fig8.period_s, continuity=continuity)
    t = np.linspace(0, 5.5, 1001)
    for k in range(5):  # equal to rounding (the KKT systems differ in conditioning)
        assert np.allclose(evaluate(other, t, k), evaluate(fig8, t, k), rtol=0, atol=1e-6)


def test_snap_cost_matches_quadrature(fig8):
    t = np.linspace(0, 5.5, 400_001)
    snap = evaluate(fig8, t, 4)
    numeric = np.trapezoid(np.sum(snap**2, axis=1), t)
    assert snap_cost(fig8) == pytest.approx(numeric, rel=1e-4)


def _perturbed(pp: PiecewisePoly, k: int, eps: float) -> float:
    """Snap cost of pp + eps * sin(2 pi k N t / T) (periodic, smooth, zero at every waypoint)."""
    n, period = pp.n_segments, pp.period_s
    t = np.linspace(0, period, 400_001)
    w = 2 * np.pi * k * n / period
    snap = evaluate(pp, t, 4) + eps * w**4 * np.sin(w * t)[:, None]
    return float(np.trapezoid(np.sum(snap**2, axis=1), t))


@pytest.mark.parametrize("k", [1, 2])
@pytest.mark.parametrize("eps", [-1e-3, 1e-3, 1e-2])
def test_snap_is_minimal_against_feasible_perturbations(fig8, k, eps):
    # any smooth periodic perturbation that keeps the waypoints costs more snap
    assert _perturbed(fig8, k, eps) > _perturbed(fig8, k, 0.0)


def test_snap_is_minimal_against_random_feasible_splines(fig8):
    # other C^4 degree-7 paths through the same waypoints: random coefficients projected
    # back onto the constraints cost more snap than the optimum
    rng = np.random.default_rng(1)
    best = snap_cost(fig8)
    for _ in range(5):
        noise = rng.normal(scale=0.05, size=fig8.coeffs.shape)
        cand = _project_feasible(PiecewisePoly(fig8.breaks_s, fig8.coeffs + noise,
                                               fig8.waypoints_m))
        assert continuity_gaps(cand, 4).max() < 1e-8
        assert np.allclose(evaluate(cand, fig8.breaks_s[:-1]), fig8.waypoints_m, atol=1e-8)
        assert snap_cost(cand) > best * (1 + 1e-6)


def _project_feasible(pp: PiecewisePoly) -> PiecewisePoly:
    """Closest (least-squares in coefficients) C^4 path through pp's waypoints."""
    n, nc, d = pp.coeffs.shape
    h = np.diff(pp.breaks_s)
    rows, rhs = [], []
    for i in range(n):
        j = (i + 1) % n
        for tau, target in ((0.0, pp.waypoints_m[i]), (h[i], pp.waypoints_m[j])):
            r = np.zeros(n * nc)
            r[i * nc:(i + 1) * nc] = trajectory._row(tau, 0)
            rows.append(r)
            rhs.append(target)
        for k in range(1, 5):
            r = np.zeros(n * nc)
            r[i * nc:(i + 1) * nc] = trajectory._row(h[i], k)
            r[j * nc:(j + 1) * nc] -= trajectory._row(0.0, k)
            rows.append(r)
            rhs.append(np.zeros(d))
    A, b = np.array(rows), np.array(rhs)
    c = pp.coeffs.reshape(n * nc, d)
    c = c - np.linalg.pinv(A) @ (A @ c - b)
    return PiecewisePoly(pp.breaks_s, c.reshape(n, nc, d), pp.waypoints_m)


def test_two_point_path_is_symmetric():
    pp = min_snap_periodic(np.array([[0.0], [1.0]]), 2.0)
    t = np.linspace(0, 2, 101)
    x = evaluate(pp, t)[:, 0]
    assert np.allclose(x, x[::-1], atol=1e-9)  # there and back, mirror images
    assert x.max() == pytest.approx(1.0, abs=1e-9)


def test_ramp_in_starts_from_rest_and_joins_the_path(fig8):
    lead = 5.5
    t = np.linspace(-1.0, 3 * 5.5, 20_001)
    r = ramp_in(fig8, t, lead)
    before = t <= 0
    assert np.allclose(r.pos_m[before], 0.0, atol=1e-12)
    assert np.allclose(r.vel_m_s[before], 0.0) and np.allclose(r.acc_m_s2[before], 0.0)
    after = t >= lead
    s = sample(fig8, t[after] - lead / 2)
    for a, b in ((r.pos_m, s.pos_m), (r.vel_m_s, s.vel_m_s), (r.acc_m_s2, s.acc_m_s2),
                 (r.jerk_m_s3, s.jerk_m_s3), (r.snap_m_s4, s.snap_m_s4)):
        assert np.allclose(a[after], b, atol=1e-9)
    # derivatives are consistent (finite differences) and continuous through the ramp
    dt = t[1] - t[0]
    for lo, hi in ((r.pos_m, r.vel_m_s), (r.vel_m_s, r.acc_m_s2), (r.acc_m_s2, r.jerk_m_s3)):
        assert np.abs(np.gradient(lo, dt, axis=0) - hi).max() < 5e-3
    # gentler than the path itself
    assert np.linalg.norm(r.acc_m_s2, axis=1).max() < 1.05 * np.linalg.norm(
        s.acc_m_s2, axis=1).max()


@pytest.mark.parametrize("kwargs", [
    {"size_m": (0.0, 1.0)}, {"size_m": (2.0, float("nan"))}, {"period_s": -1.0},
    {"n_waypoints": 6},
])
def test_bad_input_says_what_to_do(kwargs):
    with pytest.raises(UsageError):
        figure_eight(**kwargs)


def test_bad_waypoints():
    with pytest.raises(UsageError):
        min_snap_periodic(np.array([[1.0, 2.0]]), 1.0)
    with pytest.raises(UsageError):
        min_snap_periodic(np.zeros((4, 2)), 1.0, continuity=2)
    with pytest.raises(UsageError):
        ramp_in(figure_eight(), np.zeros(3), 0.0)
