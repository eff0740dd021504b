"""Roll/pitch relays: a set point step waits for a switch; a smaller h is taken at a turn."""

from __future__ import annotations

import numpy as np
import pytest
from flight_sim import ALT_RELAY, ATT_RELAY, lockstep_with_events

from mrft_gcs.flight.phases.state import LoopState
from mrft_gcs.flight.sequence import SequenceConfig, TuningSequence
from mrft_gcs.loops import Loop
from mrft_gcs.relay import MRFT


def _fly_step(step_at_s: float, at_switch: bool, gain: float = 300.0, delay_s: float = 0.03,
              h: float = 0.04, step_rad: float = 0.05, dur_s: float = 4.0, dt: float = 0.004):
    """A sized roll relay on ``gain e^(-s delay) / s^2`` whose set point steps by
    ``step_rad`` at ``step_at_s`` (the bounding relay's tilt command): the times of its
    switches and the angles."""
    cfg = SequenceConfig(att_ref_at_switch=at_switch)
    seq = TuningSequence(cfg, ATT_RELAY, ALT_RELAY)
    t = seq.loops[Loop.ROLL]
    t.h, t.state, t.relay, t.band = h, LoopState.RELAY, MRFT(-0.7, h), 0.003
    t.sized = t.centred = True
    t.resizes = cfg.att_max_resizes  # no sizing: the relay as it is
    y = w = 0.0
    k = round(delay_s / dt)
    us, ys, switches, prev = [], [], [], 0.0
    for i in range(int(dur_s / dt)):
        ts = i * dt
        u = seq.attitude.step(Loop.ROLL, step_rad if ts >= step_at_s else 0.0, y, w, ts, True,
                              True)
        st = float(t.relay.state[0])
        if prev and st != prev:
            switches.append(ts)
        prev = st
        us.append(u)
        w += gain * (us[i - k] if i >= k else 0.0) * dt
        y += w * dt
        ys.append(y)
    return np.array(switches), np.array(ys)


def test_a_set_point_step_mid_swing_waits_for_the_relays_next_switch():
    """The bounding relay steps roll's set point by 0.05 rad while its relay swings 0.1 rad:
    taken at once, a step at the wrong moment moved the error past the MRFT's threshold and
    switched the relay early into a short cycle (down to 6 % of a half-period here), whose
    small amplitude then had the next normal swing caught as a run-away. Taken at a switch,
    every half-period stays whole and the cycle settles about the new set point."""
    shortest = {}
    for at_switch in (True, False):
        ratios = []
        for step_at in np.arange(2.0, 2.5, 0.02):  # over a whole period of the cycle
            sw, ys = _fly_step(float(step_at), at_switch)
            half = np.diff(sw)
            nominal = float(np.median(half[3:10]))  # before the step
            ratios.append(float(half[sw[1:] > 1.0].min()) / nominal)
            if at_switch:
                late = ys[-250:]  # the last second: the cycle about the new set point
                assert 0.5 * (late.max() + late.min()) == pytest.approx(0.05, abs=0.02)
        shortest[at_switch] = min(ratios)
    assert shortest[True] > 0.6, shortest
    assert shortest[False] < 0.3, shortest  # the step taken at once: what the rule prevents


def test_a_relay_resized_to_a_smaller_h_goes_on_from_the_turn_of_the_axis(monkeypatch):
    """An 82 g in-domain vehicle: its pitch relay's first swing and then its steady period
    swing over 1.25 x ``att_amp_max_rad``. The smaller h taken at the turn of the axis,
    without the catch's wait at rest (up to three periods each), tunes it sooner, to gains
    as good."""
    on, events = lockstep_with_events(monkeypatch, 3)
    off, events_off = lockstep_with_events(monkeypatch, 3, att_resize_at_turn=False)
    assert any("pitch: relay sized on a period" in e and "from this turn of the axis" in e
               for e in events), events
    assert not any("from this turn" in e for e in events_off), events_off
    assert on["outcome"] == off["outcome"] == "completed"
    assert on["time_to_tune_s"] < off["time_to_tune_s"] - 1.0
    for lp in ("roll", "pitch"):
        assert on["loops"][lp]["onboard_pm_deg"] >= 15.0
        assert on["loops"][lp]["onboard_J_pct"] <= 10.0
