"""Measured frequency-response points of relay cycles, and the side fit on them."""

from __future__ import annotations

import numpy as np
import pytest

from mrft_gcs.identify import Method, identify, relay_settings
from mrft_gcs.identify.harmonics import (
    USABLE_SD,
    HarmonicPoints,
    class_log_likelihood,
    fit_inner_model,
    fit_side_model,
    harmonic_points,
    noise_std,
)
from mrft_gcs.identify.runtime import load_bundle
from mrft_gcs.loops import LoopKind
from mrft_gcs.pd_design import ise, margins, optimal_pd
from mrft_gcs.plant import closed_inner_response, inner_response, side_response
from mrft_gcs.simulate import simulate_mrft, simulate_side_mrft

ATT = (40.0, 0.02, 0.25, 0.02)  # K, T_prop, T1, tau (qdrone-like roll)
ATT_PD = (0.1, 0.012)


def _side_run(T2: float, tau: float, noise: float = 0.0, bias: float = 0.0):
    side = (9.81 * T2, T2, tau)
    run = simulate_side_mrft(ATT, ATT_PD, side, beta=-0.7, h=0.1, bias=bias, noise_std=noise,
                             band=4 * noise, duration_s=12.0 + 20 * T2, keep_s=12.0, seed=3)
    return side, run


def _attitude_identified():
    """The ATT process identified from its relay test, and the side relay it asks for."""
    b = load_bundle(LoopKind.ATTITUDE)
    run = simulate_mrft(ATT[0], *ATT[1:], beta=b.beta, h=b.h, duration_s=8.0, keep_s=4.0)
    a_id = identify(LoopKind.ATTITUDE, run.t, run.u[0], run.y[0], beta=b.beta, h=b.h,
                    setpoint=0.0)
    return a_id, relay_settings(LoopKind.SIDE, inner=a_id)


def _t_att(w):
    return closed_inner_response(*ATT_PD, inner_response(*ATT, w), w)[0]


def test_harmonic_points_are_the_plant_response():
    """For a linear plant in periodic steady state, Y_k / U_k is G(j k w) exactly."""
    p = (3.0, 0.05, 0.6, 0.02)
    run = simulate_mrft(*p, beta=-0.5, h=1.0, duration_s=12.0, keep_s=6.0)
    pts = harmonic_points(run.t, run.u[0], run.y[0])
    G = inner_response(*p, pts.w)[0]
    assert np.allclose(np.abs(pts.G[:2] / G[:2]), 1.0, atol=0.02)
    assert np.allclose(np.angle(pts.G[:2] / G[:2]), 0.0, atol=0.03)
    assert pts.cycles == 4 and pts.sd[0] < 0.05


def test_held_relay_output_gives_every_harmonic_without_lag():
    """At 250 Hz a plain sum over the held relay levels would lag by half a sample (0.26 rad
    at the 7th harmonic here, as much phase as 2 ms of delay); integrated exactly, every
    measured point is the plant's response."""
    p = (3.0, 0.05, 0.6, 0.002)
    run = simulate_mrft(*p, beta=-0.7, h=1.0, duration_s=12.0, keep_s=6.0, dt=0.004)
    pts = harmonic_points(run.t, run.u[0], run.y[0])
    d = np.log(pts.G / inner_response(*p, pts.w)[0])
    assert np.all(np.abs(d) < 1e-3), d


def test_standard_errors_cover_the_noise():
    """With 1 % noise the 5th and 7th harmonics are mostly noise; four cycles' spread alone
    understated their error (up to 2.9 standard errors on these 16 records), the noise level
    measured on the record does not."""
    p, n = (2.0, 0.03, 0.5, 0.002), 16
    clean = simulate_mrft(*p, beta=-0.7, h=1.0, duration_s=8.0, keep_s=2.0)
    sigma = 0.01 * 0.5 * np.ptp(clean.y[0])
    run = simulate_mrft(*[np.full(n, v) for v in p], beta=-0.7, h=1.0, noise_std=sigma,
                        band=4 * sigma, duration_s=8.0, keep_s=4.0, seed=4)
    for i in range(n):
        assert abs(noise_std(run.y[i]) / sigma - 1) < 0.1
        pts = harmonic_points(run.t, run.u[i], run.y[i])
        d = np.log(pts.G / inner_response(*p, pts.w)[0])
        assert np.all(np.abs(d) < 2 * pts.sd), (i, np.abs(d) / pts.sd)


def test_class_likelihood_ignores_harmonics_lost_in_noise():
    """A harmonic measured worse than USABLE_SD cannot favour one candidate over another."""
    p = (3.0, 0.05, 0.6, 0.02)
    run = simulate_mrft(*p, beta=-0.7, h=1.0, duration_s=12.0, keep_s=6.0)
    pts = harmonic_points(run.t, run.u[0], run.y[0])
    cands = inner_response([3.0, 3.0, 2.5], [0.05, 0.08, 0.05], [0.6, 0.4, 0.6],
                           [0.02, 0.01, 0.03], pts.w)
    sd = np.r_[pts.sd[:3], USABLE_SD * 1.6]  # the 7th harmonic lost in noise
    kept = class_log_likelihood(HarmonicPoints(pts.w, pts.G, sd, pts.spread, pts.harmonics,
                                               pts.cycles), cands)
    wild = HarmonicPoints(pts.w, pts.G * np.r_[1, 1, 1, 3 * np.exp(2.5j)], sd, pts.spread,
                          pts.harmonics, pts.cycles)
    assert np.argmax(kept) == 0
    assert np.allclose(class_log_likelihood(wild, cands), kept)
    assert not np.allclose(class_log_likelihood(wild, cands, max_sd=1.0), kept)


def test_harmonic_points_need_two_cycles():
    with pytest.raises(ValueError, match="two complete"):
        harmonic_points(np.arange(10.0), np.r_[np.ones(5), -np.ones(5)], np.zeros(10))


@pytest.mark.parametrize("T2, tau", [(0.3, 0.01), (5.0, 0.01), (1.0, 0.1)])
def test_side_fit_recovers_the_model(T2, tau):
    """Short and long drag time constants, which one relay point cannot tell apart."""
    side, run = _side_run(T2, tau)
    fit = fit_side_model(harmonic_points(run.t, run.u[0], run.y[0]),
                         _t_att(harmonic_points(run.t, run.u[0], run.y[0]).w))
    assert fit.T2 == pytest.approx(T2, rel=0.1)
    assert fit.K == pytest.approx(side[0], rel=0.1)
    assert abs(fit.tau - tau) < 0.01


def test_side_fit_refuses_one_harmonic():
    side, run = _side_run(1.0, 0.02)
    pts = harmonic_points(run.t, run.u[0], run.y[0])
    with pytest.raises(ValueError, match="two usable"):
        fit_side_model(pts, _t_att(pts.w), max_sd=pts.sd.min() / 2)


@pytest.mark.parametrize("T2", [0.25, 4.0])
def test_side_gains_near_optimal_with_noise_and_bias(T2):
    """End to end through identify(): noisy, biased side test, gains scored on the truth."""
    a_id, rs = _attitude_identified()
    side = (9.81 * T2, T2, 0.03)
    clean = simulate_side_mrft(ATT, (a_id.gains.Kc, a_id.gains.Kd), side, beta=rs.beta, h=rs.h,
                               duration_s=10 + 20 * T2, keep_s=8.0)
    noise = 0.01 * 0.5 * np.ptp(clean.y[0])
    srun = simulate_side_mrft(ATT, (a_id.gains.Kc, a_id.gains.Kd), side, beta=rs.beta, h=rs.h,
                              bias=0.2 * rs.h, noise_std=noise, band=4 * noise,
                              duration_s=10 + 20 * T2, keep_s=8.0, seed=5)
    s_id = identify(LoopKind.SIDE, srun.t, srun.u[0], srun.y[0], beta=rs.beta, h=rs.h,
                    inner=a_id, setpoint=0.0)
    assert s_id.diagnostics.method is Method.HARMONIC_FIT
    w = np.logspace(-3, 4, 900)
    P = closed_inner_response(a_id.gains.Kc, a_id.gains.Kd, inner_response(*ATT, w), w)[0] * \
        side_response(*side, w)[0]
    best = optimal_pd(P, w)
    Kc, Kd = s_id.gains.Kc, s_id.gains.Kd
    assert margins((Kc + 1j * w * Kd) * P, w).stable
    J = (ise(Kc, Kd, P, w) - best.ise) / best.ise * 100
    assert J < 10.0


def test_inner_fit_recovers_a_model_near_its_start():
    p = (3.0, 0.05, 0.6, 0.02)
    run = simulate_mrft(*p, beta=-0.5, h=1.0, duration_s=12.0, keep_s=6.0)
    pts = harmonic_points(run.t, run.u[0], run.y[0])
    params, cost = fit_inner_model(pts, (2.0, 0.07, 0.5, 0.03))
    assert np.allclose(np.log(params), np.log(p), atol=np.log(1.15))
    assert cost < 1.0


def test_inner_identification_keeps_its_phase_margin():
    """Random attitude processes with noise and bias: refined gains keep PM >= 15 deg."""
    from mrft_gcs.domains import D_ATT

    b = load_bundle(LoopKind.ATTITUDE)
    rng = np.random.default_rng(11)
    params = D_ATT.sample_log_uniform(12, rng)
    K = np.exp(rng.uniform(np.log(0.5), np.log(50.0), 12))
    clean = simulate_mrft(K, *params.T, beta=b.beta, h=b.h, duration_s=30.0, keep_s=4.0)
    noise = 0.01 * 0.5 * np.ptp(clean.y, axis=1)
    run = simulate_mrft(K, *params.T, beta=b.beta, h=b.h, bias=0.2 * b.h, noise_std=noise,
                        band=4 * noise, duration_s=30.0, keep_s=5.0, seed=2)
    for i in range(12):
        a_id = identify(LoopKind.ATTITUDE, run.t, run.u[i], run.y[i], beta=b.beta, h=b.h,
                        setpoint=0.0)
        assert a_id.diagnostics.method is Method.CLASSIFIER_HARMONICS
        w = np.logspace(-2, 5, 1500)
        G = inner_response(K[i], *params[i], w)[0]
        m = margins((a_id.gains.Kc + 1j * w * a_id.gains.Kd) * G, w)
        best = optimal_pd(G, w)
        J = (ise(a_id.gains.Kc, a_id.gains.Kd, G, w) - best.ise) / best.ise * 100
        assert m.stable and m.pm_deg >= 15.0 and J < 10.0, (i, m.pm_deg, J)


def test_unsteady_cycles_are_refused():
    """An oscillation that grows from cycle to cycle is not a relay test to identify."""
    from mrft_gcs.errors import IdentificationError

    b = load_bundle(LoopKind.ATTITUDE)
    t = np.arange(0, 3.0, 0.002)
    phase = 2 * np.pi * t / 0.5
    u = b.h * np.sign(np.sin(phase + 0.8))
    y = 0.02 * np.exp(0.6 * t) * np.sin(phase)
    with pytest.raises(IdentificationError, match="not steady"):
        identify(LoopKind.ATTITUDE, t, u, y, beta=b.beta, h=b.h)


def test_a_record_the_model_cannot_explain_keeps_the_classifier_rule():
    """A pure sine answering a square wave has no odd harmonics, unlike any plant here: the
    refined fit runs off and its gains are not trusted."""
    b = load_bundle(LoopKind.ATTITUDE)
    t = np.arange(0, 3.0, 0.002)
    phase = 2 * np.pi * t / 0.5
    u = b.h * np.sign(np.sin(phase + 0.8))
    a_id = identify(LoopKind.ATTITUDE, t, u, 0.02 * np.sin(phase), beta=b.beta, h=b.h)
    assert a_id.diagnostics.method is Method.CLASSIFIER
    assert a_id.gains.Kc / a_id.gains.Kd < 50


def _periodic(T_of_w, period_s: float, h: float, cycles: int = 4, dt: float = 0.004):
    """A held square wave of ``period_s`` and a linear loop's periodic answer to it."""
    n = int(round(period_s / dt))
    t = np.arange(cycles * n + 1) * dt
    u = np.where((t % period_s) < period_s / 2, h, -h)
    w = 2 * np.pi * np.fft.rfftfreq(n, dt)[1:]
    hold = (1 - np.exp(-1j * w * dt)) / (1j * w * dt)
    y1 = np.fft.irfft(np.fft.rfft(u[:n]) * np.r_[0.0, T_of_w(w) * hold], n)
    return t, u, np.r_[np.tile(y1, cycles), y1[0]]


def test_side_fit_behind_the_measured_attitude_loop():
    """The attitude loop lags its model during the side test (as when the motors saturate at
    each side relay switch): with the measured tilt, the side model is still the truth."""
    a_id, rs = _attitude_identified()
    slow = (ATT[0], ATT[1], ATT[2], 2.5 * ATT[3])  # the loop as it behaves in the test

    def t_true(w):
        return closed_inner_response(a_id.gains.Kc, a_id.gains.Kd, inner_response(*slow, w),
                                     w)[0]

    side = (9.81, 1.0, 0.03)
    t, u, tilt = _periodic(t_true, 1.2, rs.h)
    _, _, y = _periodic(lambda w: t_true(w) * side_response(*side, w)[0], 1.2, rs.h)
    kw = dict(beta=rs.beta, h=rs.h, inner=a_id)
    measured = identify(LoopKind.SIDE, t, u, y, tilt=tilt, **kw)
    modelled = identify(LoopKind.SIDE, t, u, y, **kw)
    assert measured.diagnostics.fit.t_att_measured[:2] == (1, 3)
    assert modelled.diagnostics.fit.t_att_measured == ()
    assert measured.model.T2 == pytest.approx(side[1], rel=0.05)
    assert abs(measured.model.tau - side[2]) < 0.005
    # behind the modelled loop the lag it does not know of is taken for side-model lag
    assert abs(modelled.model.tau - side[2]) > 4 * abs(measured.model.tau - side[2])


def test_side_cycles_no_multirotor_makes_are_refused():
    """A multirotor in hover accelerates sideways by about g per rad of tilt (``K / T2``);
    cycles that say twice that are disturbed, and a retry beats tuning on them."""
    from mrft_gcs.errors import IdentificationError

    a_id, rs = _attitude_identified()

    def t_att(w):
        return closed_inner_response(a_id.gains.Kc, a_id.gains.Kd, inner_response(*ATT, w),
                                     w)[0]

    for accel, ok in ((9.81, True), (2 * 9.81, False)):
        side = (accel * 0.8, 0.8, 0.05)
        t, u, tilt = _periodic(t_att, 1.2, rs.h)
        _, _, y = _periodic(lambda w, s=side: t_att(w) * side_response(*s, w)[0], 1.2, rs.h)
        kw = dict(beta=rs.beta, h=rs.h, inner=a_id, tilt=tilt)
        if ok:
            m = identify(LoopKind.SIDE, t, u, y, **kw).model
            assert m.K / m.T2 == pytest.approx(accel, rel=0.02)
        else:
            with pytest.raises(IdentificationError, match="acceleration per rad of tilt"):
                identify(LoopKind.SIDE, t, u, y, **kw)
