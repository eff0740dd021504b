"""Written gains scored on the vehicle's true onboard loop (flight/scoring.score_written).

Checked against known cases: on the bundled airframes (PX4-like, 1 kHz) with the plain PD
mapping the onboard score is the ground-station scoring's; on random vehicles the predicted
onboard closed attitude loop matches the simulated autopilot's response to a sine
(structure, loop rate, filters and the linearised square root all in it).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from mrft_gcs.flight.scoring import (
    general_ise,
    onboard_controller,
    onboard_process,
    score_gains,
    score_written,
    true_response,
)
from mrft_gcs.loops import SIDE_INNER, Loop
from mrft_gcs.pd_design import ise, margins, optimal_pd
from mrft_gcs.plant import PD, inner_response
from mrft_gcs.profiles import PDGains, gains_to_params, load_profile
from mrft_gcs.sitl import OnboardSpec, SimVehicle, load_airframe, random_airframe
from mrft_gcs.sitl.onboard import FlightMode, ParamStore

PROFILE = load_profile("sitl")
_INNER = SIDE_INNER


def _written(af, gains: dict[Loop, PD]) -> dict[str, float]:
    store = ParamStore(af.hover_thrust)
    pd = {lp: PDGains(g.Kc, g.Kd) for lp, g in gains.items() if lp is not Loop.Y}
    # the values as computed (scoring is pure: no parameter range applies here)
    return {**store.values, **gains_to_params(PROFILE, pd, store["MPC_THR_HOVER"])}


def _gains_for(models) -> dict[Loop, PD]:
    out = {}
    for lp in (Loop.ROLL, Loop.PITCH, Loop.ALTITUDE):
        G, w = true_response(models, lp)
        best = optimal_pd(G, w).pd
        out[lp] = PD(best.Kc * 1.15, best.Kd * 0.9)  # off the optimum: J and PM both move
    for lp in (Loop.X, Loop.Y):
        G, w = true_response(models, lp, out[_INNER[lp]])
        out[lp] = optimal_pd(G, w).pd
    return out


def test_general_ise_is_the_pd_ise_for_a_pd():
    w = np.logspace(-2, 3, 1500)
    G = inner_response(30.0, 0.03, 0.4, 0.01, w)[0]
    s = 1j * w
    assert general_ise(0.8 + 0 * s, 0.8 + 0.06 * s, G, w) == pytest.approx(ise(0.8, 0.06, G, w))


@pytest.mark.parametrize("name", ["qdrone", "racer250", "f550"])
def test_plain_pd_on_the_bundled_airframes_scores_as_before(name):
    af = load_airframe(name)
    models = af.linear_models()
    gains = _gains_for(models)
    sw = score_written(af, _written(af, gains), identified=gains)
    old = score_gains(models, gains)
    for lp, sc in sw.items():
        assert sc.onboard.J_pct == pytest.approx(old[lp].J_pct, abs=0.02), lp
        assert sc.onboard.pm_deg == pytest.approx(old[lp].pm_deg, abs=0.02), lp
        assert sc.onboard.gains.Kc == pytest.approx(gains[lp if lp is not Loop.Y else Loop.X].Kc
                                                    if lp in _INNER else gains[lp].Kc)
        # no GCS delay asked: the GCS-side figures are the same loop
        assert sc.gcs.pm_deg == pytest.approx(old[lp].pm_deg, abs=0.02)


def test_slower_loop_and_gcs_delay_cost_margin_as_a_delay_does():
    af = load_airframe("racer250")
    gains = _gains_for(af.linear_models())
    params = _written(af, gains)
    fast = score_written(af, params, [Loop.ROLL], identified=gains, gcs_delay_s=0.004)[Loop.ROLL]
    slow_af = replace(af, onboard=OnboardSpec(loop_hz=250.0, position_loop_hz=250.0))
    slow = score_written(slow_af, params, [Loop.ROLL])[Loop.ROLL].onboard
    G, w = onboard_process(af, Loop.ROLL, params)
    Cr, Cy = onboard_controller(af, Loop.ROLL, params, w)
    crossover = margins(Cy * G, w).wc
    # a 250 Hz sample-and-hold is about 1.5 ms more delay than the 1 kHz one
    expected = math.degrees(crossover * 0.0015)
    assert fast.onboard.pm_deg - slow.pm_deg == pytest.approx(expected, rel=0.25)
    assert fast.gcs.pm_deg < fast.onboard.pm_deg - 0.5 * math.degrees(crossover * 0.004)


def _sine_response(af, params, axis: int, freq_hz: float, amp_rad: float = 0.02):
    """Gain and phase (deg) of the simulated onboard attitude loop, set point to measured
    angle, at ``freq_hz``: the autopilot reads the set point when it runs, as from its own
    position loop."""
    v = SimVehicle(af.quiet())
    v.reset(position_ned=(0.0, 0.0, -20.0), airborne=True)
    ap = v.autopilot
    for k, val in params.items():
        ap.params.values[k] = val
    hover = v.physics._thrust_to_cmd(af.hover_thrust)  # the command of hover, on any curve
    ap.set_attitude_target((1.0, 0.0, 0.0, 0.0), hover)
    assert ap.set_mode(FlightMode.OFFBOARD).name == "ACCEPTED"
    ap.arm(True)
    n_per = 6
    t_end = (4 + n_per) / freq_hz
    ts, rs, ys = [], [], []
    while v.time_s < t_end:
        t = v.time_s
        r = amp_rad * math.sin(2 * math.pi * freq_hz * t)
        ang = (r, 0.0) if axis == 0 else (0.0, r)
        cr, sr = math.cos(ang[0] / 2), math.sin(ang[0] / 2)
        cp, sp = math.cos(ang[1] / 2), math.sin(ang[1] / 2)
        ap.set_attitude_target((cr * cp, sr * cp, cr * sp, -sr * sp), hover)
        v.step()
        if v.time_s >= 4 / freq_hz:
            ts.append(t)
            rs.append(r)
            ys.append(v.physics.meas_att[axis])
    t, y = np.asarray(ts), np.asarray(ys)
    basis = np.column_stack([np.sin(2 * np.pi * freq_hz * t), np.cos(2 * np.pi * freq_hz * t),
                             np.ones_like(t)])
    a, b, _ = np.linalg.lstsq(basis, y, rcond=None)[0]
    return math.hypot(a, b) / amp_rad, math.degrees(math.atan2(b, a))


def _pick(style: str, loop_hz: float):
    for seed in range(400):
        af = random_airframe(seed)
        if (af.onboard.style == style and af.onboard.loop_hz == loop_hz
                and not af.effects.active() and af.thrust_to_weight > 2.5
                and (style == "px4" or af.onboard.target_cutoff_hz < 25)):
            return af
    raise AssertionError("no such vehicle in the first 400 seeds")


@pytest.mark.parametrize("style,loop_hz,effects", [
    ("ardupilot", 250.0, {}), ("px4", 1000.0 / 3.0, {}),
    ("px4", 500.0, {"sensor_lpf": 20.0, "thrust_curve": 0.5})])
def test_predicted_onboard_attitude_loop_matches_the_simulated_autopilot(style, loop_hz,
                                                                         effects):
    af = _pick(style, loop_hz).with_effects(effects)
    models = af.linear_models()
    gains = _gains_for(models)
    params = _written(af, gains)
    if style == "px4" and not effects:  # exercise K, D on the measurement with its low-pass, and FF
        params.update(MC_ROLLRATE_K=0.8, MC_ROLLRATE_P=params["MC_ROLLRATE_P"] / 0.8,
                      MC_ROLLRATE_D=0.15 * params["MC_ROLLRATE_P"] * models["roll"]["T_prop"],
                      MC_ROLLRATE_FF=0.1 * params["MC_ROLLRATE_P"])
    if effects:  # gains for the filtered, steeper process the effects make
        G, w = onboard_process(af, Loop.ROLL, params)
        best = optimal_pd(G, w).pd
        params.update(MC_ROLL_P=best.Kc / best.Kd, MC_ROLLRATE_P=best.Kd)
    G, w = onboard_process(af, Loop.ROLL, params)
    Cr, Cy = onboard_controller(af, Loop.ROLL, params, w)
    T = G * Cr / (1 + G * Cy)
    # at the closed loop's -90 deg frequency the structure (filters, hold) shows most
    ph = np.degrees(np.unwrap(np.angle(T)))
    i = int(np.argmax(ph < -90.0))
    f = w[i] / (2 * np.pi)
    gain, phase = _sine_response(af, params, 0, f)
    assert gain == pytest.approx(abs(T[i]), rel=0.08), (af.description, f)
    assert phase == pytest.approx(ph[i], abs=4.0), (af.description, f)
    onb = score_written(af, params, [Loop.ROLL])[Loop.ROLL].onboard
    if effects:  # gains designed without the undeclared low-pass lose their margin on it
        blind = score_written(af, _written(af, gains), [Loop.ROLL])[Loop.ROLL].onboard
        assert onb.pm_deg == pytest.approx(20.0, abs=0.5) and blind.pm_deg < 10.0
        return
    # the onboard score sees what the structure costs against a plain PD at 1 kHz
    plain = replace(af, onboard=OnboardSpec())
    ref = score_written(plain, _written(af, gains), [Loop.ROLL])[Loop.ROLL].onboard
    assert onb.pm_deg < ref.pm_deg


def test_rate_d_on_the_error_of_the_ardupilot_like_cascade_is_what_scoring_predicts():
    # ArduCopter's AC_PID differentiates the rate error (FLTT-filtered target less the gyro),
    # low-passed at FLTD; the simulated ArduPilot-like cascade does the same, and the scoring's
    # linear model of it matches the simulated response with the rate D a tune writes
    from mrft_gcs.flight.structure import RATE_D_OVER_P_S

    af = _pick("ardupilot", 250.0)
    models = af.linear_models()
    params = _written(af, _gains_for(models))
    params.update({n: v for n, v in ParamStore(af.hover_thrust, af.onboard).values.items()
                   if n.startswith("ATC_")})
    params["MC_ROLLRATE_D"] = 2 * RATE_D_OVER_P_S * params["MC_ROLLRATE_P"]
    G, w = onboard_process(af, Loop.ROLL, params)
    Cr, Cy = onboard_controller(af, Loop.ROLL, params, w)
    T = G * Cr / (1 + G * Cy)
    ph = np.degrees(np.unwrap(np.angle(T)))
    nd = dict(params, MC_ROLLRATE_D=0.0)
    Cr0, Cy0 = onboard_controller(af, Loop.ROLL, nd, w)
    T0 = G * Cr0 / (1 + G * Cy0)
    for frac in (-45.0, -90.0):
        i = int(np.argmax(ph < frac))
        f = w[i] / (2 * np.pi)
        gain, phase = _sine_response(af, params, 0, f)
        assert gain == pytest.approx(abs(T[i]), rel=0.08), (af.description, f)
        assert phase == pytest.approx(ph[i], abs=4.0), (af.description, f)
    # and D shows: without it the prediction at the last point is another one
    assert abs(np.degrees(np.angle(T0[i] / T[i]))) > 4.0 or abs(abs(T0[i]) / abs(T[i]) - 1) > 0.08
