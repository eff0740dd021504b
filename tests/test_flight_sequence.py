"""The tuning sequence on the in-process SITL (no sockets), with a truth identifier.

The truth identifier is a test double standing in for the bundled classifiers (it returns
the airframe's true model and its optimal PD), so these tests cover everything around
identification: take-off, simultaneous relays, bounding controller, cycle detection,
hand-over to PDs, side tests and hover.
"""

import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

import numpy as np
import pytest
from flight_sim import ALT_RELAY, ATT_RELAY, fly, state_of

from mrft_gcs.flight.controllers import FlightState
from mrft_gcs.flight.sequence import LoopState, Phase, SequenceConfig, TuningSequence
from mrft_gcs.loops import Loop
from mrft_gcs.profiles import Actuation
from mrft_gcs.sitl import load_airframe
from mrft_gcs.telemetry import ActuatorTarget, AttitudeTarget


@pytest.mark.parametrize("vehicle", ["qdrone", "f550"])
def test_full_sequence_reaches_hover(vehicle):
    af = load_airframe(vehicle)
    seq = TuningSequence(SequenceConfig(hover_thrust_guess=af.hover_thrust), ATT_RELAY, ALT_RELAY)
    v, max_tilt = fly(seq, vehicle, seed=2, max_s=40.0)
    assert seq.phase is Phase.HOVER
    assert all(t.state is LoopState.TUNED for t in seq.loops.values())
    assert seq.duration_s < 20.0
    assert max_tilt < 35.0
    s = state_of(v)
    # about where the altitude relay ran: the set point, or where the climb was braked
    z_relay = seq.takeoff.z_relay_m
    assert math.hypot(s.x_m, s.y_m) < 0.2 and abs(s.z_up_m - z_relay) < 0.1 and z_relay > 0.7
    if seq.takeoff.braked:  # only once roll and pitch were tuned (brake_after_attitude)
        tuned = max(seq.loops[lp].t_tuned_s for lp in (Loop.ROLL, Loop.PITCH))
        assert tuned <= seq.takeoff.t_switch
    alt = seq.loops[Loop.ALTITUDE]
    assert alt.pd.trim == pytest.approx(af.hover_thrust, abs=0.03)  # mean relay = hover
    for lp, t in seq.loops.items():
        assert t.snapshot is not None and t.snapshot.t_s.size > 10, lp


def _state(x=0.0, y=0.0, z=0.0, t=0.0):
    return FlightState(t, 0, 0, 0, 0, 0, 0, t, x, y, z, 0, 0, 0)


def test_bounding_relay_sign_convention():
    seq = TuningSequence(SequenceConfig(), ATT_RELAY, ALT_RELAY)
    seq.start(_state())
    seq.step(_state(x=1.5, y=-1.5, t=0.004))
    roll_ref, pitch_ref = seq.tilt_cmd
    # north of the take-off point: pitch up (+theta moves -x); west: roll right (+phi moves +y)
    assert pitch_ref == pytest.approx(0.05) and roll_ref == pytest.approx(0.05)
    seq.step(_state(x=-2.5, y=2.5, t=0.008))
    assert seq.tilt_cmd == pytest.approx((-0.1, -0.1))


def test_ground_idle_and_takeoff_command():
    seq = TuningSequence(SequenceConfig(hover_thrust_guess=0.45), ATT_RELAY, ALT_RELAY)
    sp = seq.step(_state())
    assert isinstance(sp, ActuatorTarget) and sp.thrust == 0.0  # preflight: nothing
    seq.start(_state())
    sp = seq.step(_state(t=0.004))
    assert seq.phase is Phase.TAKEOFF and sp.thrust > 0.4 and sp.roll == 0.0  # PI, on ground


def test_attitude_path_leaves_attitude_loops_alone():
    seq = TuningSequence(SequenceConfig(actuation=Actuation.ATTITUDE), ATT_RELAY, ALT_RELAY)
    seq.start(_state())
    sp = seq.step(_state(t=0.004, y=1.5))
    assert isinstance(sp, AttitudeTarget)
    for lp in (Loop.ROLL, Loop.PITCH):
        assert seq.loops[lp].state is LoopState.LEFT_ALONE
        assert "autopilot keeps its own attitude loop" in seq.loops[lp].note
    assert seq.inner_done and not seq.side_waiting  # x and y wait for altitude too
    seq.loops[Loop.ALTITUDE].state = LoopState.TUNED
    assert seq.side_waiting and seq.side_ready() == [Loop.X, Loop.Y]


def _yawed(x=0.0, y=0.0, yaw=0.0, t=0.0, vx=0.0):
    return FlightState(t, 0, 0, yaw, 0, 0, 0, t, x, y, 0.0, vx, 0, 0)


def test_side_axes_follow_the_take_off_heading():
    # taking off facing east: x is forward (east), y is right (south)
    seq = TuningSequence(SequenceConfig(), ATT_RELAY, ALT_RELAY)
    seq.start(_yawed(yaw=math.pi / 2))
    seq.step(_yawed(y=1.5, yaw=math.pi / 2, t=0.004))  # 1.5 m east = 1.5 m forward
    roll_ref, pitch_ref = seq.tilt_cmd
    assert pitch_ref == pytest.approx(0.05) and roll_ref == pytest.approx(0.0, abs=1e-12)


def test_tilt_command_is_rotated_by_the_heading_drift():
    # took off facing north, has since yawed 90 deg right: a command back south is a roll right
    seq = TuningSequence(SequenceConfig(), ATT_RELAY, ALT_RELAY)
    seq.start(_yawed())
    seq.step(_yawed(x=1.5, yaw=math.pi / 2, t=0.004))
    roll_ref, pitch_ref = seq.tilt_cmd
    assert roll_ref == pytest.approx(0.05) and pitch_ref == pytest.approx(0.0, abs=1e-12)


def test_side_axis_is_brought_to_rest_once_its_attitude_loop_is_tuned():
    from mrft_gcs.flight.controllers import PDLoop

    seq = TuningSequence(SequenceConfig(), ATT_RELAY, ALT_RELAY)
    seq.start(_yawed())
    seq.step(_yawed(x=0.5, vx=0.5, t=0.004))
    assert seq.tilt_cmd[1] == 0.0  # bounding relay: idle within 1 m
    seq.loops[Loop.PITCH].pd = PDLoop(1.0, 0.1)  # pitch tuned (altitude still testing)
    seq.step(_yawed(x=0.5, vx=0.2, t=0.008))
    kp, kd = seq.config.settle_pd
    assert seq.tilt_cmd[1] == pytest.approx(kd * 0.2, rel=0.05)  # braking: pitch up
    assert seq.loops[Loop.X].state is LoopState.WAITING  # its relay waits for altitude
    seq.step(_yawed(x=0.5, vx=1.5, t=0.012))  # fast: a gentle tilt, not a 0.6 rad step
    assert seq.tilt_cmd[1] == pytest.approx(seq.config.settle_max_tilt_rad)


def test_altitude_and_side_identify_three_cycles_attitude_four():
    af = load_airframe("qdrone")
    seq = TuningSequence(SequenceConfig(hover_thrust_guess=af.hover_thrust), ATT_RELAY, ALT_RELAY)
    fly(seq, "qdrone", seed=1, max_s=30.0, hover_s=0.0)
    assert seq.phase is Phase.HOVER
    for lp, n in ((Loop.ROLL, 4), (Loop.PITCH, 4), (Loop.ALTITUDE, 3), (Loop.X, 3), (Loop.Y, 3)):
        u = seq.loops[lp].snapshot.u
        high = u > 0.5 * (u.max() + u.min())
        assert np.count_nonzero(high[1:] & ~high[:-1]) == n, lp  # rising switches = cycles


def test_full_sequence_at_any_heading(monkeypatch):
    import flight_sim

    class Yawed(flight_sim.SimVehicle):
        def __init__(self, *a, **kw):
            super().__init__(*a, **kw)
            self.physics.reset(yaw=2.0)

    monkeypatch.setattr(flight_sim, "SimVehicle", Yawed)
    af = load_airframe("qdrone")
    seq = TuningSequence(SequenceConfig(hover_thrust_guess=af.hover_thrust), ATT_RELAY, ALT_RELAY)
    v, max_tilt = fly(seq, "qdrone", seed=2, max_s=40.0)
    assert seq.yaw_ref == pytest.approx(2.0, abs=0.01)
    assert seq.phase is Phase.HOVER and seq.duration_s < 20.0 and max_tilt < 35.0
    s = state_of(v)
    z_relay = seq.takeoff.z_relay_m
    assert math.hypot(s.x_m, s.y_m) < 0.3 and abs(s.z_up_m - z_relay) < 0.1 and z_relay > 0.7


def test_side_axis_not_requested_is_held_and_never_relay_tested(monkeypatch):
    import flight_sim

    class Windy(flight_sim.SimVehicle):  # a steady push along x: an axis nobody holds drifts
        def __init__(self, *a, **kw):
            super().__init__(*a, wind_m_s=(0.2, 0.0, 0.0), **kw)

    monkeypatch.setattr(flight_sim, "SimVehicle", Windy)
    af = load_airframe("qdrone")
    seq = TuningSequence(SequenceConfig(hover_thrust_guess=af.hover_thrust), ATT_RELAY, ALT_RELAY)
    seq.leave_alone(Loop.X, "not requested")
    v, max_tilt = fly(seq, "qdrone", seed=1, max_s=30.0, hover_s=3.0)
    assert seq.phase is Phase.HOVER and max_tilt < 35.0
    x, y = seq.loops[Loop.X], seq.loops[Loop.Y]
    assert x.state is LoopState.LEFT_ALONE and x.snapshot is None and x.relay is None
    assert x.note == "not requested"
    assert y.state is LoopState.TUNED
    s = state_of(v)
    # held by the soft settle PD about where it stood when pitch was tuned, not drifting off
    assert abs(s.x_m - x.center) < 0.3 and abs(s.vx_m_s) < 0.05


def test_attitude_path_tunes_x_and_y_behind_the_measured_attitude_loop():
    """Attitude path, in-process: altitude, x and y tuned with the bundled identification;
    x and y behind the autopilot's closed attitude loop measured from their own relays."""
    from mrft_gcs.flight.scoring import onboard_attitude_response, score_gains
    from mrft_gcs.identify import Method, relay_settings
    from mrft_gcs.identify.live import bundled_identifier
    from mrft_gcs.loops import LoopKind
    from mrft_gcs.sitl.onboard import PARAM_SPECS

    af = load_airframe("qdrone")
    models, px4 = af.linear_models(), {k: s.default for k, s in PARAM_SPECS.items()}
    inners = {}

    def ident(loop, snap, inner=None):
        if inner is not None:
            inners[loop] = inner
        return bundled_identifier(loop, snap, inner)

    seq = TuningSequence(SequenceConfig(actuation=Actuation.ATTITUDE,
                                        hover_thrust_guess=af.hover_thrust),
                         relay_settings(LoopKind.ATTITUDE), relay_settings(LoopKind.ALTITUDE))
    v, max_tilt = fly(seq, "qdrone", seed=0, max_s=40.0, identifier=ident, hover_s=1.0)
    assert seq.phase is Phase.HOVER and max_tilt < 35.0 and seq.duration_s < 20.0
    assert [seq.loops[lp].state for lp in Loop] == [
        LoopState.LEFT_ALONE, LoopState.LEFT_ALONE, LoopState.TUNED, LoopState.TUNED,
        LoopState.TUNED]
    for lp, axis in ((Loop.X, "pitch"), (Loop.Y, "roll")):
        inner = inners[lp]
        assert inner.diagnostics.method is Method.CLOSED_LOOP
        measured = inner.diagnostics.measured
        w, T = measured.w[:3], measured.T[:3]  # measured: harmonics 1, 3, 5
        true = onboard_attitude_response(models[axis], px4, axis.upper(), w)
        assert np.all(np.abs(np.log(T / true)) < 0.06), (lp, np.log(T / true))
    gains = {lp: seq.loops[lp].identification.gains for lp in (Loop.ALTITUDE, Loop.X, Loop.Y)}
    for lp, sc in score_gains(models, gains, attitude_params=px4).items():
        assert sc.stable and abs(sc.J_pct) < 10.0, (lp, sc)
    s = state_of(v)
    assert abs(s.z_up_m - seq.takeoff.z_relay_m) < 0.1 and seq.takeoff.z_relay_m > 0.7


def test_roll_relay_survives_ground_station_stalls():
    """50-100 ms stalls of the GCS (the vehicle holds the last relay level) while roll's
    relay runs on for 12 s beside the altitude and x tests: a relay restarted after such a
    swing had grown it test by test past 35 deg (35.5 and 35.3 deg in the seeds where a
    stall pushed it out); the damping PD built from the relay's own cycle catches it and
    the relay resumes. The seeds are ones whose stalls do push roll out (of seeds 0-5,
    2, 3 and 5 since the climb learns the hover thrust)."""
    from flight_sim import truth_identifier

    from mrft_gcs.errors import IdentificationError

    truth = truth_identifier("racer250")

    def late_roll(loop, snap, inner=None):
        if loop is Loop.ROLL and snap.t_s[-1] < 12.0:
            raise IdentificationError("held back by the test")
        return truth(loop, snap, inner)

    af = load_airframe("racer250")
    caught = 0
    for seed in (2, 3):
        seq = TuningSequence(SequenceConfig(hover_thrust_guess=af.hover_thrust), ATT_RELAY,
                             ALT_RELAY)
        _, max_tilt = fly(seq, "racer250", seed=seed, max_s=30.0, identifier=late_roll,
                          stalls=(50.0, 1.0), hover_s=1.0)
        assert max_tilt < 35.0, (seed, seq.events)
        assert seq.phase is Phase.HOVER, (seed, seq.events)
        caught += sum("caught the run-away" in e for e in seq.events)
    assert caught >= 2  # the stalls did push roll out: the catch is what held it


def test_restarted_attitude_relay_keeps_its_runaway_limit():
    """After a catch the detector starts over (no amplitude yet): the run-away limit is
    still sized by the cycle seen before, so the relay's own start-up swing (racer250
    pitch, 0.10-0.20 rad against a 0.06 rad cycle) is not taken for another run-away;
    a swing past three cycle amplitudes still is."""
    from mrft_gcs.relay import MRFT

    seq = TuningSequence(SequenceConfig(hover_thrust_guess=0.5), ATT_RELAY, ALT_RELAY)
    t = seq.loops[Loop.PITCH]
    t.h, t.cycle = 0.12, (0.25, 0.06)
    assert not math.isfinite(t.status.amplitude)  # as right after a reset
    relay = MRFT(-0.5, t.h)
    relay.step(0.01)  # a positive output: pushes a negative error further out
    seq.shared.watch(t, relay, -0.15, float(relay.state[0]))
    assert t.catch is None and not seq.events
    seq.shared.watch(t, relay, -0.2, float(relay.state[0]))
    assert t.catch is not None and "caught the run-away" in seq.events[-1]


def test_attitude_relay_start_up_swing_and_first_run_away():
    """Before any cycle is known a start-up swing (racer250: 0.10-0.20 rad) is no run-away;
    once one complete cycle was seen, a run-away is caught by a damping PD sized from it
    rather than restarted as a sign relay (in-process with stalls that restart swung
    racer250 further out each time: 0.22 to 0.48 rad, tilt 42-90 deg, never tuned)."""
    from mrft_gcs.identify import CycleStatus
    from mrft_gcs.relay import MRFT

    seq = TuningSequence(SequenceConfig(hover_thrust_guess=0.5), ATT_RELAY, ALT_RELAY)
    t = seq.loops[Loop.ROLL]
    t.h = 0.12
    relay = MRFT(-0.5, t.h)
    relay.step(0.01)  # a positive output: pushes a negative error further out
    seq.shared.watch(t, relay, -0.2, float(relay.state[0]))
    assert t.catch is None and not seq.events  # start-up swing, nothing known yet
    t.status = CycleStatus(1, False, 0.21, 0.05, math.inf)  # one complete cycle seen
    seq.shared.watch(t, relay, -0.2, float(relay.state[0]))
    assert t.catch is not None and "caught the run-away" in seq.events[-1]
    assert t.cycle == (0.21, 0.05)


def test_noisy_cycle_at_the_largest_relay_amplitude_is_identified_not_waited_on():
    """A steady cycle too small for the noise raises the relay amplitude; once it is at its
    largest, the cycle goes to identification (with a note) instead of waiting forever."""
    seq = TuningSequence(SequenceConfig(hover_thrust_guess=0.5, h_max=(0.12, 0.25, 0.2)),
                         ATT_RELAY, ALT_RELAY)
    t = seq.loops[Loop.ROLL]
    t.state, t.h, t.band = LoopState.RELAY, 0.12, 0.004  # sigma 1 mrad
    from mrft_gcs.relay import MRFT
    t.relay = MRFT(t.beta, t.h, band=t.band)
    for k in range(400):  # 0.2 s cycles of 0.02 rad: noise 5 % of the amplitude
        ts = 0.004 * k
        t.status = t.detector.update(ts, t.h * np.sign(math.sin(2 * math.pi * ts / 0.2) + 1e-9),
                                     0.02 * math.sin(2 * math.pi * ts / 0.2 - 2.0))
    assert t.status.steady
    assert seq.ready() and t.state is LoopState.IDENTIFYING
    assert "identified as it is" in seq.events[-1]
    t2 = seq.loops[Loop.PITCH]  # below its largest amplitude: raised and started over
    t2.state, t2.h, t2.band, t2.relay = LoopState.RELAY, 0.06, 0.004, MRFT(t2.beta, 0.06)
    t2.detector, t2.status = t.detector, t.status
    assert not seq.ready() and t2.h > 0.06 and t2.state is LoopState.RELAY


@pytest.mark.parametrize("guess_factor", [0.85, 1.15])
def test_wrong_hover_guess_still_tunes_altitude(guess_factor):
    """The autopilot's hover estimate (MPC_THR_HOVER, a fresh airframe's default) can be
    15 % off: the climb learns the thrust that holds the vehicle before the altitude
    relay starts on it. Before, the relay biased at the guess sank or rose into a
    lopsided cycle, ran away again and again, and altitude was never identified."""
    af = load_airframe("qdrone")
    seq = TuningSequence(SequenceConfig(hover_thrust_guess=guess_factor * af.hover_thrust),
                         ATT_RELAY, ALT_RELAY)
    _, max_tilt = fly(seq, "qdrone", seed=1, max_s=30.0, hover_s=0.5)
    assert seq.phase is Phase.HOVER, seq.events
    alt = seq.loops[Loop.ALTITUDE]
    assert alt.state is LoopState.TUNED
    assert alt.bias == pytest.approx(af.hover_thrust, rel=0.05)  # learnt, not the guess
    assert seq.duration_s < 20.0 and max_tilt < 35.0


def test_lopsided_altitude_cycles_are_seen_after_two_cycles():
    """Two altitude cycles that stay under (or over) the set point are a lopsided mode the
    identification would refuse: the sequence sees it at once (and starts over from the
    set point) instead of waiting for three steady cycles of it first."""
    seq = TuningSequence(SequenceConfig(hover_thrust_guess=0.3), ATT_RELAY, ALT_RELAY)
    t = seq.loops[Loop.ALTITUDE]
    t.state = LoopState.RELAY
    seq.takeoff.z_relay_m = 1.0

    def feed(center):
        t.detector.reset()
        for k in range(int(3.2 / 0.004)):
            ts = k * 0.004
            ph = 2 * np.pi * ts / 0.9
            u = 0.3 + 0.1 * np.sign(np.sin(ph) + 1e-12)
            t.status = t.detector.update(ts, u, center - 0.06 * np.cos(ph))
        return seq.altitude.lopsided(t)

    assert feed(0.8) and feed(1.2)
    assert not feed(1.0)


def test_attitude_swing_still_growing_against_the_relay_is_caught():
    """A relay locked by GCS stalls into a slow, large mode swings out on its momentum
    while it already pushes back (racer250 in-process, stalls x 6: pitch to -48 deg in
    0.6 s cycles); past the run-away limit and still moving out, it is caught, so that the
    relay does not drive the return at full amplitude into as large a swing the other
    way. A swing already on its way back is left to the relay, and so is the relay's own
    start-up swing before the detector has measured a cycle (live racer250: caught ten
    times in a row at 0.18 rad without that wait)."""
    from mrft_gcs.identify import CycleStatus
    from mrft_gcs.relay import MRFT

    seq = TuningSequence(SequenceConfig(hover_thrust_guess=0.5), ATT_RELAY, ALT_RELAY)
    t = seq.loops[Loop.PITCH]
    t.h, t.cycle = 0.12, (0.25, 0.06)
    relay = MRFT(-0.5, t.h)
    relay.step(-0.01)
    relay.step(0.3)  # a positive output: pushes a positive error back
    assert float(relay.state[0]) > 0
    seq.shared.watch(t, relay, 0.3, float(relay.state[0]), e_rate=2.0)  # just (re)started
    assert t.catch is None and not seq.events
    t.status = CycleStatus(2, False, 0.25, 0.06, math.inf)  # cycles measured since
    seq.shared.watch(t, relay, 0.3, float(relay.state[0]), e_rate=-2.0)  # coming back
    assert t.catch is None and not seq.events
    seq.shared.watch(t, relay, 0.3, float(relay.state[0]), e_rate=2.0)  # still swinging out
    assert t.catch is not None and "caught the run-away" in seq.events[-1]


def test_a_swing_is_caught_where_it_will_stop_and_held_with_more_than_h():
    """A GCS stall of 60 ms during racer250's first relay cycle sent roll and pitch to
    -3.5 rad/s at 0.11 rad, inside the run-away limit; caught only past it and held with
    h, what the relay itself pushes back with, they stopped at 25.5 deg. The catch now
    looks at where the swing will stop (the plant's acceleration per h from the cycle)
    and its damping PD may use ``catch_torque_factor`` x h."""
    from mrft_gcs.identify import CycleStatus
    from mrft_gcs.relay import MRFT

    seq = TuningSequence(SequenceConfig(hover_thrust_guess=0.5), ATT_RELAY, ALT_RELAY)
    t = seq.loops[Loop.PITCH]
    t.h, t.cycle = 0.12, (0.25, 0.06)  # run-away limit 3 x 0.06 = 0.18 rad
    t.status = CycleStatus(2, False, 0.25, 0.06, math.inf)
    relay = MRFT(-0.5, t.h)
    relay.step(-0.01)
    relay.step(0.12)
    seq.shared.watch(t, relay, 0.12, float(relay.state[0]), e_rate=0.5)  # stops at 0.124 rad
    assert t.catch is None
    seq.shared.watch(t, relay, 0.12, float(relay.state[0]), e_rate=3.0)  # would stop at 0.27 rad
    assert t.catch is not None and "caught the run-away" in seq.events[-1]
    t.state, t.relay = LoopState.RELAY, relay
    u = seq.attitude.step(Loop.PITCH, 0.0, -0.2, -3.0, 1.0, True, True)
    assert t.h < u <= seq.config.catch_torque_factor * t.h


def test_a_catch_sized_on_too_small_a_cycle_is_softened_until_it_hands_back():
    """A first period that understates the plant's gain sizes a catch PD several times too
    stiff for the loop's delay (ArduCopter SITL, rate path: a 0.0055 rad first period where
    every other run measured 0.014-0.016 rad): it chatters at its limits and never hands
    the axis back to the relay. Halved each time it chatters, it settles and hands back;
    left as sized, it is still chattering 5 s later."""
    from collections import deque

    from mrft_gcs.flight.controllers import catch_pd
    from mrft_gcs.relay import MRFT

    def hand_back_s(stiffness: float, chatter_flips: int) -> float | None:
        cfg = SequenceConfig(hover_thrust_guess=0.5, catch_chatter_flips=chatter_flips)
        seq = TuningSequence(cfg, ATT_RELAY, ALT_RELAY)
        t = seq.loops[Loop.PITCH]
        t.h, t.cycle = 0.12, (0.25, 0.03)
        t.state, t.relay = LoopState.RELAY, MRFT(-0.5, t.h)
        kc, kd = catch_pd(t.h, *t.cycle)
        t.catch, t.t_catch_s = (stiffness * kc, stiffness * kd), 0.0
        dt, y, rate = 0.004, 0.05, 0.0
        pipe = deque([0.0] * 10)  # 40 ms from command to torque
        for i in range(int(5.0 / dt)):  # a double integrator, 60 rad/s^2 per unit torque
            pipe.append(seq.attitude.step(Loop.PITCH, 0.0, y, rate, i * dt, True, True))
            rate += 60.0 * pipe.popleft() * dt
            y += rate * dt
            if t.catch is None:
                return i * dt
        return None

    assert hand_back_s(1.0, 4) is not None  # as sized on the true cycle: hands back at once
    assert hand_back_s(5.0, 10**6) is None  # too stiff and left so: chatters throughout
    softened = hand_back_s(5.0, SequenceConfig().catch_chatter_flips)
    assert softened is not None and softened < 2.0


def test_cycles_refused_as_too_small_are_retried_on_the_next_cycle_then_raised():
    """A side relay whose cycles identification refused as too small for the noise runs on
    and is tried again on its next cycle (before, the detection started over: three or more
    periods, a second each, lost per refusal); ``refused_sets_before_raise`` whole new sets
    refused raise h (one: two waited six 1 s side cycles more on cycles that mostly failed)."""
    from mrft_gcs.relay import MRFT

    seq = TuningSequence(SequenceConfig(hover_thrust_guess=0.5), ATT_RELAY, ALT_RELAY)
    t = seq.loops[Loop.Y]
    t.state, t.h, t.band = LoopState.RELAY, 0.08, 1e-4
    t.relay = MRFT(t.beta, t.h, band=t.band)
    k = 0

    def run(periods):  # 1 s cycles of 2 cm
        nonlocal k
        for _ in range(int(periods * 250)):
            ts = 0.004 * k
            t.status = t.detector.update(ts, t.h * np.sign(math.sin(2 * math.pi * ts) + 1e-9),
                                         0.02 * math.sin(2 * math.pi * ts - 2.0))
            k += 1

    run(5.2)
    assert [s.loop for s in seq.ready()] == [Loop.Y]
    seen = t.status.cycles
    seq.retry(Loop.Y, larger=True)
    assert t.state is LoopState.RELAY and t.status.cycles == seen  # not started over
    assert not seq.ready()  # the same cycles are not handed over again
    run(1.0)
    assert [s.loop for s in seq.ready()] == [Loop.Y]  # one period later
    n = seq.config.cycle_rules(Loop.Y).identify_cycles
    assert seq.config.refused_sets_before_raise == 1
    for _ in range(n - 1):
        seq.retry(Loop.Y, larger=True)
        run(1.0)
        assert seq.ready() and t.h == 0.08
    seq.retry(Loop.Y, larger=True)
    assert t.h > 0.08 and t.status.cycles == 0 and "too small" in seq.events[-1]


def test_altitude_relay_raise_keeps_every_motor_inside_its_range():
    """A heavy vehicle hovering at 0.8 thrust: the altitude relay may not be raised past the
    headroom left above hover, less the share of each motor the roll and pitch relays
    running beside it take (half of each torque); clipped, its cycle turns lopsided."""
    from mrft_gcs.relay import MRFT

    seq = TuningSequence(SequenceConfig(hover_thrust_guess=0.8), ATT_RELAY, ALT_RELAY)
    sh = seq.shared
    alt = seq.loops[Loop.ALTITUDE]
    alt.bias = 0.8
    assert sh.h_max(Loop.ALTITUDE) == pytest.approx(0.2)  # 1 - 0.8 (was 0.25)
    for lp in (Loop.ROLL, Loop.PITCH):
        t = seq.loops[lp]
        t.state, t.h, t.bias = LoopState.RELAY, 0.1, -0.03
        t.relay = MRFT(t.beta, t.h, bias=t.bias)
    assert sh.h_max(Loop.ALTITUDE) == pytest.approx(0.2 - 0.13)
    alt.state, alt.h = LoopState.RELAY, 0.05
    sh.takeoff.relay = MRFT(alt.beta, alt.h, bias=0.8)
    assert sh.raise_h(alt, 2.0) and alt.h == pytest.approx(0.07)
    assert not sh.raise_h(alt, 2.0)  # at its largest


def test_driver_retries_cycles_too_small_on_the_next_cycle():
    """The driver hands a CyclesTooSmall refusal to the sequence as one to retry on the next
    cycle (the detection goes on); any other refusal starts the detection over."""
    from mrft_gcs.errors import CyclesTooSmall, IdentificationError
    from mrft_gcs.flight.driver import SequenceDriver
    from mrft_gcs.relay import MRFT

    for err, kept in ((CyclesTooSmall("too noisy"), True),
                      (IdentificationError("not steady"), False)):
        seq = TuningSequence(SequenceConfig(hover_thrust_guess=0.5), ATT_RELAY, ALT_RELAY)
        t = seq.loops[Loop.Y]
        t.state, t.h, t.band = LoopState.RELAY, 0.08, 1e-4
        t.relay = MRFT(t.beta, t.h, band=t.band)
        for k in range(1300):  # 1 s cycles of 2 cm
            ts = 0.004 * k
            t.status = t.detector.update(ts, t.h * np.sign(math.sin(2 * math.pi * ts) + 1e-9),
                                         0.02 * math.sin(2 * math.pi * ts - 2.0))

        def refuse(loop, snap, inner, err=err):
            raise err

        drv = SequenceDriver(seq, refuse)
        seen = t.status.cycles
        drv.supervise()
        assert t.state is LoopState.RELAY and drv.retries[-1][0] is Loop.Y
        assert t.status.cycles == (seen if kept else 0)


def _side_first_rise(start_high: bool) -> tuple[float, float]:
    """x relay on a point mass behind a 0.1 s attitude lag, started as the axis drifts on
    at 2 cm/s (under the settle speed): (s from the relay's start to the first rise the
    cycle detector counts, the period)."""
    from mrft_gcs.flight.controllers import PDLoop
    from mrft_gcs.identify import RelaySettings

    seq = TuningSequence(SequenceConfig(side_start_high=start_high), ATT_RELAY, ALT_RELAY)
    seq.start(_yawed())
    for lp in (Loop.ROLL, Loop.PITCH, Loop.ALTITUDE):
        t = seq.loops[lp]
        t.state, t.pd = LoopState.TUNED, PDLoop(1.0, 0.1, 0.5, 0.0, 1.0)
    seq.leave_alone(Loop.Y, "not requested")
    seq.start_side({Loop.X: RelaySettings(-0.3, 0.08)})
    x, vx, pitch, k = 0.0, 0.02, 0.0, 0
    tx = seq.loops[Loop.X]
    while tx.t_relay_start_s != tx.t_relay_start_s or tx.settling:  # NaN until started
        k += 1
        seq.step(FlightState(0.004 * k, 0, pitch, 0, 0, 0, 0, 0.004 * k, x, 0, 1.0, vx, 0, 0))
    t0 = 0.004 * k
    while len(tx.watch.detector.rise_t) < 3:
        k += 1
        seq.step(FlightState(0.004 * k, 0, pitch, 0, 0, 0, 0, 0.004 * k, x, 0, 1.0, vx, 0, 0))
        pitch += (seq.tilt_cmd[1] - pitch) * 0.004 / 0.1
        vx += -9.80665 * pitch * 0.004
        x += vx * 0.004
        assert 0.004 * k - t0 < 20.0
    rises = list(tx.watch.detector.rise_t)
    return rises[0] - t0, rises[1] - rises[0]


def test_side_relay_starts_high_so_its_first_cycle_is_counted_half_a_period_sooner():
    """The cycle detector learns a relay's levels from the data, so a rise before it has
    seen the low level is not counted: a side relay that started low (its first error just
    under zero, the axis drifting on) had its first cycle counted from a whole period after
    its start. Started high, it switches down at once and the rise half a period later
    counts (0.5-1 s of a side axis' 1-2 s cycles)."""
    high, period = _side_first_rise(True)
    low, _ = _side_first_rise(False)
    assert high < 0.75 * period, (high, period)
    assert high < low - 0.4 * period, (high, low, period)
