"""The body-rate path's numerics and profile (mrft_gcs.flight.ratepath); flown live against
ArduCopter's own SITL in tests/test_ardupilot_sitl.py."""

from __future__ import annotations

import math
import time
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
    beside_yaw,
    body_rates,
    check_feed_forward,
    rate_path_refusal,
    roll_pitch_names,
    yaw_wait_over,
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
    assert load_profile("sitl").rate_path is None
    # PX4: the same reduction on its rate controller (FF is not scaled by MC_*RATE_K)
    rp = load_profile("px4").rate_path
    assert rp is not None and rp.ff == ("MC_ROLLRATE_FF", "MC_PITCHRATE_FF", "MC_YAWRATE_FF")
    for ff, k in zip(rp.ff, rp.k, strict=True):
        assert rp.test_params[ff] == k
    for axis in ("ROLL", "PITCH", "YAW"):
        for term in ("P", "I", "D"):
            assert rp.test_params[f"MC_{axis}RATE_{term}"] == 0.0


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
    # PX4's channel is in its profile, the sequence is not built for it: refused, saying so
    why = str(rate_path_refusal(load_profile("px4"), px4))
    assert "not built for PX4" in why and "docs/px4.md" in why
    assert "no [rate_path]" in str(rate_path_refusal(load_profile("sitl"), px4))


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


def _quat_matrix(q):
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


@pytest.mark.parametrize("desired", [(0.0, 0.0, 0.0), (0.15, -0.1, 2.0), (-0.3, 0.2, -1.0)])
@pytest.mark.parametrize("target", [(0.0, 0.0, 0.0), (0.1, 0.05, 0.3)])
def test_yaw_beside_roll_pitch_onboard_gives_the_body_its_yaw_torque_alone(desired, target):
    """ArduCopter takes the rates sent with an attitude as the desired attitude's
    (``q_desired * rates``) and feeds the target's rate forward rotated into the body: the
    body's rate target must be yaw's ``d`` alone, nothing on roll and pitch."""
    body = (0.02, -0.03, target[2] - 0.1)
    a = alignment(target, body)
    ff, p, r, torque = 1.0, 0.0, 0.2, 0.05
    v = np.array(beside_yaw(torque, r, ff, p, desired, a.target_to_body))
    target_rate = _quat_matrix(quat_from_euler(*desired)) @ v
    body_rate = a.target_to_body @ target_rate
    assert body_rate == pytest.approx([0.0, 0.0, torque / ff], abs=1e-12)
    # with yaw's rate P written (the hand-over's first stage) the loop's P term is inverted
    v2 = beside_yaw(torque, r, ff, 0.5, desired)
    d = _quat_matrix(quat_from_euler(*desired)) @ np.array(v2)
    assert ff * d[2] + 0.5 * (d[2] - r) == pytest.approx(torque)


def test_channel_with_roll_pitch_onboard_sends_their_attitude_and_yaw_as_feed_forward():
    rp = load_profile("ardupilot").rate_path
    assert rp is not None
    ch = RateChannel(rp)
    ch.rp_onboard, ch.refs = True, lambda: (0.05, -0.08)
    out = ActuatorTarget(0.0, 0.3, -0.3, 0.1, 0.45)  # roll/pitch torques no longer sent
    a = ch.step(out, _state(yaw=0.7))
    assert isinstance(a, AttitudeTarget) and a.thrust == 0.45 and a.body_rates is not None
    r, pch, y = _euler(a.q_wxyz)
    assert (r, pch, y) == pytest.approx((0.05, -0.08, 0.7))
    assert _quat_matrix(a.q_wxyz) @ a.body_rates == pytest.approx([0, 0, 0.1 / rp.k[2]])
    # the heading sent follows what the target integrates: yaw's rate over time
    time.sleep(0.05)
    b = ch.step(out, _state(yaw=0.7))
    assert 0.7 < _euler(b.q_wxyz)[2] < 0.7 + 0.1 / rp.k[2] * 0.2
    # the hand-over's alignment: the body's attitude, yaw's rate beside it
    ch.hold_body = True
    c = ch.step(out, _state(roll=0.1, yaw=1.0))
    assert c.q_wxyz == pytest.approx(quat_from_euler(0.1, 0.0, 1.0)) and c.body_rates
    # the sequence on attitude set points (its side tests): their roll and pitch are sent,
    # at the heading the target integrates, yaw's torque beside them
    ch.hold_body = False
    d = ch.step_attitude(AttitudeTarget(0.0, quat_from_euler(-0.04, 0.06, 0.2), 0.5),
                         _state(yaw=1.0), 0.1)
    assert _euler(d.q_wxyz)[:2] == pytest.approx((-0.04, 0.06)) and d.thrust == 0.5
    assert _euler(d.q_wxyz)[2] == pytest.approx(1.0, abs=0.05)
    assert _quat_matrix(d.q_wxyz) @ d.body_rates == pytest.approx([0, 0, 0.1 / rp.k[2]])
    ch.hold_body = True
    ch.released = True  # yaw's own hand-over: nothing fed forward
    assert ch.step(out, _state(roll=0.1, yaw=1.0)).body_rates is None


def _euler(q):
    w, x, y, z = q
    return (math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y)),
            math.asin(2 * (w * y - z * x)),
            math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))


def test_roll_pitch_hand_over_leaves_yaw_and_the_shared_parameters_for_later():
    rp = load_profile("ardupilot").rate_path
    assert rp is not None
    names = set(roll_pitch_names(rp))
    assert {*rp.rate_p[:2], *rp.ff[:2], *rp.angle_p[:2]} <= names
    assert not names & {rp.rate_p[2], rp.ff[2], rp.angle_p[2], "ATC_RATE_FF_ENAB",
                        "ATC_ACCEL_Y_MAX", "GUID_TIMEOUT", "GCS_PID_MASK"}
    assert names <= set(rp.test_params)
    # yaw's wait counts on: its reason names where roll and pitch are
    assert "onboard" in yaw_wait_over(99.0, np.zeros(2), onboard=True)
    assert "the onboard cascade" in yaw_wait_over(1.0, np.radians([90.0, 0.0]), onboard=True)


def test_feed_forward_check_corrects_small_and_refuses_large_errors():
    d = np.linspace(0.002, 0.05, 40)
    assert check_feed_forward("pitch", 10.0, d, 10.0 * d, np.zeros(40)).verdict == "ok"
    c = check_feed_forward("pitch", 10.0, d, 10.0 * (1 + 2 * K_CORRECT) * d, np.zeros(40))
    assert c.verdict == "corrected" and c.k_measured == pytest.approx(10.0 * (1 + 2 * K_CORRECT))
    assert check_feed_forward("pitch", 10.0, d, 5.0 * d, np.zeros(40)).verdict == "refused"
    # too small to measure: nothing to judge on, refused rather than assumed
    assert check_feed_forward("yaw", 10.0, d * 0.01, d * 0.1, np.zeros(40)).verdict == "refused"


# ---------------------------------------------------------------------- yaw
def _fly_yaw(relay, K: float, T_prop: float, T1: float, tau: float, seconds: float,
             disturbance: float = 0.0, until_ready: bool = True, disturbance_from_s=0.0,
             drift_rad_s: float = 0.0):
    """A yaw plant ``K e^{-tau s} / (s (T_prop s + 1) (T1 s + 1))`` (normalised torque in,
    heading out) integrated at 1 kHz, sampled and commanded at 250 Hz as the stream does;
    the heading set point is 0, and turns at ``drift_rad_s`` from ``disturbance_from_s``.
    Returns the headings seen (rad)."""
    from collections import deque

    dt, every = 0.001, 4
    lag, r, y = 0.0, 0.0, 0.0
    queue = deque([0.0] * max(1, round(tau / dt)))
    u, seen = 0.0, []
    for k in range(round(seconds / dt)):
        if k % every == 0:
            ref = drift_rad_s * max(0.0, k * dt - disturbance_from_s)
            u = relay.step(ref, y, r, k * dt)
            seen.append(y)
            if until_ready and relay.snapshot is not None:
                break
        queue.append(u + (disturbance if k * dt >= disturbance_from_s else 0.0))
        lag += dt * (queue.popleft() - lag) / T_prop
        r += dt * (K * lag - r) / T1
        y += dt * r
    return np.array(seen)


YAW_PLANT = (20.0, 0.05, 1.0, 0.01)  # K, T_prop, T1, tau: inside the attitude domain


def test_yaw_relay_holds_then_cycles_and_hands_its_steady_cycles_once():
    from mrft_gcs.flight.controllers import YawHold
    from mrft_gcs.flight.phases.yaw import YawRelay, YawState
    from mrft_gcs.identify import relay_settings
    from mrft_gcs.loops import LoopKind

    beta = relay_settings(LoopKind.ATTITUDE).beta
    relay = YawRelay(YawHold(0.8, 0.2, limit=0.5), beta)
    seen = _fly_yaw(relay, *YAW_PLANT, seconds=15.0)
    assert relay.state is YawState.READY, (relay.state, relay.why)
    snap = relay.take()
    assert snap is not None and relay.take() is None  # handed over once
    # it cycled about the set point, near the goal swing, and never far off
    assert abs(float(np.mean(snap.y))) < 0.5 * float(np.ptp(snap.y))
    assert 0.4 < 0.5 * float(np.ptp(snap.y)) / relay.rules.amp_goal_rad < 2.5
    assert np.max(np.abs(seen)) < relay.rules.abort_rad
    assert snap.beta == beta and snap.h == relay.h


def test_yaw_identified_by_the_attitude_classifier_and_checked_on_the_cascade():
    """The bundled classifier identifies the yaw relay's cycles (the attitude model); the
    written gains keep the margin on the true plant's cascade, and twice those gains do not:
    the check that scales them is what stands between a wrong gain and the vehicle."""
    from mrft_gcs.flight.controllers import YawHold
    from mrft_gcs.flight.onboard import cascade_gains
    from mrft_gcs.flight.phases.yaw import YawRelay
    from mrft_gcs.flight.ratepath import yaw_design, yaw_names
    from mrft_gcs.identify import identify, relay_settings
    from mrft_gcs.loops import LoopKind
    from mrft_gcs.pd_design import PD
    from mrft_gcs.plant import InnerModel

    beta = relay_settings(LoopKind.ATTITUDE).beta
    relay = YawRelay(YawHold(0.8, 0.2, limit=0.5), beta)
    _fly_yaw(relay, *YAW_PLANT, seconds=15.0)
    snap = relay.take()
    assert snap is not None
    ident = identify(LoopKind.ATTITUDE, snap.t_s, snap.u, snap.y, beta=snap.beta, h=snap.h,
                     bias=snap.bias)
    m = ident.model
    assert isinstance(m, InnerModel)
    K, T_prop, T1, tau = YAW_PLANT
    # the relay's own dynamics at the cycle: K/T1 (the gain there) within a factor of 2
    assert 0.5 < (m.K / m.T1) / (K / T1) < 2.0, m
    names = yaw_names(load_profile("ardupilot").rate_path)
    d = yaw_design(ident, names, 20.0, 2.5)
    assert d.refusal is None and d.cascade is not None, d
    assert d.values[names["rate_d"]] == 0.0
    written = PD(d.values[names["angle_p"]] * d.values[names["rate_p"]],
                 d.values[names["rate_p"]])
    fe = d.values[names["flte"]]
    wi = d.values[names["rate_i"]] / written.Kd  # the written rate I's zero (0: none)
    truth = InnerModel(*YAW_PLANT)
    on_truth = cascade_gains(truth, written, 20.0, error_filter_hz=fe,
                             integrator_zero_rad_s=wi)
    assert on_truth.pm_deg >= 10.0, on_truth  # the design's 15 less the identification's error
    doubled = cascade_gains(truth, PD(2 * written.Kc, 2 * written.Kd), 20.0,
                            error_filter_hz=fe)
    assert doubled.pm_identified_deg < 10.0 and doubled.scale < 0.8, doubled


def test_yaw_design_writes_a_rate_i_that_keeps_the_margin():
    """Yaw gets a rate I like roll and pitch: its zero a decade or more below the crossover,
    the margin with it (checked again here on the cascade, I included) at least 15 deg, the
    P gains the same as without it; none where the P gains already sit on the margin."""
    from mrft_gcs.flight import ratepath
    from mrft_gcs.flight.onboard import cascade_gains
    from mrft_gcs.flight.ratepath import yaw_design, yaw_names
    from mrft_gcs.identify import Identification
    from mrft_gcs.loops import LoopKind
    from mrft_gcs.pd_design import frequency_grid, optimal_pd
    from mrft_gcs.plant import InnerModel, inner_response

    names = yaw_names(load_profile("ardupilot").rate_path)

    def design(model, decade=ratepath.YAW_RATE_I_DECADE):
        w = frequency_grid(model.T_prop, model.T1, model.tau)
        pd = optimal_pd(inner_response(model.K, model.T_prop, model.T1, model.tau, w)[0],
                        w).pd
        ident = Identification(LoopKind.ATTITUDE, model, 0, 1.0, -0.7, 0.1, 0.3, 0.01, pd)
        old, ratepath.YAW_RATE_I_DECADE = ratepath.YAW_RATE_I_DECADE, decade
        try:
            return yaw_design(ident, names, 20.0, 2.5)
        finally:
            ratepath.YAW_RATE_I_DECADE = old

    # an ArduCopter-SITL-like yaw (drag past the domain: the edge model checked too)
    m = InnerModel(60.0, 0.04, 4.2, 0.01)
    d, d0 = design(m), design(m, decade=0.0)
    c = d.cascade
    i, kd = d.values[names["rate_i"]], d.values[names["rate_p"]]
    assert i > 0 and d0.values[names["rate_i"]] == 0.0, (d.values, d0.values)
    assert {k: v for k, v in d.values.items() if k != names["rate_i"]} == {
        k: v for k, v in d0.values.items() if k != names["rate_i"]}  # P never lowered for I
    wi = i / kd
    assert c.wc_rad_s / wi >= ratepath.YAW_RATE_I_DECADE - 1e-6, c
    for model in (m, d.edge):
        check = cascade_gains(model, c.gains, 20.0, error_filter_hz=d.values[names["flte"]],
                              integrator_zero_rad_s=wi)
        assert check.scale == 1.0 and check.pm_deg >= 15.0, check
    assert "rate I" in d.note()
    # a decade's I would cost more than the margin left: lowered, not dropped
    assert check.pm_deg < d0.cascade.pm_deg
    # gains scaled onto the margin already: no I (the P is not lowered for it), and it says so
    tight = design(InnerModel(*YAW_PLANT))
    assert tight.cascade.scale < 1.0 and tight.values[names["rate_i"]] == 0.0, tight
    assert tight.cascade.integrator_refused and "no rate I" in tight.note()


def test_yaw_relay_gives_up_to_the_hold_with_the_reason():
    from mrft_gcs.flight.controllers import YawHold
    from mrft_gcs.flight.phases.yaw import YawRelay, YawRules, YawState

    hold = YawHold(0.8, 0.2, limit=0.5)
    # a heading swing past the limit (here a tiny one) ends the relay
    relay = YawRelay(hold, -0.7, YawRules(abort_rad=math.radians(0.2)))
    _fly_yaw(relay, *YAW_PLANT, seconds=10.0)
    assert relay.state is YawState.HELD and "swung" in relay.why, relay.why
    assert relay.done and relay.take() is None
    # the hold flies from there: the same output as the hold itself
    assert relay.step(0.0, 0.1, 0.0, 20.0) == hold.step(0.0, 0.1, 0.0)
    # no steady cycle within the time limit
    slow = YawRelay(hold, -0.7, YawRules(max_s=1.0))
    _fly_yaw(slow, 4.0, 0.05, 1.0, 0.01, seconds=4.0)
    assert slow.state is YawState.HELD and "no steady relay cycle" in slow.why, slow.why
    # a torque bias the hold's P cannot take out: the relay still starts (once at rest), and
    # gives up in time (the zero-gain window waits for it)
    biased = YawRelay(hold, -0.7, YawRules(max_s=3.0))
    _fly_yaw(biased, *YAW_PLANT, seconds=6.0, disturbance=0.15, until_ready=False)
    assert biased.done and math.isfinite(biased.t_relay_s), (biased.state, biased.why)


def test_yaw_design_raises_the_error_filter_only_as_far_as_the_margin_needs():
    from mrft_gcs.flight.onboard import cascade_gains
    from mrft_gcs.flight.ratepath import YAW_FLTE_KEEP, YAW_FLTE_STEP, yaw_design, yaw_names
    from mrft_gcs.identify import Identification
    from mrft_gcs.loops import LoopKind
    from mrft_gcs.pd_design import frequency_grid, optimal_pd
    from mrft_gcs.plant import InnerModel, inner_response

    m = InnerModel(*YAW_PLANT)
    w = frequency_grid(m.T_prop, m.T1, m.tau)
    pd = optimal_pd(inner_response(m.K, m.T_prop, m.T1, m.tau, w)[0], w).pd
    ident = Identification(LoopKind.ATTITUDE, m, 0, 1.0, -0.7, 0.1, 0.5, 0.03, pd)
    names = yaw_names(load_profile("ardupilot").rate_path)
    d = yaw_design(ident, names, 20.0, 2.5)
    fe = d.values[names["flte"]]
    unfiltered = cascade_gains(m, pd, 20.0).scale
    assert fe > 2.5 and d.flte_from_hz == 2.5, d
    assert d.cascade.scale >= YAW_FLTE_KEEP * unfiltered and d.cascade.pm_deg >= 15.0, d
    # one step lower would not do
    assert (cascade_gains(m, pd, 20.0, error_filter_hz=fe / YAW_FLTE_STEP).scale
            < YAW_FLTE_KEEP * unfiltered)
    # a vehicle without an error filter keeps none; the same gains, unscaled
    d0 = yaw_design(ident, names, 20.0, 0.0)
    assert d0.values[names["flte"]] == 0.0 and d0.flte_from_hz is None
    assert d0.cascade.scale == unfiltered


def test_profiles_back_up_and_restore_the_yaw_gains_the_tune_writes():
    from mrft_gcs.flight.ratepath import yaw_names

    for name in ("ardupilot", "ardupilot-ned"):
        rp = load_profile(name).rate_path
        assert rp is not None
        assert set(yaw_names(rp).values()) - {yaw_names(rp)["flte"]} <= set(rp.test_params)
        assert yaw_names(rp)["flte"] in rp.test_params


def test_yaw_relay_takes_the_torque_that_holds_the_heading_as_its_bias():
    """A yaw torque that appears once the relay runs (roll and pitch relays next to it move
    it) drifts the cycle off the set point: with re-biasing on, the relay's bias becomes the
    cycle's mean torque and the cycles come steady about the set point; off (the default),
    the relay swings off and gives up."""
    from mrft_gcs.flight.controllers import YawHold
    from mrft_gcs.flight.phases.yaw import YawRelay, YawRules, YawState

    relay = YawRelay(YawHold(0.8, 0.2, limit=0.5), -0.7, YawRules(max_rebias=2))
    _fly_yaw(relay, *YAW_PLANT, seconds=15.0, disturbance=0.1, disturbance_from_s=2.5)
    assert relay.state is YawState.READY, (relay.state, relay.why, relay.events)
    assert relay.rebiased >= 1 and any("relay bias" in e for e in relay.events)
    assert relay.bias == pytest.approx(-0.1, abs=0.02)
    snap = relay.take()
    assert abs(float(np.mean(snap.y))) < 0.5 * float(np.ptp(snap.y))
    off = YawRelay(YawHold(0.8, 0.2, limit=0.5), -0.7)
    _fly_yaw(off, *YAW_PLANT, seconds=15.0, disturbance=0.1, disturbance_from_s=2.5)
    assert off.state is YawState.HELD and off.rebiased == 0, (off.state, off.why)


def _yaw_halves(share: float) -> tuple[object, np.ndarray]:
    """A yaw relay fed a 0.3 s, 0.6 deg heading cycle whose centre moves off the set point at
    3 deg/s (as ArduCopter SITL's did, 0.3-0.6 deg a cycle); the heading is given, not
    flown, so that only the relay's switching is judged. Returns the relay and its
    half-periods over the last 2 s."""
    from mrft_gcs.flight.controllers import YawHold
    from mrft_gcs.flight.phases.yaw import YawRelay, YawRules

    relay = YawRelay(YawHold(1.35, 0.3, limit=0.5), -0.7,
                     YawRules(centre_share=share, size_on_cycle=10**6, max_s=60.0))
    A, w = math.radians(0.6), 2 * math.pi / 0.3
    ts = np.arange(0.0, 8.0, 0.004)
    us = []
    for t in ts:
        ta = max(0.0, t - 1.2)
        y = A * math.sin(w * ta) - math.radians(3.0) * ta
        us.append(relay.step(0.0, y, A * w * math.cos(w * ta), float(t)))
    us = np.array(us)
    sw = np.flatnonzero(np.diff(us) != 0)
    sw = sw[ts[sw] > 6.0]
    return relay, np.diff(ts[sw])


def test_yaw_relay_zero_follows_a_cycle_that_drifts_off_its_set_point():
    """A cycle that drifts off the set point leaves an MRFT about a fixed zero (its extremes
    are measured from zero): once the cycle no longer crosses it, the relay switches
    lopsided or not at all (here: not at all). The relay's zero follows the cycle, so it
    keeps switching twice a cycle, once per period of the heading's cycle."""
    relay, halves = _yaw_halves(0.5)
    assert relay.max_zero_rad > math.radians(5.0), relay.max_zero_rad
    periods = halves[:-1] + halves[1:]
    assert halves.size >= 10 and np.all(np.abs(periods - 0.3) < 0.012), halves
    fixed, halves = _yaw_halves(math.inf)
    assert fixed.max_zero_rad == 0.0
    assert halves.size < 10, halves


def test_report_and_table_carry_yaw_tuned_or_held():
    """``loops.yaw`` in the report JSON (SPEC 4.3 keys, then yaw's own) and a yaw row in the
    CLI's table: the written values, the gains the cascade closes and the predicted margin
    where tuned; the reason, and nulls (never NaN), where held."""
    import json

    from rich.console import Console

    from mrft_gcs.cli.tune import result_table
    from mrft_gcs.flight.api import TuneResult
    from mrft_gcs.flight.phases.yaw import YawOutcome
    from mrft_gcs.flight.ratepath import yaw_design, yaw_names
    from mrft_gcs.flight.report import report_dict
    from mrft_gcs.identify import Identification
    from mrft_gcs.loops import LoopKind
    from mrft_gcs.pd_design import frequency_grid, optimal_pd
    from mrft_gcs.plant import InnerModel, inner_response

    m = InnerModel(*YAW_PLANT)
    w = frequency_grid(m.T_prop, m.T1, m.tau)
    pd = optimal_pd(inner_response(m.K, m.T_prop, m.T1, m.tau, w)[0], w).pd
    ident = Identification(LoopKind.ATTITUDE, m, 3, 0.9, -0.7, 0.3, 0.31, 0.011, pd)
    d = yaw_design(ident, yaw_names(load_profile("ardupilot").rate_path), 20.0, 2.5)
    c = d.cascade
    tuned = YawOutcome("tuned", None, -0.7, 0.3, 0.0, 0.0005, 0.31, 0.011, ident, c.gains,
                       dict(d.values), c.pm_deg, c.wc_rad_s, 5.2, 0.05, 0.06, "yaw tuned ...")
    held = YawOutcome("held", "no steady relay cycle within 8 s", -0.7, 0.3, 0.0, 0.0005,
                      math.nan, math.nan, None, None, {}, math.nan, math.nan, math.nan, 0.2,
                      0.0, "yaw held on its own gains: no steady relay cycle within 8 s")

    def run(y):
        r = TuneResult("udp:x", "ardupilot", "ardupilot", "rate", "now", 12.0, {}, (), None,
                       "ok", yaw=y)
        console = Console(width=300, record=True)
        console.print(result_table(r))
        rows = [ln for ln in console.export_text().splitlines() if "│ yaw" in ln]
        return json.loads(json.dumps(report_dict(r), allow_nan=False))["loops"], rows

    loops, rows = run(tuned)
    y = loops["yaw"]
    assert y["state"] == "tuned" and y["reason"] is None and y["class"] == 3
    assert y["model"] == {"K": 20.0, "T_prop": 0.05, "T1": 1.0, "tau": 0.01}
    assert y["written"]["ATC_ANG_YAW_P"] == pytest.approx(c.gains.Kc / c.gains.Kd)
    assert y["written"]["ATC_RAT_YAW_P"] == pytest.approx(c.gains.Kd)
    assert y["gains"] == {"Kc": pytest.approx(c.gains.Kc), "Kd": pytest.approx(c.gains.Kd)}
    assert y["pm_predicted_deg"] == pytest.approx(c.pm_deg) and y["pm_predicted_deg"] >= 15
    assert y["tuned_after_s"] == 5.2 and y["zero_moved_deg"] == pytest.approx(math.degrees(0.06))
    assert len(rows) == 1 and "tuned" in rows[0] and "PM" in rows[0]
    loops, rows = run(held)
    y = loops["yaw"]
    assert y["state"] == "held" and y["reason"] == "no steady relay cycle within 8 s"
    assert y["gains"] is None and y["model"] is None and y["pm_predicted_deg"] is None
    assert y["written"] == {} and y["period_s"] is None and y["tuned_after_s"] is None
    assert len(rows) == 1 and "held" in rows[0] and "no steady relay cycle" in rows[0]
    loops, rows = run(None)  # yaw not relay-tested: no entry, no row (as before)
    assert "yaw" not in loops and rows == []


def test_inair_check_models_the_written_rate_i():
    """The in-air check's model of ArduCopter's cascade includes the written rate I: at low
    frequency its feedback grows as Kd w_i / s (no I: flat at Kc), and its predicted margin
    at a decade's zero is lower than without it, as the design predicts."""
    import numpy as np

    from mrft_gcs.flight.inair import OnboardCascade, plan_check
    from mrft_gcs.flight.onboard import rate_loop_gains
    from mrft_gcs.pd_design import PD
    from mrft_gcs.plant import InnerModel

    m = InnerModel(K=34.0, T_prop=0.0085, T1=0.095, tau=0.006)
    c = rate_loop_gains(m, PD(6.4, 0.21), 20.0, decade=10.0)
    wi = c.integrator_zero_rad_s
    with_i, without = (OnboardCascade(20.0, integrator_zero_rad_s=w) for w in (wi, 0.0))
    w = np.array([wi / 100.0])
    assert abs(with_i.paths(c.gains, w)[1][0]) > 50 * abs(without.paths(c.gains, w)[1][0])
    pm_i = plan_check(m, c.gains, 0.035, cascade=with_i).predicted_pm_deg
    pm_0 = plan_check(m, c.gains, 0.035, cascade=without).predicted_pm_deg
    assert 3.0 < pm_0 - pm_i < 9.0, (pm_0, pm_i)
    assert "rate I zero" in with_i.describe() and "rate I" not in without.describe()
