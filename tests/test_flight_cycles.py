"""The per-loop cycle watcher shared by the live sequence and dry-run."""

from __future__ import annotations

import doctest
import math

import numpy as np
import pytest

from mrft_gcs.flight import cycles
from mrft_gcs.flight.config import SequenceConfig
from mrft_gcs.flight.cycles import CycleRules, CycleWatcher
from mrft_gcs.loops import Loop


def test_doctests():
    assert doctest.testmod(cycles).failed == 0


def _relay(watch: CycleWatcher, periods_s, dt=0.004, t0=0.0):
    """Feed square-wave relay cycles of the given periods; the verdict at each rise."""
    verdicts, t = [], t0
    for p in periods_s:
        n = max(2, round(p / dt))
        for k in range(n):
            watch.update(t, 1.0 if k < n // 2 else -1.0, math.sin(2 * math.pi * k / n))
            if watch.rose:
                verdicts.append(watch.steady)
            t += dt
    return verdicts, t


def test_short_cycles_get_a_tolerance_of_a_few_samples():
    """A 60 ms cycle at 4 ms samples is known to one sample (7 %): a 5 % tolerance would
    never call it steady, 2.5 sample intervals does."""
    jitter = [0.060, 0.064, 0.060, 0.064, 0.060, 0.064, 0.060]
    verdicts, _ = _relay(CycleWatcher(CycleRules(n_periods=3)), jitter)
    assert any(verdicts)
    assert math.isnan(CycleWatcher(CycleRules()).dt_s)  # no interval before a period
    narrow, _ = _relay(CycleWatcher(CycleRules(n_periods=3, sample_intervals=0.0)), jitter)
    assert not any(narrow)


def test_relaxed_tolerance_from_relax_after_cycles_and_restart():
    """Periods spreading 6 %: never steady within 5 %; steady from the ``relax_after``-th
    cycle on. A restart forgets the cycles (the count starts over) but keeps the
    telemetry interval."""
    kicked = [0.200, 0.212] * 8
    strict, _ = _relay(CycleWatcher(CycleRules(n_periods=3)), kicked)
    assert not any(strict)
    w = CycleWatcher(CycleRules(n_periods=3, relax_after=8))
    relaxed, t = _relay(w, kicked)
    # verdict k is taken once k cycles are complete (the first rise completes none)
    assert not any(relaxed[:8]) and all(relaxed[8:])
    dt = w.dt_s
    w.restart()
    assert w.status.cycles == 0 and not w.steady and w.cycles() is None
    assert w.dt_s == dt
    again, _ = _relay(w, kicked[:5], t0=t)
    assert not any(again)
    w.reset()
    assert math.isnan(w.dt_s)


def test_hands_over_the_last_identify_cycles_cycles():
    w = CycleWatcher(CycleRules(n_periods=2, identify_cycles=3))
    _relay(w, [0.2] * 6)
    assert w.steady
    t, u, y = w.cycles()
    assert t[-1] - t[0] == pytest.approx(0.6, abs=0.005)
    assert np.sum(np.diff(u) > 0) == 3  # three rising switches inside, the window opens on one


@pytest.mark.parametrize("loop, n_periods, n_cycles, relax", [
    (Loop.ROLL, 3, 4, 8), (Loop.PITCH, 3, 4, 8), (Loop.ALTITUDE, 2, 3, None),
    (Loop.X, 2, 3, None), (Loop.Y, 2, 3, None)])
def test_sequence_config_gives_each_loop_its_rules(loop, n_periods, n_cycles, relax):
    """The live sequence and dry-run take a loop's rules from one place."""
    from mrft_gcs.flight.sequence import TuningSequence
    from mrft_gcs.identify import RelaySettings

    cfg = SequenceConfig()
    rules = cfg.cycle_rules(loop)
    assert (rules.n_periods, rules.identify_cycles, rules.relax_after) == (
        n_periods, n_cycles, relax)
    assert rules.period_tol == cfg.period_tol and rules.relaxed_tol == cfg.relaxed_tol
    seq = TuningSequence(cfg, RelaySettings(-0.7, 0.1), RelaySettings(-0.3, 0.1))
    assert seq.loops[loop].watch.rules == rules
