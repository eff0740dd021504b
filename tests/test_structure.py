"""Written gains designed on the autopilot's own structure (mrft_gcs.flight.structure)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from mrft_gcs.flight import structure
from mrft_gcs.flight.onboard import (
    CAP_SHARE,
    PM_ROBUST_DEG,
    measure_gcs_delay,
    onboard_side_gains,
    robust_onboard_gains,
)
from mrft_gcs.flight.scoring import (
    general_ise,
    onboard_process,
    score_written,
    structure_floor,
)
from mrft_gcs.flight.structure import (
    D_GAIN_MOVE_MAX,
    D_GM_MIN,
    RATE_D_OVER_P_S,
    OnboardStructure,
    rate_d_values,
    read_structure,
    structure_controller,
    structured_pd,
    structured_retarget,
    vehicle_structure,
)
from mrft_gcs.identify import Identification
from mrft_gcs.loops import Loop, LoopKind
from mrft_gcs.pd_design import frequency_grid, margins, optimal_pd
from mrft_gcs.plant import PD, InnerModel, SideModel, inner_response
from mrft_gcs.profiles import PDGains, gains_to_params, load_profile
from mrft_gcs.sitl import load_airframe
from mrft_gcs.sitl.onboard import ParamStore

P = 0.004  # the setpoint period (s)


def _ardupilot_like(name: str, target_hz: float, link_s: float = 0.002):
    af = load_airframe(name)
    return dataclasses.replace(af, link_delay_s=link_s, onboard=dataclasses.replace(
        af.onboard, style="ardupilot", target_cutoff_hz=target_hz, dgyro_cutoff_hz=20.0))


def _identified(af, loop: Loop, gcs_delay_s: float) -> Identification:
    m = af.linear_models()[loop.value]
    im = InnerModel(m["K"], m["T_prop"], m["T1"], m["tau"] + gcs_delay_s)
    w = frequency_grid(im.T_prop, im.T1, im.tau)
    pd = optimal_pd(inner_response(im.K, im.T_prop, im.T1, im.tau, w)[0], w).pd
    return Identification(LoopKind.ATTITUDE, im, 0, 1.0, -0.8, 0.1, 0.25, 0.03, pd)


def _written(af, gains: dict[Loop, PD], d_over_p: dict[Loop, float] | None = None):
    prm = dict(ParamStore(af.hover_thrust, af.onboard).values)
    pd = {lp: PDGains(g.Kc, g.Kd) for lp, g in gains.items()}
    prm.update(gains_to_params(load_profile("sitl"), pd, prm["MPC_THR_HOVER"]))
    prm.update(rate_d_values(load_profile("sitl"), pd, d_over_p or {}))
    return {lp: s.onboard for lp, s in score_written(af, prm, list(gains)).items()}


# f550 is slow: a 15 Hz filter costs its loop little, the design must still not lose
@pytest.mark.parametrize("name,target_hz,gain_pct", [("qdrone", 12.0, 1.0),
                                                     ("racer250", 20.0, 1.0),
                                                     ("f550", 15.0, 0.0)])
def test_the_structured_design_beats_the_pd_design_on_a_rate_target_filter(name, target_hz,
                                                                           gain_pct):
    # the same identification, the same re-targeted delay; one design ignores the filter the
    # autopilot closes the loop through, the other is made on it: scored on the true loop
    af = _ardupilot_like(name, target_hz)
    ident = _identified(af, Loop.ROLL, 0.008)
    gcs = measure_gcs_delay([0.002] * 30, P, round_trip_s=0.004)
    rt = robust_onboard_gains(ident, gcs)
    st = read_structure(Loop.ROLL, ParamStore(af.hover_thrust, af.onboard).values, "px4")
    assert st.target_hz == target_hz and not st.plain
    new = structured_retarget(ident, rt, st)
    old_sc = _written(af, {Loop.ROLL: rt.gains})[Loop.ROLL]
    new_sc = _written(af, {Loop.ROLL: new.gains}, {Loop.ROLL: new.d_over_p_s})[Loop.ROLL]
    assert new_sc.J_pct < old_sc.J_pct - gain_pct, (old_sc, new_sc)
    assert new_sc.pm_deg >= PM_ROBUST_DEG and new.pm_deg >= PM_ROBUST_DEG
    assert "rate target low-pass" in new.note()


@pytest.mark.parametrize("name,target_hz", [("qdrone", 12.0), ("racer250", 20.0),
                                            ("f550", 15.0)])
def test_rate_d_takes_the_loop_below_its_two_number_floor(name, target_hz):
    # ArduPilot's structure with its D filter read: the design writes rate D at ArduCopter's
    # default share of rate P; on the true loop it beats the best two numbers can do (the
    # floor) and the ideal PD, keeping both margins and a gain margin of 2
    af = _ardupilot_like(name, target_hz)
    ident = _identified(af, Loop.ROLL, 0.008)
    rt = robust_onboard_gains(ident, measure_gcs_delay([0.002] * 30, P, round_trip_s=0.004))
    st = read_structure(Loop.ROLL, ParamStore(af.hover_thrust, af.onboard).values, "px4")
    assert st.d_over_p_s == RATE_D_OVER_P_S and st.d_hz == 20.0  # ATC_RAT_RLL_FLTD read
    two = structured_retarget(ident, rt, dataclasses.replace(st, d_over_p_s=0.0))
    new = structured_retarget(ident, rt, st)
    assert new.d_over_p_s == RATE_D_OVER_P_S and "rate D" in new.note()
    assert two.d_over_p_s == 0.0 and "rate D" not in new.note().split("rate D")[0]
    # never more than D_GAIN_MOVE_MAX times the two-number design's gains
    assert new.gains.Kc <= two.gains.Kc * D_GAIN_MOVE_MAX * 1.0001
    assert new.gains.Kd <= two.gains.Kd * D_GAIN_MOVE_MAX * 1.0001
    prm = dict(ParamStore(af.hover_thrust, af.onboard).values)
    pd = {Loop.ROLL: PDGains(new.gains.Kc, new.gains.Kd)}
    prm.update(gains_to_params(load_profile("sitl"), pd, prm["MPC_THR_HOVER"]))
    prm.update(rate_d_values(load_profile("sitl"), pd, {Loop.ROLL: new.d_over_p_s}))
    assert prm["MC_ROLLRATE_D"] == pytest.approx(RATE_D_OVER_P_S * new.gains.Kd, rel=1e-3)
    sc = score_written(af, prm, [Loop.ROLL], floor=True)[Loop.ROLL]
    assert sc.floor is not None and sc.onboard.J_pct < 0.0 < sc.floor.J_pct
    assert sc.onboard.pm_deg >= 20.0
    G, w = onboard_process(af, Loop.ROLL, prm)
    from mrft_gcs.flight.scoring import onboard_controller
    assert margins(onboard_controller(af, Loop.ROLL, prm, w)[1] * G, w).gm >= D_GM_MIN
    # the same gains with D dropped (written as 0): far from the design (it leaned on D)
    dropped = _written(af, {Loop.ROLL: new.gains})[Loop.ROLL]
    assert dropped.J_pct > sc.onboard.J_pct + 10.0 or dropped.pm_deg < sc.onboard.pm_deg - 10


def test_rate_d_not_written_where_it_does_not_pay_or_is_switched_off(monkeypatch):
    # PX4 (no rate-target filter): no D; ArduPilot with WRITE_RATE_D off: no D
    assert read_structure(Loop.ROLL, {}, "px4").d_over_p_s == 0.0
    values = {"ATC_RAT_RLL_FLTT": 20.0}
    assert read_structure(Loop.ROLL, values).d_hz == 20.0  # FLTD's default, not read
    monkeypatch.setattr(structure, "WRITE_RATE_D", False)
    assert read_structure(Loop.ROLL, values).d_over_p_s == 0.0
    assert rate_d_values(load_profile("sitl"), {Loop.ROLL: PDGains(1.0, 0.2)}, {}) == {}


def test_structure_controller_with_rate_d_is_the_sitl_cascade_on_the_error():
    # the design's (Cr, Cy) are the scoring's ArduPilot-like onboard controller (D on the
    # error of the filtered target, AC_PID) for the same written parameters
    af = _ardupilot_like("qdrone", 15.0)
    prm = dict(ParamStore(af.hover_thrust, af.onboard).values)
    g = PD(1.2, 0.12)
    pd = {Loop.ROLL: PDGains(g.Kc, g.Kd)}
    prm.update(gains_to_params(load_profile("sitl"), pd, prm["MPC_THR_HOVER"]))
    prm.update(rate_d_values(load_profile("sitl"), pd, {Loop.ROLL: RATE_D_OVER_P_S}))
    from mrft_gcs.flight.scoring import onboard_controller
    w = np.logspace(0, 3, 50)
    Cr, Cy = onboard_controller(af, Loop.ROLL, prm, w)
    st = read_structure(Loop.ROLL, prm, "px4")
    Cr2, Cy2 = structure_controller(g, st, w)
    assert np.allclose(Cr, Cr2, rtol=1e-4) and np.allclose(Cy, Cy2, rtol=1e-4)


def test_a_plain_structure_keeps_the_pd_retarget():
    af = load_airframe("qdrone")
    ident = _identified(af, Loop.PITCH, 0.006)
    rt = robust_onboard_gains(ident, measure_gcs_delay([0.002] * 30, P))
    st = read_structure(Loop.PITCH, ParamStore(af.hover_thrust, af.onboard).values, "px4")
    assert st.plain and structured_retarget(ident, rt, st) is rt


def test_both_margins_are_honoured():
    m = InnerModel(K=150.0, T_prop=0.03, T1=0.6, tau=0.006)
    w = frequency_grid(m.T_prop, m.T1, 0.02)
    G = inner_response(m.K, m.T_prop, m.T1, m.tau, w)[0]
    worst = inner_response(m.K, m.T_prop, m.T1, 0.016, w)[0]  # 10 ms more onboard
    st = OnboardStructure(12.0)
    free = structured_pd(G, w, st)
    held = structured_pd(G, w, st, worst=(worst,), pm_worst_deg=PM_ROBUST_DEG)
    for d, G_chk in ((free, G), (held, G), (held, worst)):
        Cy = structure_controller(d.gains, st, w)[1]
        mg = margins(Cy * G_chk, w)
        assert mg.stable
    assert free.pm_deg >= 20.0 - 0.05
    assert free.pm_worst_deg == math.inf
    assert free.pm_deg < 25.0  # the constraint is active: the ISE pulls towards less margin
    assert held.pm_worst_deg >= PM_ROBUST_DEG - 0.05 and held.pm_deg >= 20.0 - 0.05
    assert held.ise >= free.ise  # the extra constraint costs, never helps
    plain = optimal_pd(G, w).pd  # the PD design, written through the same structure
    Cr, Cy = structure_controller(plain, st, w)
    assert free.ise < general_ise(Cr, Cy, G, w) * 0.99


def test_structure_read_from_the_sitl_over_its_parameter_names():
    ap_like = ParamStore(0.4, _ardupilot_like("qdrone", 17.5).onboard)
    px4_like = ParamStore(0.4, load_airframe("qdrone").onboard)
    st = vehicle_structure(lambda n: ap_like.values.get(n), "px4")
    assert st[Loop.ROLL].target_hz == st[Loop.PITCH].target_hz == 17.5
    asked: list[str] = []

    def px4_read(name: str):
        asked.append(name)
        return px4_like.values.get(name)

    st = vehicle_structure(px4_read, "px4")
    assert all(s.plain for s in st.values()) and asked == ["ATC_RAT_RLL_FLTT"]
    assert "IMU_DGYRO_CUTOFF" in px4_like and "IMU_GYRO_RATEMAX" in px4_like
    st = vehicle_structure(lambda n: None, "ardupilot")  # the family's default
    assert st[Loop.ROLL].target_hz == 20.0 and "default" in st[Loop.ROLL].source


def test_a_written_target_filter_takes_effect_in_the_sitl():
    # the rate target's step response: a lower FLTT written, a slower target
    from mrft_gcs.sitl.onboard import _RateAxis

    spec = _ardupilot_like("qdrone", 40.0).onboard
    prm = ParamStore(0.4, spec)
    for name, value in (("MC_ROLLRATE_P", 1.0), ("MC_ROLLRATE_I", 0.0),
                        ("MC_ROLLRATE_D", 0.0), ("MC_ROLLRATE_FF", 0.0)):
        assert prm.set(name, value)

    def first_outputs() -> list[float]:
        ax = _RateAxis("MC_ROLLRATE", 0.001, spec)
        return [ax.update(prm, sp, 0.0, False) for sp in (0.0, 1.0, 1.0, 1.0, 1.0)]

    fast = first_outputs()
    assert prm.set("ATC_RAT_RLL_FLTT", 5.0)
    slow = first_outputs()
    assert slow[-1] < fast[-1]
    assert not prm.set("ATC_RAT_RLL_FLTT", -1.0)  # out of the firmware's range


def test_the_measured_link_goes_out_beyond_the_share_cap():
    # 12 ms of link each way on 3 ms onboard: the least plausible GCS delay (measured) is over
    # CAP_SHARE of the identified delay; it is re-targeted, the margin check still applies
    m = InnerModel(K=300.0, T_prop=0.02, T1=1.1, tau=0.030)
    w = frequency_grid(m.T_prop, m.T1, m.tau)
    pd = optimal_pd(inner_response(m.K, m.T_prop, m.T1, m.tau, w)[0], w).pd
    ident = Identification(LoopKind.ATTITUDE, m, 0, 1.0, -0.8, 0.1, 0.25, 0.03, pd)
    gcs = measure_gcs_delay([0.002] * 30, P, round_trip_s=0.024)
    assert gcs.lo_s > CAP_SHARE * m.tau
    old = robust_onboard_gains(ident, gcs, certain_share=0.0)
    new = robust_onboard_gains(ident, gcs)
    assert old.delay_s == pytest.approx(CAP_SHARE * m.tau)
    # measured: up to the estimate (held back only as far as the margin at lo needs)
    assert gcs.lo_s < new.delay_s <= gcs.estimate_s and new.pm_deg >= PM_ROBUST_DEG - 1e-6
    assert new.gains.Kc > old.gains.Kc


def test_side_gains_behind_a_known_filter_need_not_allow_for_an_unseen_one():
    mi = InnerModel(K=40.0, T_prop=0.02, T1=0.3, tau=0.03)
    ii = Identification(LoopKind.ATTITUDE, mi, 0, 1.0, -0.8, 0.1, 0.25, 0.03, PD(2.0, 0.2))
    si = Identification(LoopKind.SIDE, SideModel(K=9.8, T2=1.5, tau=0.01), 0, 1.0, -0.8, 0.1,
                        1.0, 0.1, PD(0.3, 0.25))
    rt = robust_onboard_gains(ii, measure_gcs_delay([0.002] * 30, P, round_trip_s=0.010))
    unseen = onboard_side_gains(si, ii, rt)
    none = onboard_side_gains(si, ii, rt, target_hz=0.0)
    slow = onboard_side_gains(si, ii, rt, target_hz=8.0)
    assert min(unseen.pm_deg, none.pm_deg, slow.pm_deg) >= PM_ROBUST_DEG
    assert none.gains.Kc >= unseen.gains.Kc  # no filter to allow for: no less gain
    assert slow.gains.Kc <= none.gains.Kc  # a slower attitude loop: no more gain
    assert np.isfinite(slow.pm_deg)


# ------------------------------------------------------------------ the structure's floor
def test_the_floor_of_a_plain_structure_is_the_ideal_pd():
    # the written parameters (rate and velocity I, D at 0) close exactly a PD on PX4
    af = load_airframe("qdrone")
    params = dict(ParamStore(af.hover_thrust, af.onboard).values)
    params.update(gains_to_params(load_profile("sitl"), {
        lp: PDGains(1.0, 0.1) for lp in (Loop.ROLL, Loop.ALTITUDE, Loop.X)},
        params["MPC_THR_HOVER"]))
    for lp in (Loop.ROLL, Loop.ALTITUDE, Loop.X):
        fl = structure_floor(af, lp, params)
        assert fl.plain and fl.J_pct == 0.0 and fl.pm_deg >= 20.0 - 0.05


@pytest.mark.parametrize("name,target_hz", [("qdrone", 12.0), ("racer250", 20.0)])
def test_the_floor_of_a_rate_target_filter_bounds_every_written_design(name, target_hz):
    # on the true onboard loop: no pair of written numbers with PM >= 20 there does better than
    # the floor, neither the ideal PD written through the filter nor the tool's design
    af = _ardupilot_like(name, target_hz)
    params = dict(ParamStore(af.hover_thrust, af.onboard).values)
    params.update(gains_to_params(load_profile("sitl"), {Loop.ROLL: PDGains(1.0, 0.1)},
                                  params["MPC_THR_HOVER"]))
    fl = structure_floor(af, Loop.ROLL, params)
    assert not fl.plain and fl.J_pct > 1.0 and fl.pm_deg >= 20.0 - 0.05
    G, w = onboard_process(af, Loop.ROLL, params)
    ident = _identified(af, Loop.ROLL, 0.008)
    rt = robust_onboard_gains(ident, measure_gcs_delay([0.002] * 30, P, round_trip_s=0.004))
    st = OnboardStructure(target_hz)
    for g in (optimal_pd(G, w).pd, structured_retarget(ident, rt, st).gains):
        sc = score_written(af, {**params, **gains_to_params(
            load_profile("sitl"), {Loop.ROLL: PDGains(g.Kc, g.Kd)}, params["MPC_THR_HOVER"])},
            [Loop.ROLL], floor=True)[Loop.ROLL]
        if sc.onboard.pm_deg >= 20.0:
            assert sc.onboard.J_pct >= fl.J_pct - 0.05
        # the second figure is the first one measured from the floor instead of the ideal PD
        assert sc.floor is not None and sc.floor.J_pct == pytest.approx(fl.J_pct, abs=1e-6)
        assert (1 + sc.onboard.J_pct / 100) == pytest.approx(
            (1 + sc.J_vs_floor_pct / 100) * (1 + fl.J_pct / 100))


@pytest.mark.slow
def test_a_live_tune_of_an_ardupilot_like_vehicle_writes_rate_d_and_it_holds(tmp_path):
    """The real tune() over loopback UDP against the bundled SITL's ArduPilot-like random
    vehicle 10: rate D goes in with the roll/pitch gains (backed up, read back) at the
    default share of rate P, and the in-air check measures the loop it closes with it."""
    from pymavlink import mavutil

    from mrft_gcs.flight import tune
    from mrft_gcs.sitl import SitlProcess, random_airframe

    assert random_airframe(10).onboard.style == "ardupilot"
    with SitlProcess(random_seed=10, port=None) as sitl:
        r = tune(sitl.connection_string, "sitl", backup_dir=tmp_path)
        assert r.status == "ok", r.error
        changes = {c.name: c for c in r.parameters}
        for ax in ("ROLL", "PITCH"):
            d, p = changes[f"MC_{ax}RATE_D"], changes[f"MC_{ax}RATE_P"]
            assert d.old == pytest.approx(0.003)  # the vehicle's own, backed up
            assert d.new == pytest.approx(RATE_D_OVER_P_S * p.new, rel=1e-3)
        assert "rate D" in " ".join(r.notes)
        # roll and pitch were designed on their pooled fast lags, and the report says so
        assert "fast lags pooled" in " ".join(r.notes)
        for lp in (Loop.ROLL, Loop.PITCH):
            v = r.loops[lp].verification
            assert v is not None and v.passed and v.measured_pm_deg >= 17.0
        gcs = mavutil.mavlink_connection(sitl.connection_string, source_system=254)
        try:  # read back from the vehicle itself
            assert gcs.recv_match(type="HEARTBEAT", blocking=True, timeout=10) is not None
            gcs.mav.param_request_read_send(1, 1, b"MC_ROLLRATE_D", -1)
            m = gcs.recv_match(type="PARAM_VALUE", blocking=True, timeout=5)
            assert m is not None and m.param_value == pytest.approx(
                changes["MC_ROLLRATE_D"].new, rel=1e-5)
        finally:
            gcs.close()
    from pathlib import Path

    assert r.backup is not None and "MC_ROLLRATE_D" in Path(r.backup).read_text()
