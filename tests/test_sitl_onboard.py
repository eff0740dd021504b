"""Onboard software: the cascades are exactly the PD the tuner writes; modes; failsafes."""

from __future__ import annotations

import math

import pytest

from mrft_gcs.errors import UsageError
from mrft_gcs.sitl import CommandResult, FlightMode, SimVehicle, available_vehicles, load_airframe
from mrft_gcs.sitl.onboard import Autopilot

DT = 0.001


def _pd_autopilot(kc: float, kd: float) -> Autopilot:
    ap = Autopilot(DT)
    for axis in ("ROLL", "PITCH"):
        assert ap.params.set(f"MC_{axis}_P", kc / kd)
        assert ap.params.set(f"MC_{axis}RATE_P", kd)
        assert ap.params.set(f"MC_{axis}RATE_I", 0.0)
        assert ap.params.set(f"MC_{axis}RATE_D", 0.0)
        assert ap.params.set(f"MC_{axis}RATE_K", 1.0)
    return ap


@pytest.mark.parametrize("e,w", [(0.02, 0.0), (0.0, 0.3), (-0.03, 0.5), (0.01, -0.2)])
def test_attitude_cascade_is_the_written_pd(e, w):
    """u = Kc e - Kd w with MC_ROLL_P = Kc/Kd, MC_ROLLRATE_P = Kd, I = D = 0, K = 1."""
    kc, kd = 1.7, 0.15
    ap = _pd_autopilot(kc, kd)
    ap.landed = False
    half = e / 2
    q_sp = (math.cos(half), math.sin(half), 0.0, 0.0)  # roll setpoint e, vehicle level
    att = (0.0, 0.0, 0.0, w, 0.0, 0.0, 0.0, 0.0, -9.8)
    u = ap._attitude(q_sp, att)
    assert u[0] == pytest.approx(kc * e - kd * w, rel=1e-6, abs=1e-9)
    q_sp = (math.cos(half), 0.0, math.sin(half), 0.0)
    att = (0.0, 0.0, 0.0, 0.0, w, 0.0, 0.0, 0.0, -9.8)
    assert ap._attitude(q_sp, att)[1] == pytest.approx(kc * e - kd * w, rel=1e-6, abs=1e-9)


def test_position_cascade_structure_and_signs():
    """vel_sp = MPC_XY_P e; acc = P_ACC (vel_sp - vel); tilt = acc / g; thrust = hover (1 + a/g)."""
    ap = Autopilot(DT, hover_thrust=0.45)
    for name, val in (("MPC_XY_VEL_I_ACC", 0.0), ("MPC_XY_VEL_D_ACC", 0.0),
                      ("MPC_Z_VEL_I_ACC", 0.0), ("MPC_Z_VEL_D_ACC", 0.0),
                      ("MPC_XY_P", 1.0), ("MPC_XY_VEL_P_ACC", 2.0), ("MPC_Z_P", 1.0),
                      ("MPC_Z_VEL_P_ACC", 3.0)):
        assert ap.params.set(name, val)
    assert ap.params["MPC_THR_HOVER"] == 0.45
    ap.landed = False
    ap._hold_pos, ap._hold_yaw = (0.1, 0.0, 2.1), 0.0  # 0.1 m north, 0.1 m up of the vehicle
    captured = {}

    def fake_attitude(q_sp, att):
        captured["q"] = q_sp
        return (0.0, 0.0, 0.0)

    ap._attitude = fake_attitude
    out = ap._position(FlightMode.POSCTL, (0.0,) * 9, (0.0, 0.0, -2.0, 0.0, 0.0, 0.0))
    acc_n = 2.0 * (1.0 * 0.1)
    w, x, y, z = captured["q"]
    pitch = math.asin(2 * (w * y - z * x))
    assert pitch == pytest.approx(-acc_n / 9.80665, rel=1e-6)  # nose down to go north
    assert out[3] == pytest.approx(0.45 * (1 + 3.0 * 0.1 / 9.80665), rel=1e-6)


def test_params_reject_unknown_nan_and_out_of_range():
    ap = Autopilot(DT)
    before = ap.params["MC_ROLL_P"]
    assert not ap.params.set("MC_ROLL_P", float("nan"))
    assert not ap.params.set("MC_ROLL_P", -1.0)
    assert not ap.params.set("NO_SUCH_PARAM", 1.0)
    assert ap.params["MC_ROLL_P"] == before
    assert "NO_SUCH_PARAM" not in ap.params


def test_custom_mode_encoding_is_px4():
    assert FlightMode.OFFBOARD.custom_mode == 6 << 16
    assert FlightMode.POSCTL.custom_mode == 3 << 16
    assert FlightMode.AUTO_LAND.custom_mode == (4 << 16) | (6 << 24)
    assert FlightMode.from_px4(4, 6) is FlightMode.AUTO_LAND
    assert FlightMode.from_px4(9) is None


def _airborne(name="qdrone"):
    v = SimVehicle(load_airframe(name))
    v.reset((0.0, 0.0, -3.0), airborne=True)
    v.step()
    return v


def test_offboard_needs_setpoints_and_falls_back_to_land():
    v = _airborne()
    ap = v.autopilot
    assert ap.set_mode(FlightMode.OFFBOARD) is CommandResult.DENIED
    assert ap.set_actuator_controls(0.0, 0.0, 0.0, v.airframe.hover_thrust)
    assert ap.arm(True) is CommandResult.ACCEPTED
    assert ap.set_mode(FlightMode.OFFBOARD) is CommandResult.ACCEPTED
    v.run(0.4)
    assert ap.mode is FlightMode.OFFBOARD
    v.run(0.2)  # 0.6 s without a new setpoint
    assert ap.mode is FlightMode.AUTO_LAND
    texts = [e.text for e in ap.drain_events()]
    assert any("Failsafe" in t for t in texts)
    v.run(8.0)
    assert v.physics.on_ground and not ap.armed
    assert abs(v.physics.euler[0]) < 1e-6


def test_rejects_nan_and_non_unit_setpoints():
    ap = Autopilot(DT)
    assert not ap.set_actuator_controls(0.0, float("nan"), 0.0, 0.5)
    assert not ap.set_actuator_controls(0.0, 0.0, 0.0, 1.5)
    assert not ap.set_attitude_target((1.0, 0.0, 0.0, 0.0), float("nan"))
    assert not ap.set_attitude_target((2.0, 0.0, 0.0, 0.0), 0.5)
    assert ap.set_attitude_target((1.0, 0.0, 0.0, 0.0), 0.5)


@pytest.mark.parametrize("name", ["qdrone", "racer250", "f550"])
def test_posctl_holds_with_default_gains(name):
    v = _airborne(name)
    ap = v.autopilot
    ap.arm(True)
    assert ap.set_mode(FlightMode.POSCTL) is CommandResult.ACCEPTED
    v.run(4.0)
    assert abs(v.physics.pos[2] + 3.0) < 0.1
    assert max(abs(v.physics.pos[0]), abs(v.physics.pos[1])) < 0.05


def test_no_disarm_in_air_unless_forced():
    v = _airborne()
    ap = v.autopilot
    ap.arm(True)
    ap.set_mode(FlightMode.POSCTL)
    v.run(0.1)
    assert ap.arm(False) is CommandResult.DENIED
    assert ap.arm(False, force=True) is CommandResult.ACCEPTED


def test_unknown_vehicle_lists_available():
    with pytest.raises(UsageError) as info:
        load_airframe("no_such_vehicle")
    for name in ("qdrone", "racer250", "f550"):
        assert name in str(info.value)
    assert {"qdrone", "racer250", "f550"} <= set(available_vehicles())


def test_profile_typo_is_usage_error(tmp_path):
    src = (load_airframe("qdrone"), )
    text = (tmp_path / "x.toml")
    from mrft_gcs.sitl.airframe import vehicles_dir

    body = (vehicles_dir() / "qdrone.toml").read_text().replace("mass_kg", "mass_kgs")
    text.write_text(body)
    with pytest.raises(UsageError, match="mass_kgs"):
        load_airframe(text)
    assert src[0].frame == "quad_x"


def test_profile_loads_effects_from_file(tmp_path):
    from mrft_gcs.sitl.airframe import vehicles_dir

    body = (vehicles_dir() / "f550.toml").read_text()
    body = body.replace("[effects]", "[effects]\nsensor_lpf = 30.0")
    p = tmp_path / "f550_lpf.toml"
    p.write_text(body)
    af = load_airframe(p)
    assert af.n_motors == 6 and af.effects.active() == {"sensor_lpf": 30.0}
    assert af.with_effects({"sensor_lpf": 20.0}).effects.sensor_lpf == 20.0  # command line wins
