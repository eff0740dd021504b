"""The body-rate path's numerics and profile (mrft_gcs.flight.ratepath); flown live against
ArduCopter's own SITL in tests/test_ardupilot_sitl.py."""

from __future__ import annotations

import math
import tomllib

import numpy as np
import pytest

from mrft_gcs.errors import UsageError
from mrft_gcs.flight.api import parse_actuation, requested_loops
from mrft_gcs.flight.controllers import FlightState
from mrft_gcs.flight.ratepath import (
    K_CORRECT,
    RateChannel,
    alignment,
    body_rates,
    check_feed_forward,
    rate_path_refusal,
)
from mrft_gcs.link.firmware import Firmware
from mrft_gcs.loops import Loop
from mrft_gcs.profiles import PROFILE_DIR, Actuation, load_profile, parse_profile
from mrft_gcs.telemetry import (
    ActuatorTarget,
    AttitudeSetpoint,
    AttitudeTarget,
    AutopilotFamily,
    quat_from_euler,
)

AP = Firmware(AutopilotFamily.ARDUPILOT, 2, (4, 7, 0), "dev")


def _state(roll=0.0, pitch=0.0, yaw=0.0, p=0.0, q=0.0, r=0.0) -> FlightState:
    return FlightState(1.0, roll, pitch, yaw, p, q, r, 1.0, 0, 0, 1, 0, 0, 0)


def test_profile_rate_path_sets_every_feed_forward_to_its_k():
    for name in ("ardupilot", "ardupilot-ned"):
        rp = load_profile(name).rate_path
        assert rp is not None
        for ff, k in zip(rp.ff, rp.k, strict=True):
            assert rp.test_params[ff] == k
        # the rest of the rate loop and the angle loop are zeroed for the flight
        for n in (*rp.rate_p, *rp.angle_p, "ATC_ACCEL_R_MAX", "ATC_ACCEL_P_MAX"):
            assert rp.test_params[n] == 0.0
    assert load_profile("px4").rate_path is None and load_profile("sitl").rate_path is None


def test_profile_rate_path_refuses_a_k_its_test_params_do_not_set():
    data = tomllib.loads((PROFILE_DIR / "ardupilot.toml").read_text())
    data["rate_path"]["test_params"]["ATC_RAT_RLL_FF"] = 0.5  # k is 1
    with pytest.raises(UsageError, match="ATC_RAT_RLL_FF to its k 1"):
        parse_profile(data, "x.toml")
    data["rate_path"]["k"] = [1.0, -1.0, 1.0]
    with pytest.raises(UsageError, match="positive"):
        parse_profile(data, "x.toml")


def test_rate_actuation_tunes_all_five_and_is_refused_off_arducopter():
    assert parse_actuation("rate") is Actuation.RATE
    assert requested_loops(None, Actuation.RATE) == frozenset(Loop)
    with pytest.raises(UsageError, match="torque, attitude or rate"):
        parse_actuation("rates")
    assert rate_path_refusal(load_profile("ardupilot"), AP) is None
    px4 = Firmware(AutopilotFamily.PX4, 2, (1, 15, 0), "official")
    assert "ArduCopter only" in str(rate_path_refusal(load_profile("ardupilot"), px4))
    assert "no [rate_path]" in str(rate_path_refusal(load_profile("px4"), px4))


@pytest.mark.parametrize("target, body", [((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
                                          ((0.05, -0.1, 0.3), (0.0, 0.0, 0.0)),
                                          ((0.2, 0.1, -1.0), (-0.1, 0.25, 0.6))])
def test_rates_sent_give_the_torque_asked_for_through_a_misaligned_target(target, body):
    """What ArduPilot puts out, ``ff d + P (d - gyro)`` with ``d`` the rate sent rotated from
    its target into the body frame, equals the torque the ground station asked for."""
    a = alignment(target, body)
    torque, gyro = np.array([0.12, -0.05, 0.02]), np.array([0.4, -0.3, 0.1])
    for ff, rate_p in ((np.full(3, 10.0), np.zeros(3)), (np.full(3, 10.0), np.full(3, 0.2)),
                       (np.zeros(3), np.array([0.2, 0.25, 0.3]))):
        w = body_rates(torque, gyro, ff, rate_p, a.target_to_body)
        d = a.target_to_body @ w
        assert ff * d + rate_p * (d - gyro) == pytest.approx(torque, abs=1e-12)
    # a heading error alone leaves the thrust axes together
    assert alignment((0.0, 0.0, 0.5), (0.0, 0.0, -0.2)).thrust_error_rad == pytest.approx(0.0)
    assert alignment((0.3, 0.0, 0.0), (0.0, 0.0, 0.0)).thrust_error_rad == pytest.approx(0.3)


def test_channel_rotates_by_the_latest_target_and_zeroes_once_released():
    rp = load_profile("ardupilot").rate_path
    assert rp is not None
    ch, k = RateChannel(rp), rp.k[0]
    out = ActuatorTarget(0.0, 0.1, 0.0, 0.0, 0.4)
    aligned = ch.step(out, _state())
    assert (aligned.roll_rate_rad_s, aligned.pitch_rate_rad_s) == pytest.approx((0.1 / k, 0.0))
    ch.see_target(AttitudeSetpoint(0.0, 0.0, 0.0, math.radians(90), 0.4))
    turned = ch.step(out, _state())
    # the target is turned 90 deg in yaw: its y axis points south, so a body roll (about
    # north) is sent as a negative target pitch (ArduPilot rotates it back)
    assert (turned.roll_rate_rad_s, turned.pitch_rate_rad_s) == pytest.approx((0.0, -0.1 / k),
                                                                              abs=1e-9)
    assert ch.worst_heading_rad == pytest.approx(math.radians(90))
    ch.released = True
    z = ch.step(out, _state())
    assert (z.roll_rate_rad_s, z.pitch_rate_rad_s, z.yaw_rate_rad_s, z.thrust) == (0, 0, 0, 0.4)
    # the hand-over sets the onboard target onto the body: the body's attitude as the set
    # point, with the thrust asked for
    ch.hold_body = True
    b = ch.step(out, _state(roll=0.1, pitch=-0.2, yaw=1.0))
    assert isinstance(b, AttitudeTarget) and b.thrust == 0.4
    assert b.q_wxyz == pytest.approx(quat_from_euler(0.1, -0.2, 1.0))


def test_feed_forward_check_corrects_small_and_refuses_large_errors():
    d = np.linspace(0.002, 0.05, 40)
    assert check_feed_forward("pitch", 10.0, d, 10.0 * d, np.zeros(40)).verdict == "ok"
    c = check_feed_forward("pitch", 10.0, d, 10.0 * (1 + 2 * K_CORRECT) * d, np.zeros(40))
    assert c.verdict == "corrected" and c.k_measured == pytest.approx(10.0 * (1 + 2 * K_CORRECT))
    assert check_feed_forward("pitch", 10.0, d, 5.0 * d, np.zeros(40)).verdict == "refused"
    # too small to measure: nothing to judge on, refused rather than assumed
    assert check_feed_forward("yaw", 10.0, d * 0.01, d * 0.1, np.zeros(40)).verdict == "refused"
