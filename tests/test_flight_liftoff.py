"""Lift-off and the first seconds of the roll/pitch relays on vehicles with a torque bias
(a centre-of-mass offset) or an agile airframe, on the in-process SITL vehicle."""

import dataclasses
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

import pytest
from flight_sim import ALT_RELAY, ATT_RELAY, SIDE_RELAY, state_of

from mrft_gcs.errors import IdentificationError
from mrft_gcs.flight.sequence import LoopState, SequenceConfig, TuningSequence
from mrft_gcs.identify.live import bundled_identifier
from mrft_gcs.loops import Loop
from mrft_gcs.sitl import load_airframe, random_airframe
from mrft_gcs.sitl.airframe import GRAVITY_M_S2
from mrft_gcs.sitl.onboard import FlightMode
from mrft_gcs.sitl.vehicle import SimVehicle


def com_bias(af, dx_m: float, dy_m: float) -> tuple[float, float, float]:
    """Normalised roll/pitch torque of a centre of mass ``dx`` forward, ``dy`` right of the
    thrust centre (as :func:`mrft_gcs.sitl.random_airframe` draws it)."""
    mx, my, _ = af.max_moments_n_m
    w = af.mass_kg * GRAVITY_M_S2
    return (w * dy_m / mx, -w * dx_m / my, 0.0)


def fly_first(af, seconds: float, seed: int = 0, hover_factor: float = 1.0,
              identify: bool = False, **cfg):
    """The tune's first ``seconds`` at 250 Hz; returns (sequence, vehicle, record).

    The record holds per tick (t since the take-off command, on the ground, tilt deg,
    measured altitude m). ``identify``: steady roll/pitch cycles go to the bundled
    classifiers, as the tune does.
    """
    v = SimVehicle(af, seed=seed)
    ap = v.autopilot
    ap.set_actuator_controls(0, 0, 0, 0)
    ap.set_mode(FlightMode.OFFBOARD)
    ap.arm(True)
    seq = TuningSequence(SequenceConfig(hover_thrust_guess=hover_factor * af.hover_thrust,
                                        **cfg), ATT_RELAY, ALT_RELAY)
    for _ in range(100):  # 0.4 s on the ground: the noise that sets bands and thresholds
        v.run(0.004)
        seq.observe(state_of(v))
    seq.start(state_of(v))
    t0, rec = v.time_s, []
    while v.time_s < t0 + seconds:
        s = state_of(v)
        sp = seq.step(s)
        ap.set_actuator_controls(sp.roll, sp.pitch, sp.yaw, sp.thrust)
        rec.append((v.time_s - t0, v.physics.on_ground, math.degrees(s.tilt_rad), s.z_up_m))
        for snap in seq.ready():
            if not identify:
                continue
            try:
                seq.apply(snap.loop, bundled_identifier(snap.loop, snap, None))
            except IdentificationError:
                seq.retry(snap.loop)
        if seq.side_waiting:
            seq.start_side({Loop.X: SIDE_RELAY, Loop.Y: SIDE_RELAY})
        v.run(0.004)
    return seq, v, rec


def test_attitude_relays_start_at_lift_off_not_at_the_altitude_threshold():
    # qdrone with its centre of mass 6 mm (3 % of the arm) to the right: a roll torque the
    # ground carries until lift-off
    af = load_airframe("qdrone")
    af = dataclasses.replace(af, torque_bias=com_bias(af, 0.0, 0.006))
    seq, _, rec = fly_first(af, 1.0)
    t_lift = next(t for t, ground, _, _ in rec if not ground)
    roll = seq.loops[Loop.ROLL]
    t_relay = roll.t_relay_start_s - seq.t_start_s
    assert seq.lifted
    # within a few telemetry samples of leaving the ground (the old rule waited for 3 cm
    # of measured altitude: 0.15-0.25 s on the population, tilting 5-10 deg meanwhile)
    assert t_lift < t_relay < t_lift + 0.04, (t_lift, t_relay)
    z_at, tilt_at = next((z, tilt) for t, _, tilt, z in rec if t >= t_relay)
    assert z_at < seq.config.airborne_m and tilt_at < 1.0, (z_at, tilt_at)


def test_no_lift_off_seen_on_the_ground():
    # a hover guess far too low: the climb's thrust never lifts the vehicle, and the
    # sensor noise alone must not start the attitude relays (torque on the ground)
    seq, v, rec = fly_first(load_airframe("qdrone"), 1.0, hover_factor=0.4)
    assert all(ground for _, ground, _, _ in rec)
    assert not seq.lifted
    assert seq.loops[Loop.ROLL].state is LoopState.WAITING
    assert seq.loops[Loop.ROLL].relay is None


@pytest.mark.parametrize("bias", [(0.0386, 0.0), (-0.025, 0.03)])
def test_relay_bias_learnt_from_the_first_period(bias):
    # 0.0386: qdrone's centre of mass 6 mm off, 3 % of its arm (the most the population draws)
    af = dataclasses.replace(load_airframe("qdrone"), torque_bias=(*bias, 0.0))
    seq, _, rec = fly_first(af, 6.0, identify=True)
    for lp, b in zip((Loop.ROLL, Loop.PITCH), bias, strict=True):
        t = seq.loops[lp]
        # the relay's mean torque over a period from turn to turn is minus the bias; what
        # is left would make the relay's two levels differ by under a tenth of h
        assert abs(t.bias + b) < 0.1 * t.h, (lp, t.bias, b, t.h)
        assert t.state is LoopState.TUNED, (lp, seq.events)
        # the PD that holds the axis afterwards trims it by the same torque
        assert t.pd is not None and t.pd.trim == pytest.approx(-b, abs=0.01)
    assert max(tilt for _, _, tilt, _ in rec) < 15.0


@pytest.mark.parametrize("vehicle", ["qdrone", "racer250", "f550"])
def test_unbiased_bundled_vehicle_keeps_its_relay_amplitude(vehicle):
    # no bias, cycles small: the first period takes the relay to h_att_min, as before
    seq, _, _ = fly_first(load_airframe(vehicle), 2.5)
    for lp in (Loop.ROLL, Loop.PITCH):
        t = seq.loops[lp]
        sized = [e for e in seq.events if e.startswith(f"{lp.value}: relay sized")]
        assert t.sized and t.bias == 0.0, seq.events
        assert len(sized) == 1 and sized[0].endswith(
            f"amplitude {seq.config.h_att_start:.3g} -> {seq.config.h_att_min:.3g}"), sized


def test_agile_vehicle_relay_sized_to_its_swing():
    # random vehicle 3: 82 g, thrust/weight 4; at a fixed h of 0.12 (population benchmark,
    # 42 ms of loop delay) its cycles were 0.3-0.6 rad and the take-off passed 35 deg
    af = random_airframe(3)
    seq, _, rec = fly_first(af, 5.0)
    cfg = seq.config
    for lp in (Loop.ROLL, Loop.PITCH):
        t = seq.loops[lp]
        assert t.sized and t.h < 0.7 * t.h_goal, seq.events
        # the swing per unit h measured on the first period, and h chosen so that the
        # cycle stays within att_amp_max_rad (or the floor set by the noise / h_att_floor)
        assert t.amp_per_h * t.h <= 1.5 * cfg.att_amp_max_rad or t.h == cfg.h_att_floor
    assert seq.loops[Loop.ROLL].bias == pytest.approx(-af.torque_bias[0], abs=0.006)
    assert max(tilt for _, _, tilt, _ in rec) < 30.0


def test_relay_that_cannot_turn_the_axis_is_doubled():
    # a torque bias over the starting amplitude: the first relay cannot hold the axis
    af = load_airframe("qdrone")
    af = dataclasses.replace(af, torque_bias=(0.07, 0.0, 0.0))
    seq, _, rec = fly_first(af, 4.0)
    roll = seq.loops[Loop.ROLL]
    assert any("could not turn the axis back" in e for e in seq.events), seq.events
    assert roll.sized and roll.bias == pytest.approx(-0.07, abs=0.02), seq.events
    assert max(tilt for _, _, tilt, _ in rec) < 30.0


def test_relay_centred_on_the_torque_bias_before_its_first_period():
    """A CoM offset weakens every other push of a relay biased at zero, and the swing that
    push must brake grows (an 82 g vehicle: 30 deg before its first period was measured).
    The relay is centred on the torque bias fitted to its first swings, at a switch, before
    the first period sizes it: that period swings less than the uncentred one."""
    af = load_airframe("qdrone")
    af = dataclasses.replace(af, torque_bias=com_bias(af, 0.0, 0.006))
    swing = {}
    for r2 in (0.9, 0.0):  # 0: the centring off
        seq, _, _ = fly_first(af, 1.5, att_centre_r2=r2)
        t = seq.loops[Loop.ROLL]
        first = next(e for e in seq.events if e.startswith("roll: relay sized on its first"))
        swing[r2] = float(first.split("(")[1].split(" rad")[0])
        if r2:
            assert t.centred and "roll: relay centred" in seq.events[0]
            assert t.bias == pytest.approx(-af.torque_bias[0], rel=0.15)
    assert swing[0.9] < 0.8 * swing[0.0], swing


def test_torque_bias_fit_with_motor_lag_and_noise():
    """The fit recovers gain and bias behind a delay and a motor lag, from noisy rates; a
    record on one relay level alone pins nothing down (K and b cannot be told apart)."""
    import numpy as np

    from mrft_gcs.flight.phases.attitude import torque_bias_fit

    rng = np.random.default_rng(1)
    t = np.arange(-0.2, 0.5, 0.004)
    u = np.where((t < 0.0) | (t >= 0.25), -0.06, 0.06)
    ud = np.interp(t - 0.04, t, u)
    m = np.empty_like(ud)
    m[0] = ud[0]
    for i in range(1, t.size):  # 50 ms motors
        m[i] = m[i - 1] + (1 - math.exp(-0.004 / 0.05)) * (ud[i - 1] - m[i - 1])
    rate = np.concatenate([[0.0], np.cumsum(300.0 * (m[:-1] - 0.015) * 0.004)])
    rate += rng.normal(0, 0.05, t.size)
    f = torque_bias_fit(t, u, t[50:], rate[50:])
    assert f is not None and f.bias == pytest.approx(-0.015, abs=0.002)
    assert f.gain == pytest.approx(300, rel=0.1) and f.bias_se < 0.002
    one = torque_bias_fit(t, u, t[52:100], rate[52:100])
    assert one is None or one.bias_se > 0.1 * 0.06
