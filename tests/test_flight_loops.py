"""The ``loops`` selection of a tune: names checked against the path, before connecting."""

import pytest

from mrft_gcs.cli import main
from mrft_gcs.errors import UsageError
from mrft_gcs.flight import tune
from mrft_gcs.flight.api import requested_loops
from mrft_gcs.loops import Loop
from mrft_gcs.profiles import Actuation


def test_default_is_every_loop_the_path_can_tune():
    assert requested_loops(None, Actuation.TORQUE) == frozenset(Loop)
    assert requested_loops(None, Actuation.ATTITUDE) == {Loop.ALTITUDE, Loop.X, Loop.Y}


def test_names_enums_and_comma_strings():
    assert requested_loops(["Roll", " pitch", Loop.X], Actuation.TORQUE) == {
        Loop.ROLL, Loop.PITCH, Loop.X}
    assert requested_loops("altitude,y", Actuation.ATTITUDE) == {Loop.ALTITUDE, Loop.Y}


@pytest.mark.parametrize("loops, actuation, match", [
    (["altitude", "yaw"], Actuation.TORQUE, "unknown loop 'yaw'"),
    ([], Actuation.TORQUE, "no loop requested"),
    (["roll", "x"], Actuation.ATTITUDE, "roll cannot be tuned on the attitude path"),
])
def test_bad_selections_are_one_line_usage_errors(loops, actuation, match):
    with pytest.raises(UsageError, match=match) as err:
        requested_loops(loops, actuation)
    assert "\n" not in str(err.value) and err.value.exit_code == 2


def test_tune_refuses_a_bad_selection_before_connecting():
    # nothing listens there: a LinkError (exit 3) would mean it tried to connect first
    with pytest.raises(UsageError, match="unknown loop"):
        tune("udp:127.0.0.1:9", "sitl", loops=["z"], heartbeat_timeout_s=0.5)


def test_cli_loops_option(capsys):
    code = main(["tune", "-c", "udp:127.0.0.1:9", "--profile", "px4", "--yes",
                 "--loops", "altitude,pitch", "--timeout", "0.5"])
    assert code == 2  # px4 is on the attitude path: pitch is the autopilot's
    assert "pitch cannot be tuned on the attitude path" in capsys.readouterr().err
