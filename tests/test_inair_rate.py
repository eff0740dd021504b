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


def _flown(period: float, lag_s: float, tau_s: float, delay_s: float, seed: int,
           drop_edge: bool = False):
    """A rate-path check flown on a simulated vehicle with ArduCopter's timing: set points
    from a 250 Hz ground-station tick reach the vehicle ``lag_s`` later and become the target
    at its next 400 Hz tick; the angle follows the target through a first-order lag ``tau_s``
    and a delay ``delay_s``; ATTITUDE and ATTITUDE_TARGET are reported together every one or
    two ticks (vehicle clock in whole ms); ``drop_edge``: the record misses 60 ms from the
    third switch. Returns the probe and the exact ``T`` at the fundamental of that loop."""
    from mrft_gcs.flight.inair import CheckPlan, SquareWaveProbe
    from mrft_gcs.loops import Loop

    rng = np.random.default_rng(seed)
    amp = math.radians(1.0)
    plan = CheckPlan(MODEL, GAINS, period, amp, 12, 2 * math.pi / period, 40.0)
    probe = SquareWaveProbe({Loop.ROLL: plan}, settle_s=0.2)
    tick = 0.0025
    clock = 3.1234  # vehicle clock minus the ground station's
    t = 10.0 + rng.uniform(0, 0.004)
    sends: list[tuple[float, float]] = []  # ground-station time, set point
    switches = [(0.0, 0.0)]  # vehicle time, target
    samples: list[float] = []
    nxt = 10.0 + clock
    target = 0.0

    def angle(tv: float) -> float:  # the response to the target's switches so far
        y = 0.0
        for i in range(1, len(switches)):
            ts, level = switches[i]
            dt = tv - ts - delay_s
            if dt > 0:
                y += (level - switches[i - 1][1]) * (1 - math.exp(-dt / tau_s))
        return y

    while not probe.done:
        while nxt <= t + clock:  # the vehicle's ticks up to now
            arrived = [u for ts, u in sends if ts + lag_s + clock <= nxt]
            if arrived and arrived[-1] != target:
                target = arrived[-1]
                switches.append((nxt, target))
            if not samples or nxt - samples[-1] >= tick * rng.choice([1, 2]) - 1e-9:
                ms = math.floor(nxt * 1000) / 1000
                samples.append(nxt)
                if not (drop_edge and len(switches) >= 4 and nxt - switches[3][0] < 0.06):
                    probe.track(ms, target, 0.0)
            nxt += tick
        ts_att = math.floor(samples[-1] * 1000) / 1000
        r, _ = probe.step(t, ts_att, angle(samples[-1]), 0.0)
        sends.append((t, r))
        t += 0.004
    w = 2 * math.pi / period
    exact = np.exp(-1j * w * delay_s) / (1 + 1j * w * tau_s)
    return probe, exact


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_check_points_time_edges_on_the_vehicle_record(seed: int) -> None:
    # a 14 Hz square wave (a 90 rad/s crossover): 1 ms is 5 deg of phase there, and the
    # edges sent on a 4 ms tick jitter by up to 2 ms
    from mrft_gcs.flight.ratepath import check_points
    from mrft_gcs.loops import Loop

    probe, exact = _flown(0.07, 0.0015 + 0.001 * seed, 0.012, 0.003, seed)
    points, how = check_points(probe)
    w, T, se = points[Loop.ROLL]
    assert "edge" in how[Loop.ROLL] and se[0] < 0.05
    assert abs(np.degrees(np.angle(T[0] / exact))) < 3.0  # the check's own bar
    assert abs(T[0]) == pytest.approx(abs(exact), rel=0.05)


def test_check_points_without_an_edge_measures_nothing() -> None:
    from mrft_gcs.flight.ratepath import check_points
    from mrft_gcs.loops import Loop

    probe, _ = _flown(0.07, 0.002, 0.012, 0.003, 0, drop_edge=True)
    points, how = check_points(probe)
    assert Loop.ROLL not in points and how[Loop.ROLL].startswith("none")


def test_check_cascade_keeps_the_feedback_path() -> None:
    # the check flies without the target's own rate fed forward: the set-point path changes,
    # the feedback path (and so the margin) is the written loop's
    from mrft_gcs.flight.ratepath import check_cascade

    written = OnboardCascade(20.0, integrator_zero_rad_s=8.0, d_over_p_s=0.0267,
                             d_filter_hz=20.0)
    flown = check_cascade(written)
    w = np.array([30.0, 90.0])
    assert not flown.target_rate_ff and written.target_rate_ff
    assert np.allclose(flown.paths(GAINS, w)[1], written.paths(GAINS, w)[1])
    assert not np.allclose(flown.paths(GAINS, w)[0], written.paths(GAINS, w)[0])
