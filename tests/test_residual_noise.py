"""Residual analysis on an identified model: a sensor low-pass named from the noise's colour."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mrft_gcs.residual import RelayTest, analyse_residual
from mrft_gcs.residual.noise import noise_colour
from mrft_gcs.residual.synth import sitl_relay_record

DT = 0.004
ROLL = dict(beta=-0.7, h=0.08, duration_s=8.0)


def _ar1(cutoff_hz: float, n: int, seed: int) -> np.ndarray:
    """White noise through a first-order low-pass run at 1 kHz, sampled at 250 Hz."""
    w = np.random.default_rng(seed).standard_normal(4 * n)
    k = 1.0 - np.exp(-2 * np.pi * cutoff_hz * 1e-3)
    out, s = np.empty_like(w), 0.0
    for i, x in enumerate(w):
        s += k * (x - s)
        out[i] = s
    return out[::4]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_white_noise_is_white_and_filtered_noise_is_coloured(seed):
    t = np.arange(2000) * DT
    cycle = 0.05 * np.sin(2 * np.pi * 2.8 * t)
    white = noise_colour(cycle + 1e-3 * np.random.default_rng(seed).standard_normal(t.size),
                         DT, cycle)
    assert white is not None and not white.coloured
    assert white.rho1 == pytest.approx(white.rho1_white, abs=0.1)
    for fc in (30.0, 12.0):
        col = noise_colour(cycle + 1e-3 * _ar1(fc, t.size, seed) / _ar1(fc, t.size, seed).std(),
                           DT, cycle)
        assert col is not None and col.coloured, fc
    # no noise at all: what the high-pass leaves is the cycle's own shape, not colour
    assert not noise_colour(cycle + 1e-9 * np.sin(t * 900.0), DT, 0.99 * cycle).coloured


@pytest.mark.parametrize("seed", [3, 4])
def test_lpf_is_named_when_the_identified_model_already_holds_its_lag(seed):
    """A live tune gives the residual analysis the identified model, which fitted the
    cycle with the filter inside it (here: the filter's time constant added to T_prop):
    the cycle then shows nothing of the filter (input_bias or nothing had been named on
    live tunes with a 10-15 Hz filter), its coloured noise does."""
    rec = sitl_relay_record("roll", effects={"sensor_lpf": 12.0}, seed=seed, **ROLL)
    holds = replace(rec.model, T_prop=rec.model.T_prop + 1 / (2 * np.pi * 12.0))
    rep = analyse_residual(holds, RelayTest(rec.beta, rec.h), rec.t, rec.u, rec.y,
                           band=rec.band)
    assert rep.effect == "sensor_lpf"
    assert "low-pass" in rep.design_note
    if rep.rms_after == rep.rms_before:  # named from the noise alone: gains as they were
        assert rep.gains_model == rep.gains_with_effect


@pytest.mark.parametrize("effect", [None, {"extra_delay": 0.01}, {"torque_rate_limit": 4.0},
                                    {"input_bias": 0.02}])
def test_no_lpf_named_where_the_noise_is_white(effect):
    rec = sitl_relay_record("roll", effects=effect, seed=5, **ROLL)
    rep = analyse_residual(rec.model, RelayTest(rec.beta, rec.h), rec.t, rec.u, rec.y,
                           band=rec.band, redesign=False)
    assert rep.effect != "sensor_lpf"
    assert rep.effect is None or effect is not None
