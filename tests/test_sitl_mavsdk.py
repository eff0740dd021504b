"""Independent client check: MAVSDK (C++ library behind PyPI ``mavsdk`` 4.x) flies the SITL."""

from __future__ import annotations

import math
import time

import pytest

from mrft_gcs.sitl import SitlProcess

mavsdk = pytest.importorskip("mavsdk")


def _until(fn, timeout=5.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = fn()
        if value:
            return value
        time.sleep(0.05)
    return None


def test_mavsdk_reads_telemetry_sets_param_and_flies_offboard_attitude():
    from mavsdk import ComponentType, Configuration, Mavsdk
    from mavsdk.plugins.action import Action
    from mavsdk.plugins.offboard import Attitude, Offboard
    from mavsdk.plugins.param import Param
    from mavsdk.plugins.telemetry import Telemetry

    with SitlProcess(vehicle="qdrone", port=None) as sitl:
        sdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
        sdk.add_any_connection(sitl.mavsdk_address)
        system = sdk.first_autopilot(10.0)
        assert system is not None
        tel, param = Telemetry(system), Param(system)

        euler = _until(lambda: (lambda e: e if not math.isnan(e.roll_deg) else None)(
            tel.attitude_euler()))
        assert euler is not None and abs(euler.roll_deg) < 1.0 and abs(euler.pitch_deg) < 1.0

        assert param.get_param_float("MC_ROLL_P") == pytest.approx(6.5)
        param.set_param_float("MC_ROLL_P", 5.5)
        assert param.get_param_float("MC_ROLL_P") == pytest.approx(5.5)

        off, action = Offboard(system), Action(system)
        off.set_attitude(Attitude(0.0, 0.0, 0.0, 0.45))
        action.arm()
        assert _until(tel.armed, 3.0)
        off.start()
        end = time.monotonic() + 1.5
        while time.monotonic() < end:
            off.set_attitude(Attitude(0.0, 0.0, 0.0, 0.6))
            time.sleep(0.05)
        pv = tel.position_velocity_ned()
        assert pv.position.down_m < -0.5, pv
        assert off.is_active()
        action.land()
        assert _until(lambda: tel.position_velocity_ned().velocity.down_m_s > 0.2, 3.0)
