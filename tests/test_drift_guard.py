"""The drift guard: a relay test that carries the vehicle away from the take-off point is
stopped with an explained refusal well before the distance limit's abort."""

from __future__ import annotations

import functools
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import tune_population as tp  # noqa: E402

from mrft_gcs.errors import IdentificationError  # noqa: E402
from mrft_gcs.flight import safety  # noqa: E402
from mrft_gcs.flight.controllers import FlightState  # noqa: E402
from mrft_gcs.flight.safety import DriftTooLarge, SafetyMonitor  # noqa: E402
from mrft_gcs.flight.sequence import SequenceConfig  # noqa: E402
from mrft_gcs.profiles import SafetyLimits  # noqa: E402
from mrft_gcs.sitl import domain_check, random_airframe  # noqa: E402


def _at(x: float, y: float, vx: float = 0.0, vy: float = 0.0) -> FlightState:
    return FlightState(1.0, 0, 0, 0, 0, 0, 0, 1.0, x, y, 1.0, vx, vy, 0)


def test_the_guard_stops_a_drift_heading_out_and_lets_one_coming_back_run():
    mon = SafetyMonitor(SafetyLimits(max_distance_m=5.0), (1.0, -1.0, 0.0), 0.0)
    mon.drift_guard(_at(1.0, -1.0), "inner MRFT relay test")  # on the take-off point
    mon.drift_guard(_at(4.2, -1.0, vx=-1.0), "inner MRFT relay test")  # 3.2 m, coming back
    mon.drift_guard(_at(4.2, -1.0, vx=1.5), "inner MRFT relay test")  # 3.95 m ahead
    with pytest.raises(DriftTooLarge, match=r"drifted 3.20 m .*\+3.20 m x.*past 80% of the 5 m"):
        mon.drift_guard(_at(4.2, -1.0, vx=2.0), "inner MRFT relay test")  # 4.2 m ahead
    with pytest.raises(IdentificationError, match="landing commanded"):  # a refusal, exit 3
        mon.drift_guard(_at(1.0, 3.2), "side MRFT relay test")
    # the limit from the command line moves the guard with it
    SafetyMonitor(SafetyLimits(max_distance_m=10.0), (0.0, 0.0, 0.0), 0.0).drift_guard(
        _at(0.0, 3.6, vy=1.0), "inner MRFT relay test")


DRIFTING_SEED = 9  # a heavy vehicle (out of the domain) whose roll relay runs away again and again


def test_a_drifting_relay_test_is_refused_before_the_distance_limit():
    """On the lockstep vehicle: the take-off relays carried it sideways (roll caught by the
    damping PD again and again, its mean tilt pushing one way) past the 5 m limit, an abort;
    the guard refuses it short of 4 m, with the reason."""
    assert domain_check(random_airframe(DRIFTING_SEED)).category == "out-of-domain"
    with pytest.MonkeyPatch.context() as mp:
        # the limit on run-aways, the other net under this vehicle (it refuses it first), off
        mp.setattr(tp, "SequenceConfig", functools.partial(SequenceConfig, max_runaways=10 ** 6))
        with pytest.MonkeyPatch.context() as off:
            off.setattr(safety, "DRIFT_GUARD_FRACTION", 10.0)
            before = tp.run_lockstep(DRIFTING_SEED)
        guarded = tp.run_lockstep(DRIFTING_SEED)
    assert before["outcome"] == "aborted"
    assert "from take-off, over the 5 m" in before["reason"]
    assert guarded["outcome"] == "refused", guarded["reason"]
    assert "relay test: drifted" in guarded["reason"] and "past 80%" in guarded["reason"]
    assert float(guarded["reason"].split("drifted ")[1].split(" m")[0]) < 4.0
