"""Relay controllers: MRFT switching law and the bounding controller."""

from __future__ import annotations

import numpy as np
import pytest

from mrft_gcs.relay import MRFT, BoundingRelay, beta_for_phase, mrft_phase_deg


def run(relay, errors):
    return [float(relay.step(e)[0]) for e in errors]


def test_first_half_cycle_is_a_plain_relay():
    r = MRFT(beta=-0.5, h=2.0, bias=0.5)
    assert run(r, [0.1, 0.2, -0.01, -0.3, 0.01]) == [2.5, 2.5, -1.5, -1.5, 2.5]


def test_negative_beta_switches_before_the_zero_crossing():
    # After the first switch, +h must turn to -h once the error falls to |beta| * e_max.
    r = MRFT(beta=-0.5, h=1.0)
    run(r, [-0.1, 0.1])  # first (plain) switch to +h
    out = run(r, [0.5, 1.0, 0.8, 0.6, 0.49])
    assert out == [1, 1, 1, 1, -1]
    # and -h back to +h once the error rises to |beta| * e_min (still negative)
    out = run(r, [0.2, -0.4, -1.0, -0.7, -0.51, -0.49])
    assert out == [-1, -1, -1, -1, -1, 1]


def test_positive_beta_is_a_hysteresis_after_zero_crossing():
    r = MRFT(beta=0.5, h=1.0)
    run(r, [-0.1, 0.1])  # +h
    out = run(r, [1.0, 0.2, -0.2, -0.49, -0.51])
    assert out == [1, 1, 1, 1, -1]


def test_noise_band_prevents_chatter_near_zero():
    # One full cycle, ending just after the switch to +h, where the error hovers near zero.
    cycle = [-0.5, 0.02, 0.3, 0.1, -0.4, -0.19]
    noisy = [0.001, -0.0005, 0.0015, -0.001]
    chatter = MRFT(beta=-0.5, h=1.0, band=0.0)
    run(chatter, cycle)
    assert chatter.switches[0] == 3 and chatter.state[0] > 0
    run(chatter, noisy)
    assert chatter.switches[0] > 3  # noise arms and fires switches
    calm = MRFT(beta=-0.5, h=1.0, band=0.01)
    run(calm, cycle)
    assert calm.switches[0] == 3
    run(calm, noisy)
    assert calm.switches[0] == 3  # excursions inside the band cannot arm a switch
    run(calm, [0.2, 0.05])  # a real excursion still switches
    assert calm.switches[0] == 4


def test_vectorised_relays_are_independent():
    r = MRFT(beta=[-0.3, 0.3], h=[1.0, 2.0])
    out = r.step(np.array([0.1, -0.1]))
    np.testing.assert_array_equal(out, [1.0, -2.0])


def test_invalid_settings_rejected():
    with pytest.raises(ValueError):
        MRFT(beta=1.0, h=1.0)
    with pytest.raises(ValueError):
        MRFT(beta=0.0, h=0.0)


def test_phase_and_beta_are_inverse():
    for b in (-0.7, -0.2, 0.0, 0.4):
        assert beta_for_phase(mrft_phase_deg(b)) == pytest.approx(b)
    assert mrft_phase_deg(-0.5) == pytest.approx(30.0)  # lead


def test_bounding_relay_eq22():
    b = BoundingRelay(eps1=1.0, eps2=2.0, h1=0.05, h2=0.05)
    assert run(b, [0.5]) == [0.0]  # idle inside eps1
    assert run(b, [1.2]) == [0.05]  # engages at eps1
    assert run(b, [0.5, -0.5]) == [0.05, -0.05]  # once engaged: sign relay
    assert run(b, [-2.5]) == [pytest.approx(-0.1)]  # dead-band relay adds beyond eps2
