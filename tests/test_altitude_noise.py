"""The altitude relay against a noisy height: refused at the take-off command, with the reason,
where its cycles could not arm their switches inside the run-away guard; sized from the noise
otherwise."""

from __future__ import annotations

import numpy as np
import pytest

from mrft_gcs.errors import IdentificationError
from mrft_gcs.flight.config import SequenceConfig
from mrft_gcs.flight.phases.altitude import AltitudeRelay
from mrft_gcs.flight.phases.shared import Shared
from mrft_gcs.flight.takeoff import TakeoffController
from mrft_gcs.identify import RelaySettings
from mrft_gcs.loops import Loop
from mrft_gcs.relay import MRFT


def _relay_on_ground_noise(sigma_m: float) -> tuple[AltitudeRelay, Shared]:
    cfg = SequenceConfig()
    sh = Shared(cfg, TakeoffController(z_ref_m=cfg.z_ref_m))
    rng = np.random.default_rng(3)
    for i in range(250):  # one second of ground samples, as the sequence feeds them
        sh.pos_noise.update(0.004 * i, (0.0, 0.0, float(rng.normal(0.0, sigma_m))))
    return AltitudeRelay(sh, RelaySettings(beta=-0.7, h=0.1)), sh


@pytest.mark.parametrize("sigma_m", [0.008, 0.012, 0.019])
def test_noise_too_large_for_the_relay_is_refused_at_take_off(sigma_m):
    alt, sh = _relay_on_ground_noise(sigma_m)
    with pytest.raises(IdentificationError, match="too noisy for the relay test") as err:
        alt.start(0.0)
    band = sh.loops[Loop.ALTITUDE].band
    assert f"{100 * band:.1f} cm" in str(err.value)
    assert 3.0 * band / 0.3 > sh.config.runaway_floor_alt_max_m


@pytest.mark.parametrize("sigma_m", [0.0005, 0.004])
def test_quiet_altitude_starts_and_its_guard_floor_grows_with_the_noise(sigma_m):
    alt, sh = _relay_on_ground_noise(sigma_m)
    alt.start(0.0)
    t = sh.loops[Loop.ALTITUDE]
    relay = MRFT(t.beta, 0.1, band=t.band)
    relay.step(0.0)
    floor = max(sh.config.runaway_floor[1], 3.0 * t.band / 0.3)
    assert floor <= sh.config.runaway_floor_alt_max_m
    # the relay pushing the error out (state and error of opposite signs) just inside the
    # floor is left alone, just past it is caught
    relay.state[:] = -1.0
    sh.watch(t, relay, 0.99 * floor, -1.0)
    assert t.runaways == 0
    relay.state[:] = -1.0
    sh.watch(t, relay, 1.01 * floor, -1.0)
    assert t.runaways == 1
