"""The relay guard acts on where the tilt is heading, not only on where it was measured."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import tune_population as tp  # noqa: E402

from mrft_gcs.flight import safety  # noqa: E402
from mrft_gcs.flight.controllers import FlightState  # noqa: E402
from mrft_gcs.flight.safety import RelayTooLarge, SafetyMonitor, predicted_tilt_rad  # noqa: E402
from mrft_gcs.profiles import SafetyLimits  # noqa: E402
from mrft_gcs.sitl import domain_check, random_airframe  # noqa: E402


def _rolling(deg: float, rate_deg_s: float) -> FlightState:
    return FlightState(1.0, math.radians(deg), 0, 0, math.radians(rate_deg_s), 0, 0, 1.0,
                       0, 0, 1.0, 0, 0, 0)


def test_the_guard_stops_a_swing_heading_past_its_threshold_before_it_gets_there():
    mon = SafetyMonitor(SafetyLimits(max_tilt_deg=35.0), (0.0, 0.0, 0.0), 0.0, lead_s=0.03)
    mon.relay_guard(_rolling(28.0, -200.0), "inner MRFT relay test")  # on its way back
    mon.relay_guard(_rolling(28.0, 60.0), "inner MRFT relay test")  # 29.8 ahead: slowing
    with pytest.raises(RelayTooLarge, match=r"tilt 28.0 deg heading for 34.0 deg, past 90%"):
        mon.relay_guard(_rolling(28.0, 200.0), "inner MRFT relay test")
    # no lead: the measured tilt alone, as before
    SafetyMonitor(SafetyLimits(max_tilt_deg=35.0), (0.0, 0.0, 0.0), 0.0,
                  lead_s=0.0).relay_guard(_rolling(28.0, 200.0), "inner MRFT relay test")


def _at(t_s: float, deg: float, p_rad_s: float) -> FlightState:
    return FlightState(t_s, math.radians(deg), 0, 0, p_rad_s, 0, 0, t_s, 0, 0, 1.0, 0, 0, 0)


def test_a_braking_swing_is_let_run_where_a_speeding_one_is_stopped():
    """The same tilt and rate (27.5 deg, 2.6 rad/s: 32 deg ahead on the rate alone); the
    rate falling by 100 rad/s^2 peaks short of the guard, rising does not."""
    lim = SafetyLimits(max_tilt_deg=35.0)
    braking = SafetyMonitor(lim, (0.0, 0.0, 0.0), 0.0, lead_s=0.03)
    braking.relay_guard(_at(1.000, 26.0, 3.0), "inner MRFT relay test")
    braking.relay_guard(_at(1.004, 27.5, 2.6), "inner MRFT relay test")
    speeding = SafetyMonitor(lim, (0.0, 0.0, 0.0), 0.0, lead_s=0.03)
    speeding.relay_guard(_at(1.000, 26.0, 2.2), "inner MRFT relay test")
    with pytest.raises(RelayTooLarge, match="heading for 3[3-4]"):
        speeding.relay_guard(_at(1.004, 27.5, 2.6), "inner MRFT relay test")
    # a new take-off forgets the last swing
    speeding.reset((0.0, 0.0, 0.0), 2.0)
    with pytest.raises(RelayTooLarge, match="heading for 32.0"):
        speeding.relay_guard(_at(2.000, 27.5, 2.6), "inner MRFT relay test")


def test_the_prediction_is_never_below_the_measured_tilt():
    s = _rolling(20.0, -400.0)
    assert predicted_tilt_rad(s, 0.02) == pytest.approx(math.radians(20.0))
    assert math.degrees(predicted_tilt_rad(_rolling(20.0, 100.0), 0.05)) == pytest.approx(25.0)


GUARDED_SEED = 1  # a light vehicle (out of the domain) whose take-off relay swings far over


def test_the_guard_keeps_the_true_tilt_under_the_limit_where_the_measured_one_did_not():
    """On the lockstep vehicle (telemetry and commands over its link's delay): the guard on
    the measured tilt stopped the swing only after the vehicle had passed the guard's own
    90 % line (on older relay sizing, past the limit); looking a round trip ahead it stops it
    short of that line."""
    assert domain_check(random_airframe(GUARDED_SEED)).category == "out-of-domain"
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(safety, "predicted_tilt_rad", lambda s, *_: s.tilt_rad)
        before = tp.run_lockstep(GUARDED_SEED)
    assert before["outcome"] == "refused" and "past 90%" in before["reason"]
    assert before["max_tilt_deg"] > 0.95 * 35.0
    after = tp.run_lockstep(GUARDED_SEED)
    assert after["outcome"] == "refused" and "past 90%" in after["reason"]
    assert after["max_tilt_deg"] < 0.9 * 35.0
