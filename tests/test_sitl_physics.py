"""The simulated vehicle against the linear models of SPEC section 2 (small signals).

Each check drives the physics with a small pulse around hover and compares the measured
response with the response of the model that :meth:`Airframe.linear_models` predicts.
Tolerance: normalised RMS error below 3 % (measured: about 0.2-1.5 %).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import signal

from mrft_gcs.errors import UsageError
from mrft_gcs.sitl import FlightMode, Multirotor, SimVehicle, load_airframe

VEHICLES = ("qdrone", "racer250", "f550")
DT = 0.001
TOL = 0.03


def linear_response(model: dict[str, float], u: np.ndarray, dt: float = DT) -> np.ndarray:
    """Response of ``K e^{-tau s} / (s (T_prop s + 1)(T1 s + 1))`` (or the side model)."""
    if "T_prop" in model:
        den = np.polymul([1.0, 0.0], np.polymul([model["T_prop"], 1.0], [model["T1"], 1.0]))
    else:
        den = np.polymul([1.0, 0.0], [model["T2"], 1.0])
    t = np.arange(len(u)) * dt
    _, y, _ = signal.lsim(([model["K"]], den), u, t)
    d = int(round(model["tau"] / dt))
    return np.concatenate([np.zeros(d), y[: len(y) - d]])


def nrms(y: np.ndarray, ref: np.ndarray) -> float:
    return float(np.sqrt(np.mean((y - ref) ** 2)) / np.sqrt(np.mean(ref**2)))


def pulse(n: int, amp: float, start: int = 50, width: int = 200) -> np.ndarray:
    u = np.zeros(n)
    u[start : start + width] = amp
    return u


@pytest.mark.parametrize("name", VEHICLES)
@pytest.mark.parametrize("axis", ("roll", "pitch", "altitude"))
def test_inner_loops_match_linear_model(name, axis):
    af = load_airframe(name).quiet()
    model = af.linear_models()[axis]
    m = Multirotor(af)
    m.reset((0.0, 0.0, -5.0), airborne=True)
    n = 1000
    amp = 0.02 if axis != "altitude" else 0.03 * af.hover_thrust
    u = pulse(n, amp)
    y = np.empty(n)
    for k in range(n):
        if axis == "roll":
            m.step(u[k], 0.0, 0.0, af.hover_thrust)
            y[k] = m.meas_att[0]
        elif axis == "pitch":
            m.step(0.0, u[k], 0.0, af.hover_thrust)
            y[k] = m.meas_att[1]
        else:
            m.step(0.0, 0.0, 0.0, af.hover_thrust + u[k])
            y[k] = -m.meas_posv[2] - 5.0
    err = nrms(y, linear_response(model, u))
    assert err < TOL, f"{name} {axis}: normalised RMS error {err:.4f}"


@pytest.mark.parametrize("name", VEHICLES)
@pytest.mark.parametrize("axis", ("x", "y"))
def test_side_motion_matches_linear_model(name, axis):
    """Closed attitude loop (onboard, PX4 defaults) -> measured angle -> side model -> position."""
    af = load_airframe(name).quiet()
    model = af.linear_models()[axis]
    v = SimVehicle(af)
    v.reset((0.0, 0.0, -5.0), airborne=True)
    ap = v.autopilot
    n = 1500
    setpoint = pulse(n, 0.03, start=50, width=400)
    ap.set_attitude_target((1.0, 0.0, 0.0, 0.0), af.hover_thrust)
    ap.update(0.0, v.physics.meas_att, v.physics.meas_posv, False)
    assert ap.arm(True) is not None
    assert ap.set_mode(FlightMode.OFFBOARD).name == "ACCEPTED"
    angle = np.empty(n)
    pos = np.empty(n)
    for k in range(n):
        a = setpoint[k]
        roll, pitch = (a, 0.0) if axis == "y" else (0.0, -a)  # nose-down moves +x
        cr, sr = math.cos(roll / 2), math.sin(roll / 2)
        cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
        ap.set_attitude_target((cr * cp, sr * cp, cr * sp, -sr * sp), af.hover_thrust)
        v.step()
        att, posv = v.physics.meas_att, v.physics.meas_posv
        angle[k] = att[0] if axis == "y" else -att[1]
        pos[k] = posv[1] if axis == "y" else posv[0]
    assert np.max(np.abs(angle)) > 0.02  # the attitude loop did follow
    err = nrms(pos, linear_response(model, angle))
    assert err < TOL, f"{name} {axis}: normalised RMS error {err:.4f}"


@pytest.mark.parametrize("name", VEHICLES)
def test_linear_models_inside_table_one(name):
    from mrft_gcs.domains import AIRFRAME_RANGES, D_ALT, D_ATT, D_SIDE

    af = load_airframe(name)
    lm = af.linear_models()
    for axis in ("roll", "pitch"):
        p = [lm[axis][k] for k in D_ATT.names]
        assert D_ATT.contains(np.array(p))[0], (axis, p)
    p = [lm["altitude"][k] for k in D_ALT.names]
    assert D_ALT.contains(np.array(p))[0], p
    for axis in ("x", "y"):
        p = [lm[axis][k] for k in D_SIDE.names]
        assert D_SIDE.contains(np.array(p))[0], (axis, p)
    lo, hi = AIRFRAME_RANGES["thrust_to_weight"]
    assert lo <= af.thrust_to_weight <= hi
    lo, hi = AIRFRAME_RANGES["motor_distance_m"]
    assert lo <= 2 * af.arm_length_m <= hi
    lo, hi = AIRFRAME_RANGES["inertia_kg_m2"]
    assert all(lo <= i <= hi for i in af.inertia_kg_m2[:2])


def test_rests_on_ground_and_lifts_off_only_above_weight():
    af = load_airframe("qdrone").quiet()
    m = Multirotor(af)
    m.reset()
    for _ in range(300):
        m.step(0.0, 0.0, 0.0, 0.95 * af.hover_thrust)
    assert m.on_ground and m.pos[2] == 0.0
    for _ in range(1000):
        m.step(0.0, 0.0, 0.0, 1.2 * af.hover_thrust)
    assert not m.on_ground and m.pos[2] < -0.1
    for _ in range(3000):  # motors off: falls and stops on the floor
        m.step(0.0, 0.0, 0.0, 0.0)
    assert m.on_ground and m.pos[2] == 0.0 and np.allclose(m.vel, 0.0)


def test_same_seed_same_run_and_noise_present():
    af = load_airframe("qdrone")
    runs = []
    for seed in (3, 3, 4):
        m = Multirotor(af, seed=seed)
        m.reset((0.0, 0.0, -2.0), airborne=True)
        for _ in range(200):
            m.step(0.01, 0.0, 0.0, af.hover_thrust)
        runs.append(m.meas_att)
    assert runs[0] == runs[1]
    assert runs[0] != runs[2]


def _roll_after(af, steps=400, u=0.0):
    m = Multirotor(af)
    m.reset((0.0, 0.0, -5.0), airborne=True)
    for _ in range(steps):
        m.step(u, 0.0, 0.0, af.hover_thrust)
    return m


@pytest.mark.parametrize("effect,value", [
    ("com_offset", 0.01), ("motor_deadzone", 0.05), ("torque_rate_limit", 0.5),
    ("motor_saturation", 0.5), ("sensor_lpf", 5.0), ("thrust_curve", 0.5),
    ("quadratic_drag", 2.0),
])
def test_each_effect_changes_the_response(effect, value):
    base = load_airframe("qdrone").quiet()
    m0 = _roll_after(base, u=0.1)
    m1 = _roll_after(base.with_effects({effect: value}), u=0.1)
    if effect == "quadratic_drag":  # needs speed: compare horizontal velocity after a tilt
        m0 = _roll_after(base, steps=1500, u=0.02)
        m1 = _roll_after(base.with_effects({effect: value}), steps=1500, u=0.02)
        assert abs(m1.vel[1]) < abs(m0.vel[1]) * 0.99
    else:
        assert abs(m1.meas_att[0] - m0.meas_att[0]) > 1e-3 or abs(
            m1.pos[2] - m0.pos[2]) > 1e-3, effect
    assert base.with_effects({effect: value}).effects.active() == {effect: value}


def test_com_offset_is_an_input_bias():
    m = _roll_after(load_airframe("qdrone").quiet().with_effects({"com_offset": 0.01}))
    # CoM right of and ahead of the thrust centre: rolls right, pitches nose down
    assert m.meas_att[0] > 0.01 and m.meas_att[1] < -0.01


def test_wind_pushes_the_vehicle():
    af = load_airframe("qdrone").quiet()
    m = Multirotor(af, wind_m_s=(2.0, 0.0, 0.0))
    m.reset((0.0, 0.0, -5.0), airborne=True)
    for _ in range(500):
        m.step(0.0, 0.0, 0.0, af.hover_thrust)
    assert m.vel[0] > 0.5


def test_bad_effect_is_usage_error():
    af = load_airframe("qdrone")
    with pytest.raises(UsageError, match="known effects"):
        af.with_effects({"warp_drive": 1.0})
    with pytest.raises(UsageError, match="motor_saturation"):
        af.with_effects({"motor_saturation": 0.0})
