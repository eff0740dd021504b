"""The rate path under host load: the ground station's roll/pitch PDs and yaw's wait."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mrft_gcs.flight.config import SequenceConfig
from mrft_gcs.flight.controllers import FlightState
from mrft_gcs.flight.ratepath import (
    GCS_PD_SCALE,
    RING_RMS_RAD_S,
    YAW_AFTER_ROLL_PITCH_S,
    RateChannel,
    yaw_wait_over,
)
from mrft_gcs.flight.sequence import TuningSequence
from mrft_gcs.identify import Identification, relay_settings
from mrft_gcs.loops import Loop, LoopKind
from mrft_gcs.pd_design import PD
from mrft_gcs.plant import InnerModel
from mrft_gcs.profiles import load_profile
from mrft_gcs.telemetry import ActuatorTarget

#: roll/pitch models and PDs identified through the rate path on ArduCopter 4.7 SITL
#: (K, T_prop, T1, tau; Kc, Kd): the spread of one vehicle over five runs
IDENTIFIED = [
    (98.67, 0.00476, 0.313, 0.00853, 6.71, 0.2279),
    (34.23, 0.00905, 0.1018, 0.0065, 5.97, 0.2096),
    (268.3, 0.01329, 0.8746, 0.00433, 5.70, 0.2446),
    (242.2, 0.01029, 0.677, 0.00335, 8.32, 0.2726),
]


def _phase_margin_deg(m: InnerModel, kc: float, kd: float, extra_delay_s: float) -> float:
    """Phase margin of ``(Kc + Kd s) K e^-(tau + extra) s / (s (T1 s + 1)(T_prop s + 1))``
    at its highest gain crossover (deg)."""
    w = np.logspace(0, 3, 100_000)
    s = 1j * w
    loop = ((kc + kd * s) * m.K * np.exp(-(m.tau + extra_delay_s) * s)
            / (s * (m.T1 * s + 1) * (m.T_prop * s + 1)))
    over = np.nonzero(np.abs(loop) >= 1.0)[0]
    phase = np.unwrap(np.angle(loop))
    return 180.0 + math.degrees(float(phase[over[-1]]))


@pytest.mark.parametrize("k, tp, t1, tau, kc, kd", IDENTIFIED)
def test_ground_station_pd_keeps_its_margin_with_8_ms_more_delay(k, tp, t1, tau, kc, kd):
    """The identified roll PD as the sequence flies it on the ground station (rate path
    scale) keeps 15 deg of phase margin with 8 ms more delay than identified: the GCS loop's
    delay grew that much on a loaded host and the PD with both gains halved rang at
    200 deg/s rms (0-8 deg of margin left on these models)."""
    model = InnerModel(k, tp, t1, tau)
    seq = TuningSequence(SequenceConfig(gcs_attitude_pd_scale=GCS_PD_SCALE),
                         relay_settings(LoopKind.ATTITUDE), relay_settings(LoopKind.ALTITUDE))
    seq.apply(Loop.ROLL, Identification(LoopKind.ATTITUDE, model, 0, 1.0, -0.7, 0.1, 0.02,
                                        0.1, PD(kc, kd)))
    pd = seq.loops[Loop.ROLL].pd
    assert pd is not None and pd.Kd == pytest.approx(GCS_PD_SCALE * kd)
    # as designed, the PD itself keeps its margin on the identified model
    assert _phase_margin_deg(model, kc, kd, 0.0) > 14.0
    assert _phase_margin_deg(model, pd.Kc, pd.Kd, 0.008) >= 15.0


def _state(t: float, p: float, q: float) -> FlightState:
    return FlightState(t, 0.0, 0.0, 0.0, p, q, 0.0, t, 0, 0, 1, 0, 0, 0)


def test_channel_measures_a_ringing_pitch_and_yaw_stops_waiting():
    rp = load_profile("ardupilot").rate_path
    assert rp is not None
    ch = RateChannel(rp)
    out = ActuatorTarget(0.0, 0.0, 0.0, 0.0, 0.4)
    # pitch rings at 48 rad/s, 4 rad/s amplitude (ArduCopter SITL's pitch beside the yaw
    # relay); roll at rest. ATTITUDE at 200 Hz, the stream's ticks at 250 Hz repeat it
    for i in range(500):
        t = round(i / 250 * 200) / 200
        ch.step(out, _state(t, 0.01, 4.0 * math.sin(48.0 * t)))
    rms = ch.rp_rms
    assert rms[1] == pytest.approx(4.0 / math.sqrt(2), rel=0.2) and rms[0] < 0.05
    why = yaw_wait_over(1.0, rms)
    assert why is not None and why.startswith("pitch rang on the ground station's PD")
    # the same pitch at rest: yaw waits on, up to its cap after roll and pitch
    for i in range(500, 1000):
        ch.step(out, _state(i / 200, 0.01, 0.02))
    assert float(np.max(ch.rp_rms)) < RING_RMS_RAD_S / 10
    assert yaw_wait_over(1.0, ch.rp_rms) is None
    assert yaw_wait_over(YAW_AFTER_ROLL_PITCH_S + 0.01, ch.rp_rms) is not None


def test_check_probe_settles_on_its_centre_and_flags_a_growing_swing():
    """The rate path's in-air check holds its centre after the square waves (the input
    shaping put back mid-swing carried ArduCopter SITL's target to 49 deg) and flags a
    swing past ``CHECK_SWING`` amplitudes (the caller lands on the vehicle's own gains)."""
    from mrft_gcs.flight.inair import SquareWaveProbe, plan_check
    from mrft_gcs.flight.ratepath import CHECK_AMPLITUDE_RAD, CHECK_SETTLE_S, CHECK_SWING

    plan = plan_check(InnerModel(40.0, 0.03, 0.2, 0.01), PD(0.8, 0.1), CHECK_AMPLITUDE_RAD)
    probe = SquareWaveProbe({Loop.ROLL: plan}, (0.01, 0.0), swing_limit=CHECK_SWING,
                            settle_s=CHECK_SETTLE_S)
    t, out = 0.0, []
    while not probe.done:
        out.append((t, *probe.step(t, t, 0.01, 0.0)))
        t += 0.004
    a = np.array(out)
    waves = a[a[:, 0] < plan.duration_s - 0.01]
    after = a[a[:, 0] > plan.duration_s + 0.01]
    assert np.ptp(waves[:, 1]) == pytest.approx(2 * CHECK_AMPLITUDE_RAD)
    assert after[-1, 0] >= plan.duration_s + CHECK_SETTLE_S - 0.01
    assert np.all(after[:, 1] == 0.01) and probe.swing_over is None
    probe.step(t, t, 0.01 + 0.9 * CHECK_SWING * CHECK_AMPLITUDE_RAD, 0.0)
    assert probe.swing_over is None
    probe.step(t + 0.004, t + 0.004, 0.01 - 1.1 * CHECK_SWING * CHECK_AMPLITUDE_RAD, 0.0)
    assert probe.swing_over is not None and probe.swing_over[0] is Loop.ROLL
