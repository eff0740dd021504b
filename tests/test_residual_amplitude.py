"""Rate limit and saturation told from two relay amplitudes (SITL physics, undeclared)."""

from __future__ import annotations

import pytest

from mrft_gcs.residual.amplitude import amplitude_check
from mrft_gcs.residual.cycles import cycle_wave, uniform
from mrft_gcs.residual.synth import sitl_relay_record


def _cycle(effects, h: float, noise: bool, seed: int = 1):
    rec = sitl_relay_record("roll", effects=effects, seed=seed, beta=-0.7, h=h,
                            duration_s=6.0, noise=noise)
    dt, u, y = uniform(rec.t, rec.u, rec.y)
    w = cycle_wave(u, y, dt, max_cycles=2)
    assert w is not None
    return w.period_s, w.amplitude


@pytest.mark.parametrize(("effects", "verdict"), [
    (None, "linear"), ({"sensor_lpf": 12.0}, "linear"), ({"extra_delay": 0.02}, "linear"),
    ({"torque_rate_limit": 8.0}, "rate_limit"), ({"torque_rate_limit": 2.0}, "rate_limit"),
    ({"motor_saturation": 0.5}, "saturation")])
@pytest.mark.parametrize(("h1", "h2", "noise"), [(0.04, 0.12, False), (0.08, 0.16, True)])
def test_two_amplitudes_tell_rate_limit_and_saturation(effects, verdict, h1, h2, noise):
    chk = amplitude_check(*_cycle(effects, h1, noise), h1, *_cycle(effects, h2, noise), h2)
    assert chk.verdict == verdict, chk
    word = {"linear": "linear", "rate_limit": "rate limit", "saturation": "saturates"}[verdict]
    assert word in chk.note()


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="larger"):
        amplitude_check(0.3, 0.02, 0.12, 0.3, 0.01, 0.04)
    with pytest.raises(ValueError, match="positive"):
        amplitude_check(0.3, 0.0, 0.04, 0.3, 0.01, 0.12)
