"""Bad input never stops the SITL; MAVLink 2 signing gates commands and setpoints."""

from __future__ import annotations

import math
import os
import time

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402

from mrft_gcs.sitl import SitlProcess  # noqa: E402

M = mavutil.mavlink


def connect(sitl, **kw):
    gcs = mavutil.mavlink_connection(sitl.connection_string, source_system=255,
                                     source_component=190, **kw)
    assert gcs.recv_match(type="HEARTBEAT", blocking=True, timeout=10) is not None
    return gcs


def wait(gcs, kind, timeout, cond=lambda m: True):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        msg = gcs.recv_match(type=kind, blocking=True, timeout=max(0.01, end - time.monotonic()))
        if msg is not None and cond(msg):
            return msg
    return None


def read_param(gcs, name, timeout=2.0):
    gcs.mav.param_request_read_send(1, 1, name.encode(), -1)
    pv = wait(gcs, "PARAM_VALUE", timeout, lambda m: m.param_id == name)
    return None if pv is None else pv.param_value


def test_garbage_truncated_and_out_of_range_input_is_ignored():
    with SitlProcess(vehicle="qdrone", port=None) as sitl:
        gcs = connect(sitl)
        sock, addr = gcs.port, next(iter(gcs.clients))
        frame = gcs.mav.param_set_encode(1, 1, b"MC_ROLL_P", 3.0, 9).pack(gcs.mav)
        bad_crc = bytearray(frame)
        bad_crc[-1] ^= 0xFF
        junk = [b"", b"\x00", os.urandom(300), b"\xfd" * 50, frame[:7], frame[:-3],
                bytes(bad_crc), b"\xfd\xff" + os.urandom(400), os.urandom(4000)]
        for _ in range(20):
            for j in junk:
                sock.sendto(j, addr)
        time.sleep(0.3)  # a UDP flood may overflow socket buffers: let the SITL drain it
        # out-of-range setpoints: NaN thrust, |q| != 1, torque > 1
        gcs.mav.set_attitude_target_send(0, 1, 1, 0, [2.0, 0.0, 0.0, 0.0], 0, 0, 0, 0.5)
        gcs.mav.set_attitude_target_send(0, 1, 1, 0, [1.0, 0.0, 0.0, 0.0], 0, 0, 0, math.nan)
        gcs.mav.set_actuator_control_target_send(0, 0, 1, 1, [math.nan, 0, 0, 0.5, 0, 0, 0, 0])
        gcs.mav.set_actuator_control_target_send(0, 0, 1, 1, [5.0, 0, 0, 0.5, 0, 0, 0, 0])
        gcs.mav.command_long_send(1, 1, M.MAV_CMD_DO_SET_MODE, 0, math.nan, math.inf, 0, 0, 0,
                                  0, 0)
        # none of them counts as a setpoint stream: OFFBOARD is still refused
        gcs.mav.command_long_send(1, 1, M.MAV_CMD_DO_SET_MODE, 0, 1, 6, 0, 0, 0, 0, 0)
        ack = wait(gcs, "COMMAND_ACK", 3.0,
                   lambda m: m.command == M.MAV_CMD_DO_SET_MODE and m.result != 4)
        assert ack is not None and ack.result == M.MAV_RESULT_DENIED
        assert sitl.running
        assert read_param(gcs, "MC_ROLL_P") == 6.5  # the truncated/bad-CRC PARAM_SETs did nothing
        assert wait(gcs, "HEARTBEAT", 3.0) is not None


KEY = bytes(range(32))


def test_signing_ignores_unsigned_commands():
    with SitlProcess(vehicle="qdrone", port=None, signing_key=KEY) as sitl:
        gcs = connect(sitl)
        gcs.mav.command_long_send(1, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        assert wait(gcs, "COMMAND_ACK", 1.0) is None
        gcs.mav.param_set_send(1, 1, b"MC_ROLL_P", 2.0, 9)
        assert read_param(gcs, "MC_ROLL_P", timeout=1.0) is None  # unsigned reads ignored too
        hb = wait(gcs, "HEARTBEAT", 2.0)
        assert not hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED

        gcs.setup_signing(KEY, sign_outgoing=True)
        assert read_param(gcs, "MC_ROLL_P") == 6.5  # the unsigned PARAM_SET was dropped
        gcs.mav.command_long_send(1, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        ack = wait(gcs, "COMMAND_ACK", 2.0)
        assert ack is not None and ack.result == M.MAV_RESULT_ACCEPTED


def test_signing_with_wrong_key_is_ignored():
    with SitlProcess(vehicle="qdrone", port=None, signing_key=KEY) as sitl:
        gcs = connect(sitl)
        gcs.setup_signing(bytes(32), sign_outgoing=True)
        gcs.mav.command_long_send(1, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        assert wait(gcs, "COMMAND_ACK", 1.0) is None
        assert sitl.running
