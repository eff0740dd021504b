"""x and y share the autopilot's position and velocity P: one PD designed for both."""

from __future__ import annotations

import dataclasses

import pytest
from flight_sim import identified_side

from mrft_gcs.flight.onboard import (
    PM_ROBUST_DEG,
    SideLoop,
    measure_gcs_delay,
    onboard_extra_delay_s,
    onboard_side_gains,
    robust_onboard_gains,
    shared_side_gains,
)
from mrft_gcs.flight.scoring import score_written
from mrft_gcs.identify import Identification
from mrft_gcs.loops import Loop, LoopKind
from mrft_gcs.pd_design import frequency_grid, optimal_pd
from mrft_gcs.plant import (
    InnerModel,
    inner_response,
)
from mrft_gcs.profiles import PDGains, gains_to_params, load_profile
from mrft_gcs.sitl import load_airframe
from mrft_gcs.sitl.onboard import ParamStore

P = 0.004  # setpoint period at 250 Hz


def _attitude(af, loop: Loop, gcs_delay_s: float) -> Identification:
    """The attitude loop as the ground station identifies it: the true model with the GCS
    delay, its optimal PD."""
    m = af.linear_models()[loop.value]
    im = InnerModel(m["K"], m["T_prop"], m["T1"], m["tau"] + gcs_delay_s)
    w = frequency_grid(im.T_prop, im.T1, im.tau)
    pd = optimal_pd(inner_response(im.K, im.T_prop, im.T1, im.tau, w)[0], w).pd
    return Identification(LoopKind.ATTITUDE, im, 0, 1.0, -0.8, 0.1, 0.25, 0.03, pd)




def _truth(af, gains):
    """J / PM of the written gains on the true onboard x and y loops (the write path's
    parameters: x and y share one position and one velocity P)."""
    prm = dict(ParamStore(af.hover_thrust).values)
    prm.update(gains_to_params(load_profile("sitl"), {lp: PDGains(g.Kc, g.Kd)
                                                      for lp, g in gains.items()},
                               prm["MPC_THR_HOVER"]))
    return {lp: s.onboard for lp, s in score_written(af, prm, [Loop.X, Loop.Y]).items()}


def test_x_and_y_get_one_pd_designed_for_both_not_the_smaller_of_each_gain():
    # roll was identified with 5 ms more delay than pitch: its written gains are slower, and
    # y's design behind them is lower than x's. Written apart, the parameters take the
    # smaller gains, which leave x well below its own design
    af = load_airframe("racer250")
    af = dataclasses.replace(af, link_delay_s=0.004, onboard=dataclasses.replace(
        af.onboard, position_loop_hz=1000.0))
    gcs = measure_gcs_delay([0.002] * 30, P, round_trip_s=0.008)
    pitch, roll = _attitude(af, Loop.PITCH, 0.010), _attitude(af, Loop.ROLL, 0.015)
    rp, rr = robust_onboard_gains(pitch, gcs), robust_onboard_gains(roll, gcs)
    sx, sy = identified_side(af, Loop.X, pitch), identified_side(af, Loop.Y, roll)
    extra = onboard_extra_delay_s(Loop.X)  # the position loop's rate not read
    own = {Loop.X: onboard_side_gains(sx, pitch, rp, onboard_extra_s=extra, target_hz=0.0),
           Loop.Y: onboard_side_gains(sy, roll, rr, onboard_extra_s=extra, target_hz=0.0)}
    assert own[Loop.X].gains.Kc > 1.2 * own[Loop.Y].gains.Kc
    inner = {Loop.PITCH: rp.gains, Loop.ROLL: rr.gains}
    apart = _truth(af, {**inner, **{lp: r.gains for lp, r in own.items()}})
    assert apart[Loop.X].J_pct > 10.0
    shared = shared_side_gains([SideLoop(sx, pitch, rp, 0.0), SideLoop(sy, roll, rr, 0.0)],
                               onboard_extra_s=extra)
    assert shared[0].gains == shared[1].gains
    assert min(r.pm_deg for r in shared.values()) >= PM_ROBUST_DEG
    g = shared[0].gains  # between the two designs
    assert own[Loop.Y].gains.Kc < g.Kc < own[Loop.X].gains.Kc
    both = _truth(af, {**inner, Loop.X: g, Loop.Y: g})
    for lp in (Loop.X, Loop.Y):
        assert both[lp].J_pct <= 10.0 and both[lp].pm_deg >= PM_ROBUST_DEG


def test_one_side_loop_alone_keeps_its_own_design():
    af = load_airframe("qdrone")
    gcs = measure_gcs_delay([0.002] * 30, P, round_trip_s=0.008)
    pitch = _attitude(af, Loop.PITCH, 0.010)
    rp = robust_onboard_gains(pitch, gcs)
    sx = identified_side(af, Loop.X, pitch)
    own = onboard_side_gains(sx, pitch, rp, target_hz=0.0)
    shared = shared_side_gains([SideLoop(sx, pitch, rp, 0.0)])
    assert shared[0].gains == own.gains
    assert shared[0].pm_deg == pytest.approx(own.pm_deg)


def test_designs_near_each_other_keep_the_smaller_of_each_gain():
    # roll identified with 1 ms more delay than pitch: the smaller gains already leave both
    # loops within SHARED_ISE_SLACK of their own designs, and stay what is written
    af = load_airframe("qdrone")
    gcs = measure_gcs_delay([0.002] * 30, P, round_trip_s=0.008)
    pitch, roll = _attitude(af, Loop.PITCH, 0.010), _attitude(af, Loop.ROLL, 0.011)
    rp, rr = robust_onboard_gains(pitch, gcs), robust_onboard_gains(roll, gcs)
    sx, sy = identified_side(af, Loop.X, pitch), identified_side(af, Loop.Y, roll)
    gx = onboard_side_gains(sx, pitch, rp, target_hz=0.0).gains
    gy = onboard_side_gains(sy, roll, rr, target_hz=0.0).gains
    assert gx != gy
    shared = shared_side_gains([SideLoop(sx, pitch, rp, 0.0), SideLoop(sy, roll, rr, 0.0)])
    kd = min(gx.Kd, gy.Kd)
    assert shared[0].gains.Kd == pytest.approx(kd)
    assert shared[0].gains.Kc == pytest.approx(min(gx.Kc / gx.Kd, gy.Kc / gy.Kd) * kd)
