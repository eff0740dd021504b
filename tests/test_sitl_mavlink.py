"""The SITL as a subprocess, driven over UDP with plain pymavlink (SPEC 4.1 subset)."""

from __future__ import annotations

import math
import os
import time

import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402

from mrft_gcs.sitl import SitlProcess, load_airframe  # noqa: E402

M = mavutil.mavlink
OFFBOARD, POSCTL, LAND_MAIN, LAND_SUB = 6, 3, 4, 6


def connect(sitl: SitlProcess, **kw):
    gcs = mavutil.mavlink_connection(sitl.connection_string, source_system=255,
                                     source_component=190, **kw)
    hb = gcs.recv_match(type="HEARTBEAT", blocking=True, timeout=10)
    assert hb is not None, "no heartbeat from the SITL"
    return gcs


def wait(gcs, kind, timeout=3.0, cond=lambda m: True):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        msg = gcs.recv_match(type=kind, blocking=True, timeout=max(0.01, end - time.monotonic()))
        if msg is not None and cond(msg):
            return msg
    return None


def fresh(gcs, kind, timeout=1.0):
    """The next ``kind`` message after dropping whatever is queued (old telemetry)."""
    while gcs.recv_match(blocking=False) is not None:
        pass
    return wait(gcs, kind, timeout)


def command(gcs, cmd, *params, timeout=3.0):
    p = list(params) + [0.0] * (7 - len(params))
    gcs.mav.command_long_send(1, 1, cmd, 0, *p)
    ack = wait(gcs, "COMMAND_ACK", timeout, lambda m: m.command == cmd)
    return None if ack is None else ack.result


def set_interval(gcs, msg_id, hz):
    return command(gcs, M.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / hz)


@pytest.fixture
def sitl():
    with SitlProcess(vehicle="qdrone", port=None) as s:
        yield s


@pytest.fixture
def fast_sitl():
    with SitlProcess(vehicle="qdrone", port=None, speedup=2.0) as s:
        yield s


def test_heartbeat_is_px4_quadrotor_at_1hz(sitl):
    gcs = connect(sitl)
    t = []
    for _ in range(2):
        hb = wait(gcs, "HEARTBEAT", 3.0)
        assert hb is not None
        t.append(time.monotonic())
    assert hb.type == M.MAV_TYPE_QUADROTOR
    assert hb.autopilot == M.MAV_AUTOPILOT_PX4
    assert hb.base_mode & M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert not hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED
    assert (hb.custom_mode >> 16) & 0xFF == 1  # MANUAL at boot
    assert 0.7 < t[1] - t[0] < 1.3
    assert gcs.mavlink20()


def test_hexa_profile_announces_hexarotor():
    with SitlProcess(vehicle="f550", port=None) as s:
        hb = wait(connect(s), "HEARTBEAT")
    assert hb.type == M.MAV_TYPE_HEXAROTOR


def test_message_interval_gives_250hz_attitude_and_position(sitl):
    gcs = connect(sitl)
    assert set_interval(gcs, M.MAVLINK_MSG_ID_ATTITUDE, 250) == M.MAV_RESULT_ACCEPTED
    assert set_interval(gcs, M.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 250) == M.MAV_RESULT_ACCEPTED
    assert set_interval(gcs, M.MAVLINK_MSG_ID_HIGHRES_IMU, 100) == M.MAV_RESULT_ACCEPTED
    assert set_interval(gcs, 9999, 100) == M.MAV_RESULT_DENIED
    time.sleep(0.2)
    while gcs.recv_match(blocking=False) is not None:
        pass
    counts = {"ATTITUDE": 0, "LOCAL_POSITION_NED": 0, "HIGHRES_IMU": 0}
    t0 = time.monotonic()
    while time.monotonic() - t0 < 2.0:
        msg = gcs.recv_match(type=list(counts), blocking=True, timeout=0.1)
        if msg is not None:
            counts[msg.get_type()] += 1
    elapsed = time.monotonic() - t0
    assert counts["ATTITUDE"] / elapsed >= 245, counts
    assert counts["LOCAL_POSITION_NED"] / elapsed >= 245, counts
    assert counts["HIGHRES_IMU"] > 150, counts


def test_param_protocol(sitl):
    gcs = connect(sitl)
    gcs.mav.param_request_list_send(1, 1)
    seen = {}
    while True:
        pv = wait(gcs, "PARAM_VALUE", 2.0)
        if pv is None:
            break
        seen[pv.param_id] = pv
        if len(seen) == pv.param_count:
            break
    for name in ("MC_ROLL_P", "MC_ROLLRATE_P", "MC_ROLLRATE_I", "MC_ROLLRATE_D", "MC_ROLLRATE_K",
                 "MC_PITCH_P", "MC_PITCHRATE_P", "MC_YAW_P", "MC_YAWRATE_P", "MPC_XY_P",
                 "MPC_XY_VEL_P_ACC", "MPC_XY_VEL_I_ACC", "MPC_XY_VEL_D_ACC", "MPC_Z_P",
                 "MPC_Z_VEL_P_ACC", "MPC_Z_VEL_I_ACC", "MPC_Z_VEL_D_ACC", "MPC_THR_HOVER",
                 "COM_OF_LOSS_T"):
        assert name in seen, name
        assert seen[name].param_type == M.MAV_PARAM_TYPE_REAL32
    assert len(seen) == next(iter(seen.values())).param_count

    gcs.mav.param_set_send(1, 1, b"MC_ROLL_P", 4.25, M.MAV_PARAM_TYPE_REAL32)
    pv = wait(gcs, "PARAM_VALUE", 2.0, lambda m: m.param_id == "MC_ROLL_P")
    assert pv.param_value == pytest.approx(4.25)
    gcs.mav.param_request_read_send(1, 1, b"MC_ROLL_P", -1)
    pv = wait(gcs, "PARAM_VALUE", 2.0, lambda m: m.param_id == "MC_ROLL_P")
    assert pv.param_value == pytest.approx(4.25)
    gcs.mav.param_request_read_send(1, 1, b"", pv.param_index)
    assert wait(gcs, "PARAM_VALUE", 2.0).param_id == "MC_ROLL_P"

    gcs.mav.param_set_send(1, 1, b"MC_ROLL_P", float("nan"), M.MAV_PARAM_TYPE_REAL32)
    pv = wait(gcs, "PARAM_VALUE", 2.0, lambda m: m.param_id == "MC_ROLL_P")
    assert pv.param_value == pytest.approx(4.25)  # unchanged
    gcs.mav.param_set_send(1, 1, b"NOT_A_PARAM", 1.0, M.MAV_PARAM_TYPE_REAL32)
    got = []
    end = time.monotonic() + 1.0
    while time.monotonic() < end:
        msg = gcs.recv_match(type=["PARAM_VALUE", "STATUSTEXT"], blocking=True, timeout=0.1)
        if msg is not None:
            got.append(msg)
    assert not [m for m in got if m.get_type() == "PARAM_VALUE"]
    assert [m for m in got if m.get_type() == "STATUSTEXT" and "NOT_A_PARAM" in m.text]


def _offboard_torque_climb(gcs, thrust, seconds):
    """Stream torque setpoints (zero torque, given thrust), switch to OFFBOARD, arm, climb.

    Returns the last LOCAL_POSITION_NED and HEARTBEAT seen while still streaming.
    """
    def send():
        gcs.mav.set_actuator_control_target_send(0, 0, 1, 1, [0.0, 0.0, 0.0, thrust] + [0.0] * 4)

    for _ in range(10):
        send()
        time.sleep(0.01)
    assert command(gcs, M.MAV_CMD_DO_SET_MODE, M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                   OFFBOARD) == M.MAV_RESULT_ACCEPTED
    assert command(gcs, M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
    last = {}
    end = time.monotonic() + seconds
    while time.monotonic() < end or "HEARTBEAT" not in last:
        send()
        t_next = time.monotonic() + 0.01
        while time.monotonic() < t_next:
            msg = gcs.recv_match(type=["HEARTBEAT", "LOCAL_POSITION_NED"], blocking=True,
                                 timeout=0.005)
            if msg is not None and time.monotonic() > end - 0.3:
                last[msg.get_type()] = msg
    return last["LOCAL_POSITION_NED"], last["HEARTBEAT"]


def test_arm_offboard_torque_climb_then_land_command(fast_sitl):
    gcs = connect(fast_sitl)
    hover = load_airframe("qdrone").hover_thrust
    # OFFBOARD is refused without a setpoint stream, as PX4 does
    assert command(gcs, M.MAV_CMD_DO_SET_MODE, M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                   OFFBOARD) == M.MAV_RESULT_DENIED
    pos, hb = _offboard_torque_climb(gcs, 1.3 * hover, 1.0)
    assert pos.z < -0.5, pos
    assert hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED
    assert (hb.custom_mode >> 16) & 0xFF == OFFBOARD
    assert command(gcs, M.MAV_CMD_NAV_LAND) == M.MAV_RESULT_ACCEPTED
    hb = wait(gcs, "HEARTBEAT", 2.0, lambda m: (m.custom_mode >> 16) & 0xFF == LAND_MAIN)
    assert hb is not None and (hb.custom_mode >> 24) & 0xFF == LAND_SUB
    hb = wait(gcs, "HEARTBEAT", 12.0, lambda m: not m.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED)
    assert hb is not None, "did not land and disarm"
    pos = fresh(gcs, "LOCAL_POSITION_NED")
    assert abs(pos.z) < 0.05


def test_offboard_loss_failsafe_lands(fast_sitl):
    gcs = connect(fast_sitl)
    hover = load_airframe("qdrone").hover_thrust
    pos, _ = _offboard_torque_climb(gcs, 1.3 * hover, 0.8)
    assert pos.z < -0.3
    # stop streaming: failsafe within COM_OF_LOSS_T (0.5 s simulated)
    st = wait(gcs, "STATUSTEXT", 3.0, lambda m: "ailsafe" in m.text)
    assert st is not None and st.severity <= M.MAV_SEVERITY_WARNING
    hb = wait(gcs, "HEARTBEAT", 2.0, lambda m: (m.custom_mode >> 16) & 0xFF == LAND_MAIN)
    assert hb is not None
    hb = wait(gcs, "HEARTBEAT", 15.0, lambda m: not m.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED)
    assert hb is not None, "did not land and disarm after the failsafe"
    att = fresh(gcs, "ATTITUDE")
    assert abs(att.roll) < 0.05 and abs(att.pitch) < 0.05


def test_attitude_target_is_tracked_by_onboard_cascade(fast_sitl):
    gcs = connect(fast_sitl)
    hover = load_airframe("qdrone").hover_thrust
    roll = 0.1
    q = [math.cos(roll / 2), math.sin(roll / 2), 0.0, 0.0]

    def send(thrust, quat):
        gcs.mav.set_attitude_target_send(0, 1, 1, 0b00000111, quat, 0.0, 0.0, 0.0, thrust)

    for _ in range(10):
        send(hover, [1.0, 0.0, 0.0, 0.0])
        time.sleep(0.01)
    assert command(gcs, M.MAV_CMD_DO_SET_MODE, M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                   OFFBOARD) == M.MAV_RESULT_ACCEPTED
    assert command(gcs, M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
    end = time.monotonic() + 1.5
    while time.monotonic() < end:
        send(1.25 * hover, [1.0, 0.0, 0.0, 0.0] if time.monotonic() < end - 1.0 else q)
        time.sleep(0.01)
    att = fresh(gcs, "ATTITUDE")
    assert att.roll == pytest.approx(roll, abs=0.03)
    command(gcs, M.MAV_CMD_NAV_LAND)


def test_timesync_is_answered_at_once_and_times_the_link():
    """TIMESYNC answered from the vehicle clock: the tool times the link with it, and a
    random vehicle with its link delay each way shows twice that as the round trip."""
    from mrft_gcs.link import VehicleLink, measure_link
    from mrft_gcs.link.quality import timesync_rtts
    from mrft_gcs.sitl.population import random_airframe

    with SitlProcess(vehicle="qdrone", port=None) as sitl:
        with VehicleLink.connect(sitl.connection_string) as link:
            quick, lost = timesync_rtts(link, pings=10)
            assert measure_link(link).rtt_method == "TIMESYNC"
    assert lost == 0 and max(quick) < 20.0
    delay_ms = random_airframe(4).link_delay_s * 1e3  # 6.1 ms each way
    with SitlProcess(port=None, random_seed=4) as sitl:
        with VehicleLink.connect(sitl.connection_string) as link:
            slow, _ = timesync_rtts(link, pings=10)
    assert 2 * delay_ms - 1.0 < min(slow) < 2 * delay_ms + 8.0


def test_attitude_target_is_reported_when_asked(fast_sitl):
    """ATTITUDE_TARGET (the set point the attitude loop tracks) streams once asked for, with
    the vehicle clock, as PX4 and ArduPilot send it."""
    from mrft_gcs.link import VehicleLink
    from mrft_gcs.telemetry import AttitudeSetpoint

    with VehicleLink.connect(fast_sitl.connection_string) as link:
        with link.subscribe(AttitudeSetpoint) as sub:
            assert sub.get(0.3) is None  # off by default
            link.request_message_interval(83, 100.0)
            got = [sub.get(1.0) for _ in range(20)]
    assert all(isinstance(g, AttitudeSetpoint) for g in got)
    assert got[-1].t_s > got[0].t_s and abs(got[-1].roll_rad) < 1e-6
