"""Residual analysis: exact simulation; effects named on SITL records that do not declare them."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mrft_gcs.loops import LoopKind
from mrft_gcs.plant import InnerModel
from mrft_gcs.residual import RelayTest, analyse_residual
from mrft_gcs.residual.effects import EFFECTS, ExtraDelay, Knobs, candidate_effects
from mrft_gcs.residual.simulate import simulate_effects, simulate_input
from mrft_gcs.residual.synth import sitl_relay_record
from mrft_gcs.simulate import simulate_mrft

MODEL = InnerModel(38.1, 0.02, 0.25, 0.022)
ROLL = dict(beta=-0.5, h=0.08, duration_s=8.0)


class _Signed(ExtraDelay):
    def bounds(self, ctx):
        return -0.01, 0.01


@pytest.fixture(scope="module")
def roll_model() -> InnerModel:
    """The airframe's roll model, delay calibrated once on a clean noise-free run."""
    rec = sitl_relay_record("roll", noise=False, **ROLL)
    rep = analyse_residual(rec.model, RelayTest(rec.beta, rec.h), rec.t, rec.u, rec.y,
                           effects=(_Signed(),), floor=0.0, min_reduction=0.0, redesign=False)
    assert abs(rep.fits[0].value) < 0.003  # the SITL lags its linear model by ~1 ms only
    return replace(rec.model, tau=rec.model.tau + rep.fits[0].value)


def test_neutral_knobs_reproduce_the_reference_simulator():
    k = Knobs.neutral(3)
    k.delay_s[1] = 0.0063
    run = simulate_effects(MODEL, -0.4, 0.05, k, dt=0.004, duration_s=3.0)
    for i, extra in ((0, 0.0), (1, 0.0063)):
        ref = simulate_mrft(MODEL.K, MODEL.T_prop, MODEL.T1, MODEL.tau + extra, -0.4, 0.05,
                            dt=0.004, duration_s=3.0, engine="numpy")
        np.testing.assert_allclose(run.y[i], ref.y[0], atol=1e-12)
        np.testing.assert_array_equal(run.u[i], ref.u[0])


def test_driving_the_model_with_a_runs_commands_gives_its_output_back():
    k = Knobs.neutral(6)
    k.delay_s[1] = 0.0063
    k.lpf_tau_s[2] = 0.01
    k.rate[3] = 3.0
    k.deadzone[4] = 0.01
    k.drag[5], k.bias[5] = 2.0, 0.01
    run = simulate_effects(MODEL, -0.4, 0.05, k, dt=0.004, duration_s=3.0)
    for i in range(k.n):
        y = simulate_input(MODEL, run.u[i], k, 0.004)[i]
        np.testing.assert_allclose(y, run.y[i], rtol=0, atol=1e-12)


def test_every_effect_changes_the_cycle_of_its_loop():
    for kind in (LoopKind.ATTITUDE, LoopKind.ALTITUDE):
        effs = candidate_effects(kind)
        k = Knobs.neutral(len(effs) + 1)
        from mrft_gcs.residual.effects import RelayContext

        ctx = RelayContext(h=0.05, bias=0.0, period_s=0.4, amplitude=0.03, dt=0.004)
        for i, e in enumerate(effs):
            lo, hi = e.bounds(ctx)
            e.apply(k, np.array([i + 1]), np.array([lo + 0.7 * (hi - lo)]))
        run = simulate_effects(MODEL, -0.4, 0.05, k, dt=0.004, duration_s=4.0, keep_s=1.0)
        for i, e in enumerate(effs):
            assert np.abs(run.y[i + 1] - run.y[0]).max() > 1e-4, e.name
    assert {e.name for e in EFFECTS} >= {"input_bias", "extra_delay", "sensor_lpf",
                                        "actuator_saturation", "actuator_rate_limit",
                                        "quadratic_drag", "motor_deadzone", "thrust_curve"}


def test_undeclared_sensor_lpf_is_named_with_its_cutoff(roll_model):
    rec = sitl_relay_record("roll", effects={"sensor_lpf": 15.0}, seed=3, **ROLL)
    rep = analyse_residual(roll_model, RelayTest(rec.beta, rec.h), rec.t, rec.u, rec.y,
                           band=rec.band)
    assert rep.effect == "sensor_lpf"
    assert rep.effect_params["cutoff_hz"] == pytest.approx(15.0, rel=0.2)
    assert rep.rms_after < 0.3 * rep.rms_before
    # A filter adds lag: the re-designed PD is gentler.
    assert rep.gains_with_effect.Kc < rep.gains_model.Kc


def test_clean_record_names_no_effect(roll_model):
    rec = sitl_relay_record("roll", seed=11, **ROLL)
    rep = analyse_residual(roll_model, RelayTest(rec.beta, rec.h), rec.t, rec.u, rec.y,
                           band=rec.band, redesign=False)
    assert rep.effect is None and rep.effect_params == {}
    assert rep.rms_after == rep.rms_before < rep.threshold
    assert rep.as_dict() == {"rms_before": rep.rms_before, "rms_after": rep.rms_before,
                             "effect": None, "effect_params": {}}


def test_undeclared_torque_bias_is_named_input_bias(roll_model):
    rec = sitl_relay_record("roll", effects={"input_bias": 0.02}, seed=5, **ROLL)
    rep = analyse_residual(roll_model, RelayTest(rec.beta, rec.h), rec.t, rec.u, rec.y,
                           band=rec.band, redesign=False)
    assert rep.effect == "input_bias"
    assert rep.effect_params["bias"] == pytest.approx(0.02, rel=0.25)
    assert rep.before.duty != 0


def test_no_cycle_is_an_identification_error():
    from mrft_gcs.errors import IdentificationError

    t = np.arange(0, 2, 0.004)
    with pytest.raises(IdentificationError, match="relay cycle"):
        analyse_residual(MODEL, RelayTest(-0.5, 0.08), t, np.full(t.size, 0.08), t)


def test_undeclared_rate_limit_is_told_from_a_delay(roll_model):
    # Closed loop, a rate limit and a delay both lengthen the period; the response to
    # each recorded switch (a ramp of the input against a shift) tells them apart.
    rec = sitl_relay_record("roll", effects={"torque_rate_limit": 3.0}, seed=7, **ROLL)
    rep = analyse_residual(roll_model, RelayTest(rec.beta, rec.h), rec.t, rec.u, rec.y,
                           band=rec.band, redesign=False)
    assert rep.effect == "actuator_rate_limit"
    assert rep.effect_params["rate"] == pytest.approx(3.0, rel=0.15)
    assert rep.open_loop[0].name == "actuator_rate_limit"
    assert rep.open_loop[1].rms > 1.1 * rep.open_loop[0].rms
    assert rep.rms_after < 0.2 * rep.rms_before


def test_a_biased_relay_tells_a_dead_zone_from_saturation(roll_model):
    # Without a relay bias both only shrink the two levels alike; with one, a dead zone
    # shrinks both levels by the same amount, a saturation clips the larger one only.
    rec = sitl_relay_record("roll", effects={"motor_deadzone": 0.02}, seed=2,
                            relay_bias=0.02, **ROLL)
    rep = analyse_residual(roll_model, RelayTest(rec.beta, rec.h, rec.bias), rec.t, rec.u,
                           rec.y, band=rec.band, redesign=False)
    assert rep.effect == "motor_deadzone"
    assert rep.effect_params["deadband"] == pytest.approx(0.02, rel=0.25)
    sat = next(f for f in rep.fits if f.name == "actuator_saturation")
    assert sat.rms > 3 * rep.rms_after
