"""The onboard position loop's rate: read from the vehicle, fallen back on where it is not said,
and designed for (the altitude and x/y gains allow for its hold, not the slowest rate's)."""

from __future__ import annotations

import math

import pytest
from pymavlink import mavutil

from mrft_gcs.flight.api import _optional_reader, tune
from mrft_gcs.flight.onboard import (
    POSITION_LOOP_MIN_HZ,
    GcsDelay,
    PositionLoopRate,
    onboard_extra_delay_s,
    onboard_side_gains,
    read_position_rate,
    robust_onboard_gains,
    vehicle_position_rate,
)
from mrft_gcs.flight.report import report_dict
from mrft_gcs.identify import Identification
from mrft_gcs.link import VehicleLink
from mrft_gcs.loops import Loop, LoopKind
from mrft_gcs.plant import PD, InnerModel, SideModel
from mrft_gcs.sitl import SitlProcess
from mrft_gcs.sitl.onboard import ParamStore
from mrft_gcs.sitl.population import random_airframe

M = mavutil.mavlink


@pytest.mark.parametrize("values, family, hz", [
    ({"SCHED_LOOP_RATE": 400.0}, "ardupilot", 400.0),
    ({"SCHED_LOOP_RATE": 1000.0}, "px4", 1000.0),  # the profile's family is not the vehicle's
    ({"EKF2_PREDICT_US": 10000.0}, "px4", 100.0),
    ({"EKF2_PREDICT_US": 10000.0, "IMU_INTEG_RATE": 200.0}, "px4", 100.0),
    # 2.5 IMU samples round half up, as PX4's roundf: every 3 of 250 Hz
    ({"EKF2_PREDICT_US": 10000.0, "IMU_INTEG_RATE": 250.0}, "px4", 250.0 / 3),
    ({"EKF2_PREDICT_US": 40000.0}, "px4", 25.0),  # slower than the fallback: taken as read
])
def test_the_rate_is_what_the_firmware_runs_at(values, family, hz):
    r = read_position_rate(values, family)
    assert r.read and r.hz == pytest.approx(hz)
    assert r.hold_s == pytest.approx(0.5 / hz)


@pytest.mark.parametrize("values", [
    {}, {"SCHED_LOOP_RATE": 0.0}, {"SCHED_LOOP_RATE": math.nan}, {"SCHED_LOOP_RATE": 5000.0},
    {"EKF2_PREDICT_US": 0.0}, {"EKF2_PREDICT_US": 1e6}, {"EKF2_PREDICT_US": -1.0},
])
def test_absent_or_implausible_falls_back_to_the_slowest_rate_and_says_why(values):
    r = read_position_rate(values, "px4")
    assert not r.read and r.hz == POSITION_LOOP_MIN_HZ
    assert "assumed" in r.source and (not values or next(iter(values)) in r.source)


def test_an_implausible_integration_rate_leaves_the_filter_period_alone():
    r = read_position_rate({"EKF2_PREDICT_US": 5000.0, "IMU_INTEG_RATE": 0.0}, "px4")
    assert r.read and r.hz == pytest.approx(200.0)


def test_the_reader_asks_the_family_first_and_the_other_where_unanswered():
    asked: list[str] = []
    ap = {"SCHED_LOOP_RATE": 500.0}

    def read(name: str) -> float | None:
        asked.append(name)
        return ap.get(name)
    r = vehicle_position_rate(read, "px4")
    assert r.hz == 500.0 and asked == ["EKF2_PREDICT_US", "SCHED_LOOP_RATE"]
    asked.clear()
    assert vehicle_position_rate(read, "ardupilot").hz == 500.0
    assert asked == ["SCHED_LOOP_RATE"]  # an ArduPilot costs no unanswered read


def test_the_hold_allowed_for_follows_the_rate_read():
    assert onboard_extra_delay_s(Loop.ALTITUDE) == pytest.approx(0.5 / POSITION_LOOP_MIN_HZ)
    assert onboard_extra_delay_s(Loop.Y, 250.0) == pytest.approx(0.002)
    assert onboard_extra_delay_s(Loop.ROLL, 250.0) == 0.0
    assert onboard_extra_delay_s(Loop.X, math.nan) == pytest.approx(0.5 / POSITION_LOOP_MIN_HZ)


def _alt_ident() -> Identification:
    m = InnerModel(K=8.0, T_prop=0.03, T1=0.6, tau=0.03)
    from mrft_gcs.pd_design import frequency_grid, optimal_pd
    from mrft_gcs.plant import inner_response
    w = frequency_grid(m.T_prop, m.T1, m.tau)
    pd = optimal_pd(inner_response(m.K, m.T_prop, m.T1, m.tau, w)[0], w).pd
    return Identification(LoopKind.ALTITUDE, m, 0, 1.0, -0.8, 0.1, 0.3, 0.05, pd)


def test_a_fast_position_loop_read_gives_stiffer_altitude_gains_than_the_fallback():
    ident = _alt_ident()
    gcs = GcsDelay(0.006, 0.004, 0.01, 0.004, True, "", 0.002)
    slow = robust_onboard_gains(ident, gcs, onboard_extra_s=onboard_extra_delay_s(
        Loop.ALTITUDE, read_position_rate({}).hz))
    fast = robust_onboard_gains(ident, gcs, onboard_extra_s=onboard_extra_delay_s(
        Loop.ALTITUDE, read_position_rate({"SCHED_LOOP_RATE": 400.0}).hz))
    assert fast.extra_s < slow.extra_s
    assert fast.gains.Kc > slow.gains.Kc and fast.delay_s >= slow.delay_s
    assert fast.pm_deg >= 15.0 and slow.pm_deg >= 15.0


def test_a_fast_position_loop_read_lets_the_side_gains_move_further():
    mi = InnerModel(K=40.0, T_prop=0.02, T1=0.3, tau=0.03)
    ii = Identification(LoopKind.ATTITUDE, mi, 0, 1.0, -0.8, 0.1, 0.25, 0.03, PD(2.0, 0.2))
    si = Identification(LoopKind.SIDE, SideModel(K=9.8, T2=1.5, tau=0.05), 0, 1.0, -0.8, 0.1,
                        1.0, 0.1, PD(0.5, 0.4))
    rt = robust_onboard_gains(ii, GcsDelay(0.012, 0.010, 0.016, 0.002, True, "", 0.01))
    slow = onboard_side_gains(si, ii, rt, onboard_extra_s=onboard_extra_delay_s(Loop.X))
    fast = onboard_side_gains(si, ii, rt, onboard_extra_s=onboard_extra_delay_s(Loop.X, 500.0))
    assert fast.gains != slow.gains and fast.pm_deg >= 15.0


def test_the_report_carries_the_rate_and_whether_it_was_read():
    from mrft_gcs.flight.api import TuneResult
    r = TuneResult("udp:x", "px4", "sitl", "torque", "now", math.nan, {}, (), None, "ok",
                   position_loop=read_position_rate({"EKF2_PREDICT_US": 8000.0}, "px4"))
    d = report_dict(r)["position_loop"]
    assert d["hz"] == pytest.approx(125.0) and d["read"] is True and d["hold_ms"] == 4.0
    assert "EKF2_PREDICT_US = 8000" in d["source"]
    assert report_dict(TuneResult("udp:x", "px4", "sitl", "torque", "now", math.nan, {}, (),
                                  None, "ok"))["position_loop"] is None
    assert not PositionLoopRate().read


def _seeds(style: str) -> list[int]:
    return [s for s in range(40) if random_airframe(s).onboard.style == style]


def test_the_simulated_vehicles_say_their_position_rate_as_their_firmware_would():
    """Every vehicle of the population: the rate the tool reads from its parameters is the
    one its position loop runs at (what the onboard truth scores with)."""
    for seed in range(40):
        af = random_airframe(seed)
        ob = af.onboard
        if ob.style == "ardupilot":  # ArduCopter's position controller is in its main loop
            assert ob.position_loop_hz == ob.loop_hz, seed
        store = ParamStore(af.hover_thrust, ob)
        for family in ("px4", "ardupilot"):
            r = vehicle_position_rate(lambda n, st=store: st[n] if n in st else None, family)
            assert r.read and r.hz == pytest.approx(ob.position_loop_hz), (seed, r)


@pytest.mark.parametrize("style", ["px4", "ardupilot"])
def test_the_rate_read_over_mavlink_from_the_bundled_sitl_is_the_vehicle_s(style, tmp_path):
    """The tool's own reader, over UDP, against the simulator as a process; and a dry-link
    tune (the tool up to take-off) reports what it read."""
    seed = next(s for s in _seeds(style) if random_airframe(s).onboard.position_loop_hz
                < random_airframe(s).onboard.loop_hz or style == "ardupilot")
    af = random_airframe(seed)
    with SitlProcess(random_seed=seed, port=None) as sitl:
        with VehicleLink.connect(sitl.connection_string, timeout_s=10) as link:
            r = vehicle_position_rate(_optional_reader(link), "px4")
        assert r.read, r
        assert r.hz == pytest.approx(af.onboard.position_loop_hz, rel=1e-3), (seed, r)
        res = tune(sitl.connection_string, "sitl", dry_link=True, backup_dir=tmp_path)
    assert res.position_loop == r
    assert any(n.startswith("position loop: ") for n in res.notes)


def test_dry_run_reads_the_position_rate_a_log_holds_as_a_tune_reads_it(tmp_path):
    from mrft_gcs.dryrun import log_position_rate
    from mrft_gcs.logs import decode_log
    from mrft_gcs.residual.synth import sitl_relay_record, write_relay_tlog

    rec = sitl_relay_record("roll", seed=3, beta=-0.7, h=0.08, duration_s=2.0)
    plain, ekf = tmp_path / "plain.tlog", tmp_path / "ekf.tlog"
    write_relay_tlog(plain, "roll", rec.t, rec.u, rec.y)
    write_relay_tlog(ekf, "roll", rec.t, rec.u, rec.y,
                     params={"EKF2_PREDICT_US": 4000.0, "IMU_INTEG_RATE": 250.0})
    r = log_position_rate(decode_log(ekf), "px4")
    assert r.read and r.hz == pytest.approx(250.0)
    assert not log_position_rate(decode_log(plain), "px4").read
