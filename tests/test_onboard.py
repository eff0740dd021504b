"""GCS delay measured on a clock model, checked for plausibility, designed over (onboard)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mrft_gcs.flight.onboard import (
    AGE_CLIP_PERIODS,
    PM_ROBUST_DEG,
    GcsDelay,
    command_delay_s,
    measure_gcs_delay,
    onboard_gains,
    robust_onboard_gains,
)
from mrft_gcs.identify import Identification
from mrft_gcs.link.clock import ClockModel, clock_bins, fit_clock
from mrft_gcs.loops import LoopKind
from mrft_gcs.pd_design import frequency_grid, margins, optimal_pd
from mrft_gcs.plant import PD, InnerModel, inner_response, loop_response

P = 0.004  # setpoint period at 250 Hz

#: onboard (true) inner-loop models of the bundled airframes: K, T_prop, T1, tau (s), as
#: Airframe.linear_models gives them from profiles/vehicles/*.toml
MODELS = {
    "qdrone roll": (38.14, 0.020, 0.25, 0.022),
    "qdrone altitude": (10.79, 0.020, 0.50, 0.092),
    "racer250 roll": (117.06, 0.018, 0.30, 0.008),
    "racer250 altitude": (17.65, 0.018, 0.40, 0.034),
    "f550 roll": (72.68, 0.045, 0.60, 0.025),
    "f550 altitude": (13.66, 0.045, 0.70, 0.105),
}


def pm_deg(g: PD, K: float, T_prop: float, T1: float, tau: float) -> float:
    w = frequency_grid(T_prop, T1, tau)
    mg = margins(loop_response(g.Kc, g.Kd, inner_response(K, T_prop, T1, tau, w), w)[0], w)
    return mg.pm_deg if mg.stable else -math.inf


def identified(K: float, T_prop: float, T1: float, tau_onboard: float, d_true: float
               ) -> Identification:
    """What a GCS relay identifies: the onboard loop plus the GCS delay, and its
    ISE-optimal PD (PM 20 deg on the GCS-side loop)."""
    tau = tau_onboard + d_true
    w = frequency_grid(T_prop, T1, tau)
    pd = optimal_pd(inner_response(K, T_prop, T1, tau, w)[0], w).pd
    return Identification(LoopKind.ATTITUDE, InnerModel(K=K, T_prop=T_prop, T1=T1, tau=tau),
                          0, 1.0, -0.8, 0.1, 0.25, 0.03, pd)


def session(seed: int, slips: tuple[tuple[float, float], ...], *, duration_s: float = 60.0,
            phase_s: float = 0.0017, load: bool = True):
    """A tune's timestamps: the vehicle streams ATTITUDE every 4 ms of its own time,
    its clock stopping for ``step`` s of real time at each (vehicle time, step) of
    ``slips``; the link delays 0.2 ms plus jitter (on a loaded host, one sample in 20 late
    by up to 5 ms); the ground station's stream ticks every 4 ms of real time at
    ``phase_s`` and answers the latest sample received.

    Returns receive and vehicle times of the samples (in receive order), and per tick the
    vehicle time it answered, when it left, and the answered sample's true age (from the
    earliest the link could deliver it).
    """
    rng = np.random.default_rng(seed)
    vt = np.round(np.arange(0.0, duration_s, P) * 1e3) / 1e3  # time_boot_ms
    off = 500.0 + sum((step * (vt >= t) for t, step in slips), np.zeros(len(vt)))
    lat = 0.0002 + rng.exponential(0.0003, len(vt))
    if load:
        lat += (rng.random(len(vt)) < 0.05) * rng.uniform(0, 0.005, len(vt))
    rx = vt + off + lat
    order = np.argsort(rx, kind="stable")
    rx, vt_rx, off_rx = rx[order], vt[order], off[order]
    ticks = 500.0 + phase_s + np.arange(1, int(duration_s / P)) * P
    i = np.searchsorted(rx, ticks, side="right") - 1
    ok = i >= 0
    ticks, i = ticks[ok], i[ok]
    # the newest vehicle time received so far (a late older sample never replaces it)
    newest = np.maximum.accumulate(vt_rx)[i]
    j = np.searchsorted(vt, newest)
    send = ticks + 5e-5
    true_age = send - (newest + off[j] + 0.0002)
    return rx, vt_rx, newest, send, true_age, off_rx


#: the busy host's story: the vehicle's clock slips 8 times in a minute, 5-20 ms each
BUSY = ((5.0, 0.006), (12.0, 0.020), (19.0, 0.005), (26.0, 0.012), (33.0, 0.009),
        (38.5, 0.015), (47.0, 0.007), (55.0, 0.018))


def measure_on(rx, vt, t_ans, send, window):
    clock = ClockModel()
    for a, b in zip(rx.tolist(), vt.tolist(), strict=True):
        clock.update(a, b)
    fit = clock.fit()
    m = (t_ans >= window[0]) & (t_ans <= window[1])
    ages = send[m] - t_ans[m] - fit.offset_at(t_ans[m])
    return measure_gcs_delay(ages, P, sample_t_s=t_ans[m], clock=fit), fit


def test_busy_host_ages_no_longer_saturate():
    rx, vt, t_ans, send, true_age, _ = session(1, BUSY)
    window = (40.0, 43.0)  # the identified cycles: after 67 ms of slips, none inside
    m = (t_ans >= window[0]) & (t_ans <= window[1])
    # the old measurement: one offset, the session's least-delayed sample
    old = command_delay_s(send[m] - t_ans[m] - np.min(rx - vt), P)
    assert old == pytest.approx(AGE_CLIP_PERIODS * P)  # 12 ms: every age at the clip
    gcs, fit = measure_on(rx, vt, t_ans, send, window)
    assert len(fit.slips) == len(BUSY)
    assert gcs.measured, gcs.why
    truth = np.mean([true_age[m][t_ans[m] == t].min() for t in np.unique(t_ans[m])])
    assert gcs.measured_s == pytest.approx(truth, abs=3e-4)
    assert gcs.lo_s <= truth + 1e-4
    assert gcs.measured_s < 1.5 * P


def test_busy_host_slip_inside_the_cycles_is_rejected():
    rx, vt, t_ans, send, _, _ = session(2, BUSY)
    gcs, _ = measure_on(rx, vt, t_ans, send, (37.0, 40.0))  # the 15 ms slip at 38.5 s
    assert not gcs.measured
    assert "slipped" in gcs.why and "+15" in gcs.why
    assert gcs.estimate_s == 0.5 * P and gcs.lo_s == 0.0


@pytest.mark.parametrize("name", list(MODELS))
def test_busy_host_written_gains_keep_margin_on_the_onboard_loop(name):
    K, Tp, T1, tau = MODELS[name]
    rx, vt, t_ans, send, true_age, _ = session(3, BUSY)
    for window in ((40.0, 43.0), (37.0, 40.0)):
        m = (t_ans >= window[0]) & (t_ans <= window[1])
        # the true GCS delay: the age plus the link's 0.2 ms and the vehicle's pickup
        d_true = float(np.mean(true_age[m])) + 0.0002 + 0.0005
        ident = identified(K, Tp, T1, tau, d_true)
        gcs, _ = measure_on(rx, vt, t_ans, send, window)
        new = robust_onboard_gains(ident, gcs)
        assert pm_deg(new.gains, K, Tp, T1, tau) >= PM_ROBUST_DEG, (window, new.note())
        old = onboard_gains(ident, command_delay_s(send[m] - t_ans[m] - np.min(rx - vt), P))
        assert pm_deg(old, K, Tp, T1, tau) < pm_deg(new.gains, K, Tp, T1, tau)


def test_quiet_host_measures_as_before():
    # no slips, no load: the tracked envelope and the session's least offset agree
    rx, vt, t_ans, send, _, _ = session(4, (), load=False, phase_s=0.0029)
    window = (20.0, 24.0)
    m = (t_ans >= window[0]) & (t_ans <= window[1])
    old = command_delay_s(send[m] - t_ans[m] - np.min(rx - vt), P)
    gcs, fit = measure_on(rx, vt, t_ans, send, window)
    assert fit.slips == () and abs(fit.skew_ppm) < 50
    assert gcs.measured and gcs.measured_s == pytest.approx(old, abs=1e-4)


def test_implausible_measurements_fall_back():
    assert not measure_gcs_delay([0.007] * 40, P).measured  # mean over 1.5 periods
    assert measure_gcs_delay([0.007] * 40, P, latency_s=0.002).measured  # within the link's
    g = measure_gcs_delay([0.002] * 30 + [0.02] * 15, P)
    assert not g.measured and "clip" in g.why
    vt = np.arange(0.0, 20.0, P)
    fit = fit_clock(clock_bins(10.0 + vt * (1 + 1500e-6), vt))
    g = measure_gcs_delay([0.002] * 40, P, sample_t_s=np.linspace(5, 6, 40), clock=fit)
    assert not g.measured and "1500 ppm" in g.why
    few = measure_gcs_delay([0.002] * 5, P)
    assert not few.measured and math.isnan(few.measured_s) and few.estimate_s == 0.5 * P


def test_slow_telemetry_counts_first_answers():
    # telemetry at 50 Hz, stream at 250 Hz: a sample is answered five times, 0-16 ms after
    # it came; the loop's delay is the first answer's (here 1 ms), not their mean (7.8 ms)
    t = np.repeat(np.arange(0.0, 2.0, 0.02), 5)
    ages = np.tile([0.001, 0.005, 0.009, 0.013, 0.017], 100)
    g = measure_gcs_delay(ages, P, sample_t_s=t)
    assert g.measured and g.measured_s == pytest.approx(0.001)
    assert command_delay_s(ages, P) == pytest.approx(0.0078)  # all answers, clipped at 12 ms


@pytest.mark.parametrize("name", list(MODELS))
@pytest.mark.parametrize("estimate,lo", [(0.003, 0.002), (0.006, 0.0), (0.012, 0.001)])
def test_robust_design_keeps_margin_over_the_plausible_range(name, estimate, lo):
    K, Tp, T1, tau = MODELS[name]
    ident = identified(K, Tp, T1, tau, 0.003)
    rt = robust_onboard_gains(ident, GcsDelay(estimate, lo, estimate + P, estimate, True))
    tau_id = ident.model.tau
    for d_true in np.linspace(lo, estimate + P, 5):
        assert pm_deg(rt.gains, K, Tp, T1, tau_id - d_true) >= PM_ROBUST_DEG - 0.05, (
            d_true, rt.note())
    assert rt.pm_deg == pytest.approx(pm_deg(rt.gains, K, Tp, T1, tau_id - lo), abs=0.05)
    if not rt.held_back:
        assert rt.delay_s == pytest.approx(min(estimate, 0.5 * tau_id))
    else:
        # held back only as far as needed: a little more re-target loses the margin
        more = onboard_gains(ident, rt.delay_s + 2e-4)
        assert pm_deg(more, K, Tp, T1, tau_id - lo) < PM_ROBUST_DEG
    note = rt.note()
    assert note.startswith(f"re-targeted by {rt.delay_s * 1e3:.1f} ms (measured")
    assert f"plausible {lo * 1e3:.1f}.." in note
