"""The MRFT cycle predicted from the torque-bias fit against a relay run on the same axis."""

from __future__ import annotations

import math

import numpy as np
import pytest
from flight_sim import lockstep_with_events

from mrft_gcs.flight.phases.attitude import predicted_swing, torque_bias_fit
from mrft_gcs.flight.sequence import SequenceConfig, TuningSequence
from mrft_gcs.relay import MRFT


def _run(gain: float, drag: float, delay_s: float, lag_s: float, h: float, beta: float,
         dur_s: float = 4.0, dt: float = 1e-3):
    """An MRFT on ``gain e^(-s delay) / (s (s + drag) (lag s + 1))`` from rest: times,
    commands, rates and angles."""
    n = int(dur_s / dt)
    relay = MRFT(beta, h)
    y = w = m = 0.0
    k = round(delay_s / dt)
    u = np.zeros(n)
    ts, ws, ys = np.arange(n) * dt, np.zeros(n), np.zeros(n)
    for i in range(n):
        ws[i], ys[i] = w, y
        u[i] = float(relay.step(np.array([0.01 - y]))[0])
        ud = u[i - k] if i >= k else 0.0
        m += (ud - m) * (dt / lag_s if lag_s else 1.0)
        w += (gain * m - drag * w) * dt
        y += w * dt
    return ts, u, ws, ys


@pytest.mark.parametrize(("gain", "drag", "delay_s", "lag_s"),
                         [(500.0, 0.0, 0.03, 0.0), (1000.0, 0.6, 0.03, 0.03),
                          (600.0, 1.5, 0.05, 0.02)])
def test_predicted_swing_matches_the_relay_on_the_fitted_axis(gain, drag, delay_s, lag_s):
    beta, h = -0.7, 0.06
    ts, u, ws, ys = _run(gain, drag, delay_s, lag_s, h, beta)
    # the first swings from rest, as the relay fits them before its first period
    sel = (ts > 0.05) & (ts < 0.6)
    fit = torque_bias_fit(ts, u, ts[sel], ws[sel], ys[sel])
    assert fit is not None and fit.r2 > 0.99
    assert fit.lag_s == pytest.approx(lag_s, abs=0.021)
    period, amp = predicted_swing(fit, h, beta)
    late = ts > 2.5  # the steady cycle
    amp_run = 0.5 * float(np.ptp(ys[late]))
    # the describing function underrates a square push on a double integrator (10-15 %), and
    # the fit's lag grid (20 ms steps) the lag's phase: within a third, never over it
    assert amp == pytest.approx(amp_run, rel=0.35) and amp < amp_run
    crossings = np.flatnonzero(np.diff(np.sign(ys[late] - 0.01)) > 0)
    period_run = float(np.mean(np.diff(ts[late][crossings])))
    assert period == pytest.approx(period_run, rel=0.2)


def test_no_swing_predicted_without_lead_delay_or_lag():
    fit = torque_bias_fit(*(lambda r: (r[0], r[1], r[0][50:900], r[2][50:900]))(
        _run(500.0, 0.0, 0.03, 0.0, 0.06, -0.7)))
    assert fit is not None
    nodelay = type(fit)(fit.gain, 0.0, 0.0, 0.0, 1.0)
    assert all(math.isnan(x) for x in predicted_swing(nodelay, 0.06, 0.0))


def test_a_swing_the_fit_predicts_too_large_is_braked_and_the_relay_lowered(monkeypatch):
    """An 82 g vehicle behind 30-40 ms of loop delay: at the starting h its roll relay's
    first swings tilt it 23 deg with pitch's. The fit of its first swings predicts that
    cycle; the push then starting brakes the swing under way harder, and the relay takes
    the smaller h from the axis' turn on: it tilts less at take-off and still tunes."""
    on, events = lockstep_with_events(monkeypatch, 3)
    off, events_off = lockstep_with_events(monkeypatch, 3, att_pred_amp_rad=0.0)
    assert any("roll: the fit predicts" in e and "braked" in e for e in events), events
    assert not any("the fit predicts" in e for e in events_off), events_off
    assert on["outcome"] == off["outcome"] == "completed"
    tilt_on = on["max_tilt_by_phase"]["take-off"]
    tilt_off = off["max_tilt_by_phase"]["take-off"]
    assert tilt_on < tilt_off - 2.0 and tilt_on < 21.0, (tilt_on, tilt_off)


def test_a_catch_held_at_rest_off_its_set_point_takes_the_torque_bias_and_hands_back():
    """The relay's run-away catch (a PD without I) on an axis with a torque bias the relay
    lacked can sit at rest just outside the envelope it hands back in: the vehicle leans
    there for good and drifts off. At rest for a cycle, its torque becomes the relay's
    bias, and the catch hands the axis back to the relay."""
    from flight_sim import ALT_RELAY, ATT_RELAY

    from mrft_gcs.flight.phases.state import LoopState
    from mrft_gcs.loops import Loop

    seq = TuningSequence(SequenceConfig(), ATT_RELAY, ALT_RELAY)
    t = seq.loops[Loop.ROLL]
    t.h, t.state, t.relay = 0.028, LoopState.RELAY, MRFT(-0.7, 0.028)
    t.catch, t.cycle, t.t_catch_s = (0.094, 0.0124), (0.528, 0.12), -10.0
    gain, b_true, dt = 300.0, 0.021, 0.004  # rad/s^2 per unit torque; the CoM's torque
    y, rate, held = -0.3, 0.0, 0.0  # comes to rest at -b/Kc = -0.22 rad, outside 0.12
    for k in range(int(4.0 / dt)):
        u = seq.attitude.step(Loop.ROLL, 0.0, y, rate, k * dt, True, True)
        rate += gain * (u - b_true) * dt
        y += rate * dt
        if t.catch is None:
            break
        held = k * dt
    assert t.catch is None, (y, t.bias)
    assert t.bias == pytest.approx(b_true, rel=0.05)
    assert held < 2.5
    assert any("held at rest off its set point" in e for e in seq.events), seq.events


def test_a_relay_that_keeps_running_away_stops_the_tests_before_the_drift_limit(monkeypatch):
    """An out-of-domain 1.6 kg vehicle (motor lag 68 ms): its roll relay runs away again
    and again, each catch leaning it the same way, and without a limit on run-aways it
    drifted to the 5 m limit. The fifth stops the tests with the reason (a refusal). The
    drift guard, the other net under it, is off here, and the bounding relay's set point
    steps reach the relay at once (``att_ref_at_switch`` off), as when these run-aways were
    seen: taken at the relay's switches they no longer run it away, and the drift guard
    stops this vehicle instead."""
    from mrft_gcs.flight import safety

    monkeypatch.setattr(safety, "DRIFT_GUARD_FRACTION", 10.0)
    rec, _ = lockstep_with_events(monkeypatch, 9, att_ref_at_switch=False)
    assert rec["outcome"] == "refused" and "ran away 5 times" in rec["reason"], rec["reason"]
    rec, _ = lockstep_with_events(monkeypatch, 9, att_ref_at_switch=False, max_runaways=10 ** 6)
    assert rec["outcome"] == "aborted" and "5 m limit" in rec["reason"], rec["reason"]
