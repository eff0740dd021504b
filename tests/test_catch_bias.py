"""The run-away catch must take up a torque bias (a centre of mass off the middle).

A relay sized on its first swing keeps a zero bias (the bias is measured on later periods).
Where the vehicle needs a holding torque that is a large share of the new, smaller h, the
relay runs away and the catch PD takes the axis. A plain PD holds it at rest at
``e = bias / Kc`` off its set point: a random in-domain vehicle needed +0.021 normalised
torque behind a catch of Kc 0.0955 /rad, so roll sat 12.5 deg off its set point, far outside
the envelope the catch hands back in, and the vehicle flew sideways to the 5 m limit.
"""

from __future__ import annotations

from collections import deque

import pytest
from flight_sim import ALT_RELAY, ATT_RELAY

from mrft_gcs.flight.controllers import catch_pd
from mrft_gcs.flight.sequence import LoopState, SequenceConfig, TuningSequence
from mrft_gcs.loops import Loop
from mrft_gcs.relay import MRFT

#: the drifting vehicle's figures: h after sizing on its first swing, the cycle the catch
#: was sized on (period s, amplitude rad), the holding torque (normalised)
H, CYCLE, TRIM = 0.0283, (0.528, 0.12), 0.021
GAIN = 60.0  # rad/s^2 per unit torque
DT = 0.004


def _fly_catch(trim: float, seconds: float = 6.0) -> tuple[float | None, float, float]:
    """Roll in the catch from rest 0.2 rad off its set point (on the side the catch would
    hold it), a torque ``trim`` needed to
    hold it: (time it handed back to the relay or None, the relay's bias then, the angle
    at the end, rad)."""
    seq = TuningSequence(SequenceConfig(hover_thrust_guess=0.5), ATT_RELAY, ALT_RELAY)
    t = seq.loops[Loop.ROLL]
    t.h, t.cycle, t.bias = H, CYCLE, 0.0
    t.state, t.relay = LoopState.RELAY, MRFT(-0.5, H)
    t.catch, t.t_catch_s = catch_pd(H, *CYCLE), 0.0
    t.catch_release = 0.1  # a resized relay: handed back near rest, as in that flight
    y, rate = (-0.2 if trim >= 0 else 0.2), 0.0  # on the side the PD would rest on
    pipe = deque([0.0] * 5)  # 20 ms from command to torque
    back = None
    for i in range(int(seconds / DT)):
        pipe.append(seq.attitude.step(Loop.ROLL, 0.0, y, rate, i * DT, True, True))
        rate += GAIN * (pipe.popleft() - trim) * DT
        y += rate * DT
        if t.catch is None and back is None:
            back = i * DT
            break
    assert t.relay is not None
    return back, float(t.relay.bias[0]), y


def test_the_catch_alone_would_hold_the_axis_far_off_its_set_point():
    """The numbers of the cause: a plain PD's rest point lies outside the hand-back
    envelope (so without integral action the catch never releases)."""
    kc, _ = catch_pd(H, *CYCLE)
    assert TRIM < SequenceConfig().catch_torque_factor * H  # the PD is not at its limit
    assert TRIM / kc > CYCLE[1]  # its rest point: outside the envelope it hands back in


@pytest.mark.parametrize("trim", [TRIM, -TRIM, 0.04])
def test_a_catch_with_a_torque_bias_hands_back_centred_on_it(trim):
    """The catch takes up the holding torque (at least half of it by the hand-back), brings
    roll back towards its set point and hands back to the relay within a few cycle periods.
    A plain PD (no integral) would still hold it 0.22 rad off at the end."""
    back, bias, y = _fly_catch(trim)
    assert back is not None and back < 10 * CYCLE[0], back
    assert bias / trim > 0.5, bias
    assert abs(y) < CYCLE[1]


def test_a_catch_without_bias_still_hands_back_unbiased():
    """No holding torque: the catch hands back as before, its bias near zero."""
    back, bias, _ = _fly_catch(0.0)
    assert back is not None and back < 5 * CYCLE[0], back
    assert abs(bias) < 0.2 * H
