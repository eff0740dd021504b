"""The RotorPy physics backend in-process: frames, its hover linearisation (the truth a tune
is scored on) against RotorPy's own response, the fixed-step integrator against RotorPy's
``Multirotor.step``, and the errors a user can hit."""

from __future__ import annotations

import dataclasses
import math
import os
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import signal

pytest.importorskip("rotorpy", reason="RotorPy is in the test extra: pip install -e '.[test]'")
sys.path.insert(0, str(Path(__file__).parent))  # the sitl_cli helper

from mrft_gcs.cli import main  # noqa: E402
from mrft_gcs.errors import UsageError  # noqa: E402
from mrft_gcs.sitl.population import domain_check  # noqa: E402
from mrft_gcs.sitl.process import SitlConfig, build_vehicle  # noqa: E402
from mrft_gcs.sitl.rotorpy_physics import (  # noqa: E402
    ROTORPY_VEHICLES,
    RotorpyMultirotor,
    rotorpy_airframe,
    rotorpy_vehicle,
)

DT = 0.004


def _quiet(name: str):
    """The set as shipped, without delays and noise, so the response is RotorPy's alone."""
    spec = rotorpy_airframe(name)
    af = dataclasses.replace(spec.airframe.quiet(), actuator_delay_s=0.0,
                             attitude_sensor_delay_s=0.0, position_sensor_delay_s=0.0)
    return dataclasses.replace(spec, airframe=af)


def _linear(model: dict, u: float, t: np.ndarray) -> np.ndarray:
    k, tp, t1 = model["K"], model["T_prop"], model["T1"]
    # from t = 0: scipy starts the simulation at T[0]
    _, y = signal.step(signal.lti([k * u], [tp * t1, tp + t1, 1.0, 0.0]), T=np.r_[0.0, t])
    return y[1:]


@pytest.mark.parametrize("name", ROTORPY_VEHICLES)
def test_linearisation_matches_rotorpys_response_at_hover(name):
    """Small torque and thrust steps from hover: RotorPy's angle and height follow the
    airframe's linear models (the scoring truth) to within 2 % over 0.3 s."""
    spec = _quiet(name)
    models = spec.airframe.linear_models()
    hover = spec.airframe.hover_thrust
    n = int(0.3 / DT)
    t = DT * np.arange(1, n + 1)
    for axis, cmd in (("roll", (0.01, 0.0, 0.0, hover)), ("pitch", (0.0, 0.01, 0.0, hover)),
                      ("altitude", (0.0, 0.0, 0.0, hover + 0.01))):
        ph = RotorpyMultirotor(spec, dt_s=DT)
        ph.reset((0.0, 0.0, -2.0), airborne=True)
        out = []
        for _ in range(n):
            ph.step(*cmd)
            r, p, _ = ph.euler
            out.append({"roll": r, "pitch": p, "altitude": -2.0 - ph.pos[2]}[axis])
        # RotorPy's g (9.81) against the hover thrust of g0 (9.80665): a tiny sink to remove
        if axis == "altitude":
            ref = RotorpyMultirotor(spec, dt_s=DT)
            ref.reset((0.0, 0.0, -2.0), airborne=True)
            drift = []
            for _ in range(n):
                ref.step(0.0, 0.0, 0.0, hover)
                drift.append(-2.0 - ref.pos[2])
            out = list(np.subtract(out, drift))
        lin = _linear(models[axis], 0.01, t)
        assert np.max(np.abs(np.array(out) - lin)) < 0.02 * np.max(np.abs(lin)), axis


def test_frames_are_ned_frd():
    spec = _quiet("crazyfliebrushless")
    hover = spec.airframe.hover_thrust
    ph = RotorpyMultirotor(spec, dt_s=DT)
    ph.reset((0.0, 0.0, -1.0), airborne=True)
    for _ in range(60):
        ph.step(0.01, 0.0, 0.0, hover)
    roll, _, _ = ph.euler
    assert roll > 0.05 and ph.rates[0] > 0 and ph.vel[1] > 0  # right wing down, moves east
    ph.reset((0.0, 0.0, -1.0), airborne=True)
    for _ in range(60):
        ph.step(0.0, 0.01, 0.0, hover)
    assert ph.euler[1] > 0.05 and ph.vel[0] < 0  # nose up, moves south
    ph.reset((0.0, 0.0, -1.0), airborne=True)
    for _ in range(60):
        ph.step(0.0, 0.0, 0.05, hover)
    assert ph.rates[2] > 0 and ph.euler[2] > 0  # yaw clockwise seen from above
    ph.reset((0.0, 0.0, -1.0), airborne=True)
    for _ in range(60):
        ph.step(0.0, 0.0, 0.0, 1.3 * hover)
    assert ph.pos[2] < -1.02 and ph.vel[2] < 0  # climbs: z down is negative
    sf = ph.meas.specific_force_body
    assert sf[2] < -9.81  # accelerometer: more than 1 g of thrust, along -z body


def test_on_ground_at_rest_until_thrust_lifts_it():
    spec = _quiet("crazyfliebrushless")
    ph = RotorpyMultirotor(spec, dt_s=DT)
    ph.reset()
    for _ in range(100):
        ph.step(0.0, 0.0, 0.0, 0.5 * spec.airframe.hover_thrust)
    assert ph.on_ground and ph.pos[2] == 0.0
    for _ in range(150):
        ph.step(0.0, 0.0, 0.0, 1.5 * spec.airframe.hover_thrust)
    assert not ph.on_ground and ph.pos[2] < -0.05


@pytest.mark.parametrize("name", ROTORPY_VEHICLES)
def test_fixed_step_integrator_agrees_with_rotorpys_own_step(name):
    spec = _quiet(name)
    hover = spec.airframe.hover_thrust
    traces = {}
    for integrator in ("rk2", "rotorpy"):
        ph = RotorpyMultirotor(spec, dt_s=DT, integrator=integrator)
        ph.reset((0.0, 0.0, -1.0), airborne=True)
        tr = []
        for i in range(200):  # a relay-like square wave on every axis
            u = 0.03 if (i // 25) % 2 == 0 else -0.03
            ph.step(u, -0.5 * u, 0.2 * u, hover * (1 + 0.5 * u))
            tr.append((*ph.euler, *ph.pos))
        traces[integrator] = np.array(tr)
    span = np.ptp(traces["rotorpy"], axis=0)
    err = np.max(np.abs(traces["rk2"] - traces["rotorpy"]), axis=0)
    assert np.all(err <= 0.01 * span + 1e-6), (err, span)


def test_seeded_vehicles_are_reproducible_and_valid():
    a, b = rotorpy_airframe(seed=4), rotorpy_airframe(seed=4)
    assert a.airframe == b.airframe and a.name == ROTORPY_VEHICLES[4 % 3]
    assert a.airframe.name == "rotorpy-crazyflie-4"
    assert rotorpy_airframe(seed=5).airframe != a.airframe
    # the shipped brushless set lies in Table I's domain; the others do not, for stated reasons
    assert domain_check(rotorpy_airframe("crazyfliebrushless").airframe).in_domain
    why = {n: domain_check(rotorpy_airframe(n).airframe).reasons for n in ROTORPY_VEHICLES}
    assert any("T_prop" in r for r in why["hummingbird"])
    assert any("T1" in r for r in why["crazyflie"])


def test_vehicle_steps_at_the_onboard_loop_rate_and_hovers_on_its_autopilot():
    from mrft_gcs.sitl.onboard import FlightMode

    v = build_vehicle(SitlConfig(physics="rotorpy"))
    assert v.dt == pytest.approx(1.0 / v.airframe.onboard.loop_hz) and v.control_every == 1
    v.reset((0.0, 0.0, -1.0), airborne=True)
    v.step()  # the land detector sees it airborne
    ap = v.autopilot
    ap.arm(True)
    ap.set_mode(FlightMode.POSCTL)
    v.run(3.0)
    assert math.dist(v.physics.pos, (0.0, 0.0, -1.0)) < 0.1
    assert max(abs(a) for a in v.physics.euler[:2]) < math.radians(3)


def test_errors_are_one_line_usage_errors():
    with pytest.raises(UsageError, match="unknown RotorPy vehicle 'qdrone'"):
        rotorpy_airframe("qdrone")
    with pytest.raises(UsageError, match="not available with --physics rotorpy"):
        spec = rotorpy_airframe()
        rotorpy_vehicle(dataclasses.replace(
            spec, airframe=spec.airframe.with_effects({"thrust_curve": 0.5})))
    with pytest.raises(UsageError, match="physics 'bullet'"):
        build_vehicle(SitlConfig(physics="bullet"))
    assert main(["sitl", "--physics", "rotorpy", "--vehicle", "qdrone"]) == 2
    assert main(["sitl", "--physics", "bullet"]) == 2


def test_without_rotorpy_the_error_names_the_extra(monkeypatch):
    from mrft_gcs.errors import MissingDependency
    from mrft_gcs.sitl.rotorpy_physics import rotorpy_params

    monkeypatch.setitem(sys.modules, "rotorpy.vehicles.crazyflie_params", None)
    with pytest.raises(MissingDependency, match=r"pip install 'mrft-gcs\[test\]'"):
        rotorpy_params("crazyflie")


# --------------------------------------------------------------------------- live over UDP
def test_cli_serves_rotorpy_physics_over_mavlink_and_stops_on_sigterm():
    import signal as sig

    from pymavlink import mavutil
    from pymavlink.dialects.v20 import common as M
    from sitl_cli import start_sitl_cli

    from mrft_gcs.sitl.process import free_udp_port

    port = free_udp_port()
    proc, text = start_sitl_cli("--physics", "rotorpy", "--port", str(port))
    gcs = None
    try:
        assert "rotorpy-crazyfliebrushless" in text and "RotorPy" in text, text
        assert "in-domain" in text, text
        gcs = mavutil.mavlink_connection(f"udp:127.0.0.1:{port}", source_system=255)
        hb = gcs.recv_match(type="HEARTBEAT", blocking=True, timeout=10)
        assert hb is not None and hb.autopilot == M.MAV_AUTOPILOT_PX4
        gcs.mav.param_request_read_send(1, 1, b"MPC_THR_HOVER", -1)
        pv = gcs.recv_match(type="PARAM_VALUE", blocking=True, timeout=5)
        af = rotorpy_airframe().airframe
        assert pv is not None and pv.param_value == pytest.approx(
            round(af.hover_thrust, 2), abs=1e-6)
        proc.send_signal(sig.SIGTERM)
        assert proc.wait(10) == 0
    finally:
        if gcs is not None:
            gcs.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait()


#: The live tune of the RotorPy vehicle runs only when asked (``MRFT_LIVE_ROTORPY=1``): the
#: shipped brushless Crazyflie is small and quick enough that a real-time tune over UDP is
#: marginal on a shared 2-core host (tilt aborts at 35 deg in about a third of live runs,
#: docs/sitl.md); the lockstep test below tunes the same vehicle in CI.
LIVE = os.environ.get("MRFT_LIVE_ROTORPY") == "1"


@pytest.fixture(scope="module")
def tuned_rotorpy(tmp_path_factory):
    """One full tune of the RotorPy-backed SITL process, torque path, bundled classifiers;
    then the vehicle's parameters read back over a new link."""
    from mrft_gcs.flight import tune
    from mrft_gcs.link import VehicleLink
    from mrft_gcs.params import ParamClient
    from mrft_gcs.sitl import SitlProcess

    folder = tmp_path_factory.mktemp("rotorpy")
    with SitlProcess(physics="rotorpy", port=None, seed=1) as sitl:
        assert sitl.command()[-2:] == ["--physics", "rotorpy"]
        result = tune(sitl.connection_string, "sitl", actuation="torque", backup_dir=folder)
        with VehicleLink.connect(sitl.connection_string) as link:
            params = {n: p.value for n, p in ParamClient(link).read_all().items()}
    return result, params, sitl.airframe


@pytest.mark.skipif(not LIVE, reason="live RotorPy tune: set MRFT_LIVE_ROTORPY=1 (marginal in "
                    "real time on a shared host; the lockstep tune runs instead)")
def test_tune_of_rotorpy_vehicle_writes_gains_that_hold_on_its_truth(tuned_rotorpy):
    """The written gains scored on the loops the onboard autopilot closes with them around
    RotorPy's dynamics (linearised at hover). The bars here (stable, PM >= 10 deg,
    J <= 20 %) catch a broken tune; the issue's bars (PM >= 15, J <= 10) are what
    ``benchmarks/tune_thirdparty.py`` reports against."""
    from mrft_gcs.flight.scoring import score_written
    from mrft_gcs.loops import Loop

    result, params, af = tuned_rotorpy
    assert result.status == "ok" and result.actuation == "torque"
    assert result.max_tilt_deg < 35 and result.hover_error_m < 0.3
    loops = (Loop.ROLL, Loop.PITCH, Loop.ALTITUDE, Loop.X, Loop.Y)
    for lp in loops:
        lr = result.loops[lp]
        assert lr.state == "tuned" and lr.gains is not None and lr.gains.Kc > 0, lp
    for c in result.parameters:  # written and read back
        assert params[c.name] == pytest.approx(c.new, rel=1e-6, abs=1e-9)
    identified = {lp: result.loops[lp].identification.gains for lp in loops}
    scores = score_written(af, params, loops, identified=identified)
    for lp, s in scores.items():
        assert s.onboard.stable, lp
        assert s.onboard.pm_deg >= 10.0 and s.onboard.J_pct <= 20.0, (lp, s.onboard)
    for lp in (Loop.ROLL, Loop.PITCH):  # the in-air check measured the written loop
        ver = result.loops[lp].verification
        assert ver is not None and math.isfinite(ver.measured_pm_deg), lp


def test_lockstep_benchmark_tunes_the_in_domain_rotorpy_set():
    """benchmarks/tune_thirdparty.py --mode lockstep on the shipped brushless Crazyflie:
    simulated time, so the figures do not depend on the host."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import tune_thirdparty as tt

    r = tt.run_lockstep("crazyfliebrushless", None)
    assert r["vehicle"] == "rotorpy-crazyfliebrushless" and r["category"] == "in-domain"
    assert r["outcome"] == "completed", r["reason"]
    assert set(r["loops"]) == {"roll", "pitch", "altitude", "x", "y"}
    for name, fig in r["loops"].items():
        assert fig["onboard_stable"] and fig["onboard_pm_deg"] >= 10.0, (name, fig)
    assert r["time_to_tune_s"] < 20 and r["max_tilt_deg"] < 35
    assert "completed" in tt.line(r)


def test_the_benchmark_scores_the_delays_the_vehicle_realises():
    """RotorPy is stepped once per onboard loop period, so its delays are whole periods (the
    shipped sets' 2 ms sensor delay is none at 250 Hz). ``tune_thirdparty`` scores on those:
    the in-air check flown in-process on that vehicle then reads the margin of that truth."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import tune_thirdparty as tt
    from flight_sim import fly_roll_check

    from mrft_gcs.flight.inair import AGREE_DEG
    from mrft_gcs.flight.scoring import score_written
    from mrft_gcs.loops import Loop
    from mrft_gcs.pd_design import frequency_grid, optimal_pd
    from mrft_gcs.plant import PD, InnerModel, inner_response
    from mrft_gcs.profiles import PDGains, gains_to_params, load_profile
    from mrft_gcs.sitl.onboard import ParamStore

    spec = rotorpy_airframe("crazyfliebrushless")
    af = spec.airframe
    real = tt.realised(af)
    period = 1.0 / af.onboard.loop_hz
    for d in (real.actuator_delay_s, real.attitude_sensor_delay_s, real.position_sensor_delay_s):
        assert d / period == pytest.approx(round(d / period))
    assert real.attitude_sensor_delay_s == 0.0 < af.attitude_sensor_delay_s
    # gains designed on a model with a little more lag than the truth (as identified live)
    m = InnerModel(648.9, 0.0412, 0.947, 0.0074)
    w = frequency_grid(m.T_prop, m.T1, m.tau)
    g = optimal_pd(inner_response(m.K, m.T_prop, m.T1, m.tau, w)[0], w).pd
    _, check = fly_roll_check(rotorpy_vehicle(spec, seed=0), af.hover_thrust,
                              PD(g.Kc, g.Kd), m, level_ticks=250)
    prm = dict(ParamStore(af.hover_thrust, af.onboard).values)
    prm.update(gains_to_params(load_profile("sitl"), {Loop.ROLL: PDGains(g.Kc, g.Kd)},
                               prm["MPC_THR_HOVER"]))
    truth = score_written(real, prm, [Loop.ROLL])[Loop.ROLL].onboard.pm_deg
    assert check.steady and abs(check.measured_pm_deg - truth) < AGREE_DEG, (check, truth)
