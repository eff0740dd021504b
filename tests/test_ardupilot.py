"""Knowing the autopilot (AUTOPILOT_VERSION, parameter names), timing the link with TIMESYNC,
refusing paths the firmware cannot carry, and the hover check that gates status ``ok``.

The live parts run over real UDP sockets: against the bundled SITL (which answers neither
AUTOPILOT_VERSION nor TIMESYNC: the fallbacks) and against a small ArduPilot-like MAVLink
peer that answers the way ArduCopter does (AUTOPILOT_VERSION on MAV_CMD_REQUEST_MESSAGE,
TIMESYNC at once, PARAM_REQUEST_READ only from a 10 Hz parameter stream). The real
ArduCopter SITL is exercised in tests/test_ardupilot_sitl.py when it is built.
"""

from __future__ import annotations

import socket
import threading
import time
import tomllib
from dataclasses import replace

import numpy as np
import pytest
from pymavlink import mavutil

from mrft_gcs.errors import LinkError, ParameterError, UsageError
from mrft_gcs.flight.api import tune
from mrft_gcs.flight.controllers import FlightState
from mrft_gcs.flight.hover import HoverLimits, check_hover, check_hover_states
from mrft_gcs.link import VehicleLink, measure_link, require_relay_capable
from mrft_gcs.link.firmware import (
    Firmware,
    decode_sw_version,
    detect_firmware,
    torque_path_refusal,
)
from mrft_gcs.link.quality import RTT_PARAM_READ, RTT_TIMESYNC
from mrft_gcs.loops import Loop
from mrft_gcs.plant import InnerModel
from mrft_gcs.profiles import (
    PROFILE_DIR,
    PDGains,
    ardupilot_altitude_cascade,
    fit_profile,
    gains_to_params,
    load_profile,
    parse_profile,
)
from mrft_gcs.telemetry import Attitude, AutopilotFamily, LocalPosition

OLD_NAMES = {n: 1.0 for n in load_profile("ardupilot").parameter_names()}
NEW_NAMES = {n: 1.0 for n in load_profile("ardupilot-ned").parameter_names()}


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _sw(major: int, minor: int, patch: int, kind: int) -> int:
    return (major << 24) | (minor << 16) | (patch << 8) | kind


# ---------------------------------------------------------------- firmware facts
@pytest.mark.parametrize("value, expected", [
    (_sw(4, 7, 0, 0), (4, 7, 0, "dev")),
    (_sw(4, 6, 2, 255), (4, 6, 2, "official")),
    (_sw(4, 3, 8, 192), (4, 3, 8, "rc")),
    (_sw(1, 14, 0, 255), (1, 14, 0, "official")),
    (_sw(1, 16, 0, 194), (1, 16, 0, "rc")),  # PX4 counts rc2 as 194
])
def test_flight_sw_version_decodes(value, expected):
    assert decode_sw_version(value) == expected


@pytest.mark.parametrize("family, version, refused", [
    (AutopilotFamily.ARDUPILOT, (4, 7, 0), True),
    (AutopilotFamily.ARDUPILOT, None, True),
    (AutopilotFamily.PX4, (1, 13, 3), False),
    (AutopilotFamily.PX4, (1, 14, 0), True),
    (AutopilotFamily.PX4, (1, 16, 0), True),
    (AutopilotFamily.PX4, None, False),  # not known: the bundled SITL serves torque as PX4 1.13
])
def test_torque_path_refused_where_firmware_has_no_torque_input(family, version, refused):
    why = torque_path_refusal(Firmware(family, 2, version, "official" if version else ""))
    assert (why is not None) == refused
    if refused:
        assert "SET_ACTUATOR_CONTROL_TARGET" in why


# ---------------------------------------------------------------- parameter names
def _fw(version):
    return Firmware(AutopilotFamily.ARDUPILOT, 2, version, "dev" if version else "")


@pytest.mark.parametrize("version", [(4, 7, 0), (4, 5, 7), None])
def test_profile_follows_the_names_the_vehicle_has(version):
    asked: list[str] = []

    def has(names):
        return lambda n: asked.append(n) or n in names

    prof, note = fit_profile(load_profile("ardupilot"), _fw(version), has(OLD_NAMES))
    assert prof.name == "ardupilot" and "PSC_POSZ_P" in note
    prof, note = fit_profile(load_profile("ardupilot"), _fw(version), has(NEW_NAMES))
    assert prof.name == "ardupilot-ned"
    assert "instead of ardupilot" in note and "PSC_D_POS_P" in note
    assert set(prof.parameter_names()) <= set(NEW_NAMES)


def test_profile_for_another_autopilot_or_with_no_matching_names_is_refused():
    with pytest.raises(UsageError, match="ArduCopter 4.7.0-dev .* profile px4 .* --profile "
                                         "ardupilot"):
        fit_profile(load_profile("px4"), _fw((4, 7, 0)), lambda n: True)
    with pytest.raises(ParameterError, match="PSC_POSZ_P .ardupilot.*PSC_D_POS_P"):
        fit_profile(load_profile("ardupilot"), _fw((4, 7, 0)), lambda n: False)


def test_metre_based_acceleration_gain_gives_the_same_climb_rate_gain():
    gains = {Loop.ALTITUDE: PDGains(Kc=0.5, Kd=0.2)}
    old = gains_to_params(load_profile("ardupilot"), gains, 0.4)
    new = gains_to_params(load_profile("ardupilot-ned"), gains, 0.4)
    assert new["PSC_D_ACC_P"] == pytest.approx(0.1 * old["PSC_ACCZ_P"])
    assert new["PSC_D_VEL_P"] == pytest.approx(old["PSC_VELZ_P"])
    assert new["PSC_D_POS_P"] == pytest.approx(old["PSC_POSZ_P"])


def test_altitude_mapping_not_written_when_a_profile_says_so_and_refused_when_asked(tmp_path):
    assert not load_profile("ardupilot").altitude.not_written  # proven in LOITER (profile)
    prof = load_profile("ardupilot")
    prof = replace(prof, altitude=replace(prof.altitude, not_written="not proven here"))
    with pytest.raises(UsageError, match="altitude cannot be written with profile ardupilot: "
                                         "not proven here"):
        tune("udp:127.0.0.1:9", prof, loops=["altitude", "x"], backup_dir=tmp_path)


# ArduCopter SITL's altitude through the 2 Hz throttle filter (PILOT_THR_FILT 2, baro noise
# 0.2 m) as the relay identified it, with its PD; and what the relay found without the filter
SITL_ALT = (InnerModel(K=12.92, T_prop=0.1529, T1=0.3139, tau=0.00203),
            PDGains(Kc=2.9915, Kd=0.65085))
UNFILTERED = (InnerModel(K=2.926, T_prop=0.00548, T1=0.0949, tau=0.00457),
              PDGains(Kc=134.7, Kd=3.28))


def _arducopter_loop(m: InnerModel, w: float, pos_p: float, vel_p: float, acc_p: float,
                     acc_i: float, hz_acc: float, hz_vel: float, hz_imu: float) -> complex:
    """AC_PosControl::update_U_controller as a loop at w rad/s, in cm and cm/s^2 as it runs:
    vel_target = POSZ_P e; accel_target [cm/s^2] = VELZ_P lpf(vel_target - v) [cm/s];
    throttle = 0.001 (ACCZ_P + ACCZ_I/s) lpf(accel_target - accel_measured) [cm/s^2]."""
    s = 1j * w

    def lpf(hz):
        return 1 / (1 + s / (2 * np.pi * hz))

    plant = m.K * np.exp(-m.tau * s) / (s * (m.T_prop * s + 1) * (m.T1 * s + 1))  # m/unit
    z_cm = 100 * plant  # cm per unit throttle
    accel_target = vel_p * lpf(hz_vel) * (pos_p * -z_cm - s * z_cm)  # for a unit throttle
    error = accel_target - s * s * z_cm * lpf(hz_imu)
    return -0.001 * (acc_p + acc_i / s) * lpf(hz_acc) * error  # loop = -(throttle back)


def test_altitude_cascade_equals_the_pd_at_its_crossover():
    model, gains = SITL_ALT
    prof = load_profile("ardupilot")
    out = gains_to_params(prof, {Loop.ALTITUDE: gains}, 0.39, {Loop.ALTITUDE: model})
    cas = ardupilot_altitude_cascade(model, gains, prof.altitude)
    w = cas.crossover_rad_s
    s = 1j * w
    pd = model.K * np.exp(-model.tau * s) / (s * (model.T_prop * s + 1) * (model.T1 * s + 1)) \
        * (gains.Kc + gains.Kd * s)
    assert abs(pd) == pytest.approx(1.0, abs=0.01)
    onboard = _arducopter_loop(model, w, out["PSC_POSZ_P"], out["PSC_VELZ_P"],
                               out["PSC_ACCZ_P"], out["PSC_ACCZ_I"], out["PSC_ACCZ_FLTE"],
                               out["PSC_VELZ_FLTE"], 20.0)
    assert onboard == pytest.approx(pd, rel=1e-6)
    assert cas.cascade_margin_deg == pytest.approx(cas.pd_margin_deg, abs=0.5)
    assert 10 < cas.pd_margin_deg < 60 and cas.cascade_gain_margin > 3
    assert cas.low_gain_ratio > 1  # ACCZ_I: more low-frequency gain than the PD
    # in ArduPilot's documented range neighbourhood, not the 61 / 227 of the fast-loop mapping
    assert 2 < out["PSC_POSZ_P"] < 15 and 5 < out["PSC_VELZ_P"] < 40
    assert {out[n] for n in ("PSC_VELZ_I", "PSC_VELZ_D")} == {0.0}
    # the metre-based names: the same gains, the acceleration loop's P and I x 0.1
    ned = gains_to_params(load_profile("ardupilot-ned"), {Loop.ALTITUDE: gains}, 0.39,
                          {Loop.ALTITUDE: model})
    assert ned["PSC_D_POS_P"] == pytest.approx(out["PSC_POSZ_P"])
    assert ned["PSC_D_VEL_P"] == pytest.approx(out["PSC_VELZ_P"])
    assert ned["PSC_D_ACC_P"] == pytest.approx(0.1 * out["PSC_ACCZ_P"])
    assert ned["PSC_D_ACC_I"] == pytest.approx(0.1 * out["PSC_ACCZ_I"])


def test_altitude_pd_beyond_the_acceleration_loop_is_refused():
    """The 0.08 s cycles of a relay flown without the throttle filter design a PD crossing
    over near 100 rad/s: no positive POSZ_P / VELZ_P reach it through ArduCopter's loop."""
    model, gains = UNFILTERED
    with pytest.raises(UsageError, match="no positive PSC_POSZ_P / PSC_VELZ_P"):
        gains_to_params(load_profile("ardupilot"), {Loop.ALTITUDE: gains}, 0.39,
                        {Loop.ALTITUDE: model})


def test_test_params_are_parsed_and_checked():
    assert load_profile("ardupilot").test_params == {"PILOT_THR_FILT": 2.0}
    assert load_profile("px4").test_params == {}
    data = tomllib.loads((PROFILE_DIR / "ardupilot.toml").read_text())
    for bad in ({"PILOT_THR_FILT": "2"}, {"BAD NAME": 1.0}, {"X": float("nan")}):
        with pytest.raises(UsageError, match="test_params"):
            parse_profile({**data, "test_params": bad})


# ---------------------------------------------------------------- hover check
def _window(n=100, height=1.0, wobble_m=0.0, tilt_rad=0.0, vz=0.0):
    t = np.arange(n) * 0.02
    xyz = np.column_stack([wobble_m * np.sin(t * 3), np.zeros(n), np.full(n, height)])
    return (t, xyz, np.full(n, vz), np.full(n, tilt_rad), np.zeros(n))


def test_hover_check_passes_a_steady_hover_and_fails_ground_and_swinging():
    assert check_hover(*_window(), ground_z_up_m=0.0).passed
    ground = check_hover(*_window(height=0.02), ground_z_up_m=0.0)
    assert not ground.airborne and "not airborne" in ground.reason
    # the reported run: hit the ground in the hand-over, 2.9 m off and 28.5 deg of tilt
    hit = check_hover(*_window(height=0.4, wobble_m=2.9, tilt_rad=np.radians(28.5)), 0.0)
    assert not hit.steady and "2.90 m" in hit.reason and "28.5 deg" in hit.reason
    falling = check_hover(*_window(vz=-1.0), ground_z_up_m=0.0)
    assert not falling.passed and "vertical speed" in falling.reason
    assert not check_hover(*_window(n=3), ground_z_up_m=0.0).passed


def test_hover_check_fails_on_samples_recorded_from_a_vehicle_on_the_ground():
    sitl = pytest.importorskip("mrft_gcs.sitl")
    port = _free_udp_port()
    with sitl.SitlProcess(vehicle="qdrone", port=port, speedup=1.0, seed=0), \
            VehicleLink.connect(f"udp:127.0.0.1:{port}") as link:
        link.request_message_interval("ATTITUDE", 50)
        link.request_message_interval("LOCAL_POSITION_NED", 50)
        att = pos = None
        states = []
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            s = link.next_sample(0.1)
            att = s if isinstance(s, Attitude) else att
            pos = s if isinstance(s, LocalPosition) else pos
            if att is not None and pos is not None:
                states.append(FlightState(att.t_s, att.roll_rad, att.pitch_rad, att.yaw_rad,
                                          0, 0, 0, pos.t_s, pos.x_m, pos.y_m, -pos.z_m,
                                          pos.vx_m_s, pos.vy_m_s, -pos.vz_m_s))
    assert len(states) > 20
    result = check_hover_states(states, ground_z_up_m=states[0].z_up_m)
    assert result.steady and not result.airborne and not result.passed, result
    # the same samples, judged as if the take-off point had been 1 m lower, pass
    assert check_hover_states(states, states[0].z_up_m - 1.0, HoverLimits()).passed


# ---------------------------------------------------------------- the bundled SITL
def test_bundled_sitl_is_known_as_px4_and_timed():
    sitl = pytest.importorskip("mrft_gcs.sitl")
    port = _free_udp_port()
    with sitl.SitlProcess(vehicle="qdrone", port=port, speedup=1.0, seed=0), \
            VehicleLink.connect(f"udp:127.0.0.1:{port}") as link:
        fw = detect_firmware(link)
        # it answers AUTOPILOT_VERSION as a PX4 1.13 (the last with the torque path)
        assert fw.family is AutopilotFamily.PX4 and fw.version == (1, 13, 0), fw
        assert fw.source == "AUTOPILOT_VERSION"
        assert torque_path_refusal(fw) is None  # its torque path is the point of the SITL
        q = measure_link(link, rate_hz=250.0, window_s=0.5)
        assert q.rtt_method == RTT_TIMESYNC and q.rtt_lost == 0, q.line()
        require_relay_capable(q)


# ---------------------------------------------------------------- an ArduCopter-like peer
class ArduCopterLike(threading.Thread):
    """Answers as ArduCopter does: HEARTBEAT as MAV_AUTOPILOT_ARDUPILOTMEGA quad,
    AUTOPILOT_VERSION 4.7.0-dev on request, TIMESYNC at once, PARAM_REQUEST_READ only
    from a 10 Hz parameter stream, ATTITUDE and LOCAL_POSITION_NED at 250 Hz."""

    def __init__(self, port: int, params: dict[str, float], timesync: bool = True) -> None:
        super().__init__(daemon=True)
        self.conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1,
                                               source_component=1)
        self.params = params
        self.timesync = timesync
        self.commands: list[int] = []
        self.stop = threading.Event()

    def run(self) -> None:
        mav, names = self.conn.mav, list(self.params)
        pending: list[str] = []
        next_beat = next_param = next_tm = 0.0
        t0 = time.monotonic()
        while not self.stop.is_set():
            now = time.monotonic()
            boot_ms = int((now - t0) * 1000)
            if now >= next_beat:
                next_beat = now + 0.2
                mav.heartbeat_send(2, 3, 81, 0, 3)
            if now >= next_tm:
                next_tm = now + 0.004
                mav.attitude_send(boot_ms, 0, 0, 0, 0, 0, 0)
                mav.local_position_ned_send(boot_ms, 0, 0, 0, 0, 0, 0)
            if now >= next_param and pending:
                next_param = now + 0.1
                name = pending.pop(0)
                mav.param_value_send(name.encode(), self.params[name], 9, len(names),
                                     names.index(name))
            msg = self.conn.recv_match(blocking=True, timeout=0.002)
            if msg is None:
                continue
            kind = msg.get_type()
            if kind == "TIMESYNC" and msg.tc1 == 0 and self.timesync:
                mav.timesync_send(time.monotonic_ns(), msg.ts1)
            elif kind == "PARAM_REQUEST_READ":
                pid = msg.param_id if isinstance(msg.param_id, str) else msg.param_id.decode()
                name = pid if msg.param_index < 0 else names[msg.param_index]
                if name in self.params:
                    pending.append(name)
            elif kind == "COMMAND_LONG":
                self.commands.append(int(msg.command))
                mav.command_ack_send(msg.command, 0)
                if msg.command == 512 and int(msg.param1) == 148:
                    mav.autopilot_version_send(0, _sw(4, 7, 0, 0), 0, 0, 0, [0] * 8, [0] * 8,
                                               [0] * 8, 0, 0, 0)

    def __enter__(self) -> ArduCopterLike:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.join(2.0)
        self.conn.close()


def test_ardupilot_like_peer_is_known_and_timed_with_timesync():
    port = _free_udp_port()
    with ArduCopterLike(port, OLD_NAMES), VehicleLink.connect(f"udp:127.0.0.1:{port}") as link:
        fw = detect_firmware(link)
        assert fw.name == "ArduCopter 4.7.0-dev" and fw.source == "AUTOPILOT_VERSION"
        q = measure_link(link, rate_hz=250.0, window_s=0.5)
        assert q.rtt_method == RTT_TIMESYNC and q.rtt_lost == 0, q.line()
        assert q.rtt_p50_ms < 50, q.line()  # a parameter read would take ~100 ms here


def test_peer_without_timesync_is_timed_with_parameter_reads_and_refused_when_slow():
    port = _free_udp_port()
    with ArduCopterLike(port, OLD_NAMES, timesync=False), \
            VehicleLink.connect(f"udp:127.0.0.1:{port}") as link:
        q = measure_link(link, rate_hz=250.0, window_s=0.5, pings=3)
        assert q.rtt_method == RTT_PARAM_READ and q.rtt_p50_ms > 50, q.line()
        with pytest.raises(LinkError, match=r"round trip \(PARAM_REQUEST_READ\) \d+ ms"):
            require_relay_capable(q)


def test_torque_on_ardupilot_is_refused_before_arming(tmp_path):
    port = _free_udp_port()
    with ArduCopterLike(port, OLD_NAMES) as peer:
        with pytest.raises(UsageError, match="--actuation torque cannot fly this vehicle: "
                                             "ArduCopter 4.7.0-dev has no handler for "
                                             "SET_ACTUATOR_CONTROL_TARGET") as err:
            tune(f"udp:127.0.0.1:{port}", "ardupilot", actuation="torque", backup_dir=tmp_path)
    assert "\n" not in str(err.value)
    assert 400 not in peer.commands  # never armed
    assert err.value.partial_result.firmware.name == "ArduCopter 4.7.0-dev"
