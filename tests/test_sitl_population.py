"""Random vehicles: deterministic per seed, spread over the ranges, physically sensible, and
served over real UDP by the SITL process and ``mrft-tune sitl --random``."""

from __future__ import annotations

import math
import os
import signal
import statistics
import time

import numpy as np
import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402
from sitl_cli import start_sitl_cli

from mrft_gcs.cli import main  # noqa: E402
from mrft_gcs.errors import UsageError  # noqa: E402
from mrft_gcs.sitl import (  # noqa: E402
    SimVehicle,
    SitlProcess,
    available_vehicles,
    domain_check,
    load_airframe,
    random_airframe,
)
from mrft_gcs.sitl.airframe import GRAVITY_M_S2  # noqa: E402
from mrft_gcs.sitl.onboard import FlightMode, sqrt_controller  # noqa: E402
from mrft_gcs.sitl.population import LOOP_RATES_HZ  # noqa: E402
from mrft_gcs.sitl.process import free_udp_port  # noqa: E402

M = mavutil.mavlink
POPULATION = [random_airframe(s) for s in range(300)]


def test_same_seed_same_vehicle_other_seed_other_vehicle():
    assert random_airframe(11) == random_airframe(11)
    assert random_airframe(11) != random_airframe(12)
    assert random_airframe(11).name == "random-11"
    assert len({a.mass_kg for a in POPULATION}) == len(POPULATION)


@pytest.mark.parametrize("bad", [-1, 1.5, "3", True])
def test_bad_seed_is_usage_error(bad):
    with pytest.raises(UsageError, match="seed"):
        random_airframe(bad)


def test_population_covers_the_ranges_and_both_cascades():
    def spread(values, lo, hi):
        v = np.asarray(values)
        return v.min() >= lo and v.max() <= hi and np.percentile(v, 5) < lo + 0.15 * (hi - lo) \
            and np.percentile(v, 95) > hi - 0.15 * (hi - lo)

    assert spread([math.log(a.mass_kg) for a in POPULATION], math.log(0.03), math.log(3.0))
    assert spread([a.thrust_to_weight for a in POPULATION], 1.8, 6.0)
    assert spread([a.telemetry_max_hz for a in POPULATION], 50, 500)
    taus = [a.motor_tau_s for a in POPULATION]
    assert min(taus) < 0.013 and max(taus) > 0.07 and min(taus) >= 0.01 and max(taus) <= 0.08
    assert {a.onboard.loop_hz for a in POPULATION} == set(LOOP_RATES_HZ)
    assert {a.onboard.style for a in POPULATION} == {"px4", "ardupilot"}
    assert {a.frame for a in POPULATION} == {"quad_x", "hexa_x"}
    effects = {name for a in POPULATION for name in a.effects.active()}
    assert len(effects) >= 5
    cats = [domain_check(a).category for a in POPULATION]
    for c in ("in-domain", "out-of-domain", "hidden-effect"):
        assert 0.1 < cats.count(c) / len(cats) < 0.7, (c, cats.count(c))
    hover = [a.hover_estimate_factor for a in POPULATION]
    assert min(hover) < 0.85 and max(hover) > 1.2
    # the delay splits differently: each part is the largest of the attitude loop's sometimes
    assert any(a.actuator_delay_s > 2 * a.attitude_sensor_delay_s for a in POPULATION)
    assert any(a.attitude_sensor_delay_s > 2 * a.actuator_delay_s for a in POPULATION)
    assert any(a.link_delay_s > a.actuator_delay_s + a.attitude_sensor_delay_s
               for a in POPULATION)


def test_every_vehicle_is_physically_sensible():
    for a in POPULATION:
        a.validate()
        ix, iy, iz = a.inertia_kg_m2
        # inertia from mass and arm: between the motors alone and a solid disc
        assert 0.15 * a.mass_kg * a.arm_length_m ** 2 < ix < 0.5 * a.mass_kg * a.arm_length_m ** 2
        assert 0.8 * iy < ix < 1.25 * iy and max(ix, iy) < iz < ix + iy
        assert 0.04 < a.arm_length_m < 0.4
        assert 0.0 < a.hover_thrust < 0.6
        assert a.position_sensor_delay_s > a.attitude_sensor_delay_s
        assert all(abs(b) < 0.05 for b in a.torque_bias)  # CoM a few % of the arm off
        assert a.onboard.position_loop_hz >= 50 and a.onboard.position_loop_hz <= a.onboard.loop_hz
        for model in a.linear_models().values():
            assert all(v > 0 and math.isfinite(v) for v in model.values())
        # the hover the autopilot believes is the true one times its misestimate
        v = SimVehicle(a)
        believed = v.autopilot.params["MPC_THR_HOVER"]
        assert abs(believed - np.clip(a.hover_thrust * a.hover_estimate_factor, 0.1, 0.8)) < 0.006


def test_bundled_vehicles_are_in_domain_and_unchanged_onboard():
    for name in available_vehicles():
        af = load_airframe(name)
        assert domain_check(af).category == "in-domain", (name, domain_check(af).reasons)
        assert af.onboard.loop_hz == 1000.0 and af.link_delay_s == 0.0
        assert SimVehicle(af).control_every == 1


def test_onboard_loop_runs_at_its_rate_and_holds_the_command():
    # at 250 Hz the autopilot runs on every 4th physics step
    af = next(a for a in POPULATION if a.onboard.loop_hz == 250.0)
    v = SimVehicle(af)
    assert v.control_every == 4 and v.autopilot.dt == pytest.approx(0.004)
    ap = v.autopilot
    ap.set_attitude_target((math.cos(0.05), math.sin(0.05), 0.0, 0.0), 0.0)
    assert ap.set_mode(FlightMode.OFFBOARD).name == "ACCEPTED"
    ap.arm(True)
    cmds = []
    for _ in range(40):
        ap.set_attitude_target((math.cos(0.05), math.sin(0.05), 0.0, 0.0), 0.0)
        v.step()
        cmds.append(v._cmd)
    changes = [i for i in range(1, len(cmds)) if cmds[i] != cmds[i - 1]]
    assert changes and all(i % 4 == 0 for i in changes)


def test_sqrt_controller_is_linear_near_zero_and_limited_beyond():
    assert sqrt_controller(0.01, 8.0, 20.0, 0.0) == pytest.approx(0.08)
    big = sqrt_controller(1.0, 8.0, 20.0, 0.0)
    assert big == pytest.approx(math.sqrt(2 * 20.0 * (1.0 - 0.5 * 20.0 / 64.0)))
    assert sqrt_controller(-1.0, 8.0, 20.0, 0.0) == pytest.approx(-big)
    assert sqrt_controller(0.01, 0.0, 20.0, 0.0) == pytest.approx(math.sqrt(0.4))
    assert sqrt_controller(0.001, 100.0, 0.0, 0.0025) == pytest.approx(0.1)  # |e|/dt caps it


def test_ardupilot_like_vehicle_hovers_on_its_attitude_loop():
    """The ArduPilot-like cascade (square root, target filter, D on error) holds level."""
    af = next(a for a in POPULATION if a.onboard.style == "ardupilot"
              and domain_check(a).category == "in-domain" and a.thrust_to_weight < 4)
    v = SimVehicle(af.quiet())
    v.reset(position_ned=(0.0, 0.0, -2.0), airborne=True)
    ap = v.autopilot
    prm = ap.params
    # a modest PD on the onboard loops: Kd from the roll model, angle P a fifth of its corner
    m = af.linear_models()["roll"]
    kd = 0.3 / (m["K"] * (m["T_prop"] + m["tau"] + 0.004))
    for ax in ("ROLL", "PITCH"):
        prm.set(f"MC_{ax}RATE_P", kd)
        prm.set(f"MC_{ax}RATE_I", 0.0)
        prm.set(f"MC_{ax}RATE_D", 0.0)
        prm.set(f"MC_{ax}_P", 0.2 / (m["T_prop"] + m["tau"] + 0.004))
    ap.set_attitude_target((1.0, 0.0, 0.0, 0.0), af.hover_thrust)
    ap.set_mode(FlightMode.OFFBOARD)
    ap.arm(True)
    worst = 0.0
    for _ in range(1500):
        ap.set_attitude_target((1.0, 0.0, 0.0, 0.0), af.hover_thrust)
        v.step()
        r, p, _ = v.physics.euler
        worst = max(worst, abs(r), abs(p))
    assert worst < math.radians(2.0), math.degrees(worst)


def test_random_vehicle_over_udp_has_its_link_delay_and_telemetry_rate():
    af = random_airframe(8)  # 51 Hz telemetry, 8 ms each way
    assert af.telemetry_max_hz < 100 and af.link_delay_s > 0.007
    assert "telemetry" in " ".join(domain_check(af).reasons)
    with SitlProcess(random_seed=8, port=None) as sitl:
        gcs = mavutil.mavlink_connection(sitl.connection_string, source_system=255,
                                         source_component=190)
        try:
            assert gcs.recv_match(type="HEARTBEAT", blocking=True, timeout=10) is not None
            rtts = []
            for _ in range(5):
                t0 = time.monotonic()
                gcs.mav.command_long_send(1, 1, M.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                          M.MAVLINK_MSG_ID_ATTITUDE, 2000.0, 0, 0, 0, 0, 0)
                ack = gcs.recv_match(type="COMMAND_ACK", blocking=True, timeout=3)
                assert ack is not None and ack.result == M.MAV_RESULT_ACCEPTED
                rtts.append(time.monotonic() - t0)
            assert min(rtts) >= 2 * af.link_delay_s - 0.002, rtts  # both ways delayed
            stamps = []
            end = time.monotonic() + 1.5
            while time.monotonic() < end:
                m = gcs.recv_match(type="ATTITUDE", blocking=True, timeout=0.5)
                if m is not None:
                    stamps.append(m.time_boot_ms)
            steps = np.diff(stamps[5:])
            # asked 500 Hz; the vehicle streams at its own cap (vehicle clock, load-proof)
            assert statistics.median(steps) == pytest.approx(1000 / af.telemetry_max_hz, abs=1.5)
        finally:
            gcs.close()


def test_cli_random_serves_mavlink_and_stops_on_sigterm():
    port = free_udp_port()
    proc, text = start_sitl_cli("--random", "5", "--port", str(port))
    gcs = None
    try:
        assert "random-5" in text and "Table I domain:" in text, text
        assert domain_check(random_airframe(5)).category in text
        gcs = mavutil.mavlink_connection(f"udp:127.0.0.1:{port}", source_system=255)
        hb = gcs.recv_match(type="HEARTBEAT", blocking=True, timeout=10)
        assert hb is not None and hb.autopilot == M.MAV_AUTOPILOT_PX4
        gcs.mav.param_request_read_send(1, 1, b"MPC_THR_HOVER", -1)
        pv = gcs.recv_match(type="PARAM_VALUE", blocking=True, timeout=5)
        af = random_airframe(5)
        assert pv is not None
        assert pv.param_value == pytest.approx(
            round(af.hover_thrust * af.hover_estimate_factor, 2), abs=1e-6)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(10) == 0
    finally:
        if gcs is not None:
            gcs.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_cli_random_usage_errors(capsys):
    assert main(["sitl", "--random", "3", "--vehicle", "qdrone"]) == 2
    assert "not both" in capsys.readouterr().err
    assert main(["sitl", "--random", "-4"]) == 2
    assert "seed" in capsys.readouterr().err


def test_weight_is_carried_at_the_believed_hover_only_with_the_integrator():
    """A misestimated hover thrust is a real bias: the vehicle sinks or climbs on it."""
    af = next(a for a in POPULATION if a.hover_estimate_factor < 0.85 and not a.effects.active())
    v = SimVehicle(af.quiet())
    v.reset(position_ned=(0.0, 0.0, -2.0), airborne=True)
    ap = v.autopilot
    believed = ap.params["MPC_THR_HOVER"]
    ap.set_actuator_controls(0.0, 0.0, 0.0, believed)
    ap.set_mode(FlightMode.OFFBOARD)
    ap.arm(True)
    for _ in range(300):
        ap.set_actuator_controls(0.0, 0.0, 0.0, believed)
        v.step()
    assert v.physics.vel[2] > 0.05  # NED: sinking
    assert believed * af.thrust_to_weight * GRAVITY_M_S2 < GRAVITY_M_S2
