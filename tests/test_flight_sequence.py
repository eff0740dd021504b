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
    assert math.hypot(s.x_m, s.y_m) < 0.2 and abs(s.z_up_m - 1.0) < 0.1
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
