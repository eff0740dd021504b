"""End to end over loopback UDP against the SITL subprocess: tune, report, read-back, faults.

Until the bundled classifiers exist (``models/manifest.json``), the full tunes inject the
truth identifier (a test double, see ``flight_sim``); the test with the bundled classifiers
runs as soon as they land.
"""

import json
import math
import sys
import threading
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from flight_sim import (  # noqa: E402
    ALT_RELAY,
    ATT_RELAY,
    SIDE_RELAY,
    again_if_host_stalled,
    truth_identifier,
)

from mrft_gcs.cli import main  # noqa: E402
from mrft_gcs.errors import SafetyAbort  # noqa: E402
from mrft_gcs.flight import tune  # noqa: E402
from mrft_gcs.flight.inair import PASS_PM_DEG  # noqa: E402
from mrft_gcs.flight.plot import plot_cycles  # noqa: E402
from mrft_gcs.flight.report import report_dict, write_report  # noqa: E402
from mrft_gcs.flight.safety import LimitExceeded  # noqa: E402
from mrft_gcs.link import VehicleLink  # noqa: E402
from mrft_gcs.loops import Loop, LoopKind  # noqa: E402
from mrft_gcs.params import ParamClient  # noqa: E402
from mrft_gcs.sitl import SitlProcess  # noqa: E402

RELAY = {LoopKind.ATTITUDE: ATT_RELAY, LoopKind.ALTITUDE: ALT_RELAY, LoopKind.SIDE: SIDE_RELAY}
MODELS = Path(__file__).resolve().parents[1] / "models" / "manifest.json"


def _truth(vehicle):
    ti = truth_identifier(vehicle)
    return lambda loop, snap, inner: ti(loop, snap, inner)


@pytest.fixture(scope="module")
def tuned(tmp_path_factory):
    def flight():
        folder = tmp_path_factory.mktemp("tune")  # each flight its own backups
        with SitlProcess(vehicle="qdrone", port=None, seed=3) as sitl:
            result = tune(sitl.connection_string, "sitl", backup_dir=folder, relay=RELAY,
                          identifier=_truth("qdrone"), hover_check_s=2.0)
            with VehicleLink.connect(sitl.connection_string) as link:
                readback = ParamClient(link).read_many([c.name for c in result.parameters])
                mode = link.heartbeat.custom_mode
        return result, readback, mode, folder

    return again_if_host_stalled(flight)


def test_tune_over_udp_report_and_readback(tuned):
    result, readback, mode, folder = tuned
    assert result.status == "ok"
    assert 0 < result.duration_s < 25
    assert result.max_tilt_deg < 35
    assert result.hover_error_m < 0.2  # held in POSCTL near the entry point on the new gains
    assert (mode >> 16) & 0xFF == 3  # POSCTL
    assert result.stream.rate_hz_achieved > 200
    names = {c.name for c in result.parameters}
    assert {"MC_ROLL_P", "MC_PITCHRATE_P", "MPC_Z_P", "MPC_XY_VEL_P_ACC"} <= names
    for c in result.parameters:
        assert readback[c.name].value == pytest.approx(c.new, rel=1e-6, abs=1e-9)
    assert Path(result.backup).is_file() and Path(result.tlog).stat().st_size > 10_000
    rep = report_dict(result)
    text = json.dumps(rep, allow_nan=False)  # no NaN anywhere
    assert json.loads(text)["schema"] == "mrft-gcs/tune-report/1"
    assert set(rep["loops"]) == {"roll", "pitch", "altitude", "x", "y"}
    for name, loop in rep["loops"].items():
        for key in ("model", "class", "confidence", "beta", "h", "period_s", "amplitude",
                    "gains", "residual"):
            assert key in loop, (name, key)
        assert loop["state"] == "tuned" and loop["gains"]["Kc"] > 0
        assert set(loop["residual"]) == {"rms_before", "rms_after", "effect", "effect_params"}
    for name in ("roll", "pitch"):  # measured in the air on the autopilot's own loop
        ver = rep["loops"][name]["verification"]
        assert ver["passed"] and ver["method"].startswith("square wave")
        assert ver["measured_pm_deg"] >= 15 and ver["predicted_pm_deg"] >= 15
        assert "ATTITUDE_TARGET" in ver["note"]  # the vehicle's own record was the input
    for name in ("altitude", "x", "y"):  # checked by the hover on the written gains
        ver = rep["loops"][name]["verification"]
        assert ver["passed"] and ver["method"].startswith("hover") and ver["note"]
    assert set(rep["loops"]["x"]["model"]) == {"K", "T2", "tau"}
    assert set(rep["loops"]["roll"]["model"]) == {"K", "T_prop", "T1", "tau"}
    firmware = rep["vehicle"].pop("firmware")
    assert rep["vehicle"] == {"connection": result.connection, "autopilot": "px4",
                              "profile": "sitl", "actuation": "torque"}
    # the bundled SITL answers AUTOPILOT_VERSION as a PX4 1.13
    assert firmware["autopilot"] == "px4" and firmware["source"] == "AUTOPILOT_VERSION"
    assert rep["hover_check"]["passed"] and rep["hover_check"]["min_height_m"] > 0.3
    assert rep["parameters"][0].keys() == {"name", "old", "new", "on_vehicle"}
    assert all(p["on_vehicle"] == p["new"] for p in rep["parameters"])  # no comparison: kept
    assert write_report(result, folder / "r.json").is_file()
    png = plot_cycles(result, folder / "cycles.png")
    assert png.read_bytes()[:4] == b"\x89PNG"


def test_inair_check_undoes_a_retarget_that_went_too_far(tmp_path):
    """The busy-host failure: the written gains re-targeted by 12 ms of GCS delay the
    vehicle never had (on qdrone's 22 ms loop, no margin left onboard). The in-air check
    finds the written loop unsteady (or steady with a few degrees of margin), backs the gains
    off and measures them; the gains left on the vehicle keep their margin on the true model."""
    from mrft_gcs.flight.scoring import score_gains
    from mrft_gcs.sitl import load_airframe

    with SitlProcess(vehicle="qdrone", port=None, seed=5) as sitl:
        result = tune(sitl.connection_string, "sitl", backup_dir=tmp_path, relay=RELAY,
                      identifier=_truth("qdrone"), hover_check_s=1.0, gcs_delay_s=0.012,
                      residuals=False)
        with VehicleLink.connect(sitl.connection_string) as link:
            readback = ParamClient(link).read_many(["MC_ROLL_P", "MC_ROLLRATE_P"])
    assert result.status == "ok"
    models = load_airframe("qdrone").linear_models()
    scores = score_gains(models, {lp: result.loops[lp].gains for lp in (Loop.ROLL, Loop.PITCH)})
    for lp in (Loop.ROLL, Loop.PITCH):
        ver = result.loops[lp].verification
        assert ver is not None and ver.passed and "re-designed" in ver.action, ver
        # what the first check found: no steady response, or a steady one short of the margin
        first = ver.action.split(": PM ", 1)[1].split(" -> ")[0]
        assert first == "no steady response" or float(first) < PASS_PM_DEG, ver.action
        assert scores[lp].pm_deg >= 15
        assert abs(ver.measured_pm_deg - scores[lp].pm_deg) < 4.0
    roll = result.loops[Loop.ROLL].gains
    assert readback["MC_ROLLRATE_P"].value == pytest.approx(roll.Kd, rel=1e-5)
    assert readback["MC_ROLL_P"].value == pytest.approx(roll.Kc / roll.Kd, rel=1e-5)
    old = {c.name: c.old for c in result.parameters}
    assert old["MC_ROLL_P"] == pytest.approx(6.5)  # the value from before the tune


def test_tune_only_the_requested_loops(tmp_path):
    """x/y not requested: not relay-tested; roll is flown and identified but not written."""
    with SitlProcess(vehicle="qdrone", port=None, seed=7) as sitl:
        with VehicleLink.connect(sitl.connection_string) as link:
            before = ParamClient(link).read_many(["MC_ROLL_P", "MPC_XY_P"])
        result = tune(sitl.connection_string, "sitl", backup_dir=tmp_path, relay=RELAY,
                      identifier=_truth("qdrone"), hover_check_s=1.0,
                      loops=["altitude", "pitch"], residuals=False)
        with VehicleLink.connect(sitl.connection_string) as link:
            after = ParamClient(link).read_many(["MC_ROLL_P", "MPC_XY_P", "MC_PITCH_P"])
    assert result.status == "ok" and result.hover_error_m < 0.3
    names = {c.name for c in result.parameters}
    assert {"MC_PITCH_P", "MC_PITCHRATE_P", "MPC_Z_P"} <= names
    assert not names & {"MC_ROLL_P", "MC_ROLLRATE_P", "MPC_XY_P", "MPC_XY_VEL_P_ACC"}
    for name in ("MC_ROLL_P", "MPC_XY_P"):
        assert after[name].value == before[name].value
    assert after["MC_PITCH_P"].value != before["MC_ROLL_P"].value  # written (was the default)
    loops = report_dict(result)["loops"]
    for lp in ("x", "y"):
        assert loops[lp]["state"] == "left alone" and "not requested" in loops[lp]["note"]
        assert result.loops[Loop(lp)].cycles is None  # never relay-tested
    assert loops["roll"]["state"] == "tuned" and "not written" in loops["roll"]["note"]


def test_wrong_hover_estimate_is_learnt_before_the_altitude_relay(tmp_path):
    """The autopilot's hover estimate 15 % low (a fresh airframe's default, a new battery):
    the climb learns the thrust that holds the vehicle and the altitude relay is biased at
    it. Before, the relay biased at the estimate sank, ran away three times and the tune
    ended in 'no steady relay oscillation' (measured live on qdrone)."""
    from mrft_gcs.sitl import load_airframe

    true_hover = load_airframe("qdrone").hover_thrust
    with SitlProcess(vehicle="qdrone", port=None, seed=1) as sitl:
        with VehicleLink.connect(sitl.connection_string) as link:
            ParamClient(link).write({"MPC_THR_HOVER": round(0.85 * true_hover, 3)}, tmp_path)
        result = tune(sitl.connection_string, "sitl", backup_dir=tmp_path, relay=RELAY,
                      identifier=_truth("qdrone"), hover_check_s=1.0, loops=["altitude"],
                      residuals=False)
    assert result.status == "ok", result.notes
    alt = result.loops[Loop.ALTITUDE]
    assert alt.state == "tuned"
    assert alt.bias == pytest.approx(true_hover, rel=0.05)  # learnt, not the 0.85 estimate


def _failing(vehicle, times):
    """The truth identifier, but altitude's first ``times`` identifications raise a bare
    ValueError (as a numerical failure inside the harmonic fits did twice under stalls)."""
    ti, calls = truth_identifier(vehicle), []

    def ident(loop, snap, inner):
        if loop is Loop.ALTITUDE and len(calls) < times:
            calls.append(snap.t_s[-1])
            raise ValueError("fewer than two usable harmonics")
        return ti(loop, snap, inner)

    return ident, calls


def test_a_numerical_failure_in_identification_is_retried_on_the_next_cycles(tmp_path):
    ident, calls = _failing("qdrone", 1)
    with SitlProcess(vehicle="qdrone", port=None, seed=2) as sitl:
        result = tune(sitl.connection_string, "sitl", backup_dir=tmp_path, relay=RELAY,
                      identifier=ident, hover_check_s=1.0, loops=["altitude"],
                      residuals=False)
    assert result.status == "ok", result.notes
    assert len(calls) == 1
    alt = result.loops[Loop.ALTITUDE]
    assert alt.state == "tuned" and alt.cycles[0][0] > calls[0]  # on later cycles
    assert ("altitude: identification retried after a numerical error (ValueError: fewer "
            "than two usable harmonics)") in result.notes
    assert {c.name for c in result.parameters} >= {"MPC_Z_P", "MPC_Z_VEL_P_ACC"}


def test_a_numerical_failure_that_repeats_stops_the_test_and_lands(tmp_path):
    from mrft_gcs.errors import IdentificationError

    ident, calls = _failing("qdrone", 99)
    with SitlProcess(vehicle="qdrone", port=None, seed=6) as sitl:
        with pytest.raises(IdentificationError, match="failed 3 times on a numerical error "
                           r"\(ValueError: fewer than two usable harmonics\)") as err:
            tune(sitl.connection_string, "sitl", backup_dir=tmp_path, relay=RELAY,
                 identifier=ident, loops=["altitude"], residuals=False)
        with VehicleLink.connect(sitl.connection_string) as link:  # the vehicle was told to land
            deadline = time.monotonic() + 2.0
            while (link.heartbeat.custom_mode >> 16) & 0xFF != 4 and time.monotonic() < deadline:
                time.sleep(0.05)
            assert (link.heartbeat.custom_mode >> 16) & 0xFF == 4  # AUTO (LAND)
    assert len(calls) == 3
    assert err.value.partial_result.parameters == ()  # nothing written
    assert sum("numerical error" in n for n in err.value.partial_result.notes) == 2


def test_telemetry_cut_mid_test_lands_with_exit_code_5(tmp_path):
    with SitlProcess(vehicle="qdrone", port=None, seed=4) as sitl:
        cut = threading.Thread(target=sitl.stop, daemon=True)

        def progress(snap: dict) -> None:
            # in the air, mid-test: a second of setpoints streamed since the take-off
            if snap["stream_sent"] > 250 and not cut.is_alive() and cut.ident is None:
                cut.start()

        with pytest.raises(SafetyAbort) as err:
            tune(sitl.connection_string, "sitl", backup_dir=tmp_path, relay=RELAY,
                 identifier=_truth("qdrone"), on_progress=progress)
    assert err.value.exit_code == 5
    assert "no telemetry" in str(err.value) and "landing command" in str(err.value)
    partial = err.value.partial_result
    assert partial.status.startswith("error:5") and partial.parameters == ()
    assert partial.stream.sent > 100


def test_a_pilot_taking_over_stops_the_tool_without_a_landing(tmp_path):
    """Mid-test the vehicle is switched to POSCTL by someone else (as an RC mode switch
    would): the tool stops streaming, writes nothing and commands no landing."""
    from mrft_gcs.errors import PilotTookOver
    from mrft_gcs.link.modes import PX4_MODES

    with SitlProcess(vehicle="qdrone", port=None, seed=6) as sitl:
        pilot = VehicleLink.connect(sitl.connection_string)
        switch = threading.Thread(target=pilot.set_mode, args=(PX4_MODES["position"],),
                                  daemon=True)

        def progress(snap: dict) -> None:
            if snap["stream_sent"] > 500 and switch.ident is None:  # two seconds in the air
                switch.start()

        try:
            with pytest.raises(PilotTookOver) as err:
                tune(sitl.connection_string, "sitl", backup_dir=tmp_path, relay=RELAY,
                     identifier=_truth("qdrone"), on_progress=progress)
            switch.join(3.0)
            time.sleep(1.5)  # a land command, had one been sent, would show by now
            mode = pilot.heartbeat.custom_mode
            armed = pilot.heartbeat.armed
        finally:
            pilot.close()
    assert err.value.exit_code == 5 and "left OFFBOARD" in str(err.value)
    assert "nothing was written" in str(err.value)
    assert (mode >> 16) & 0xFF == 3 and armed  # still POSCTL, flying: no land command
    assert err.value.partial_result.parameters == ()


def test_tilt_limit_aborts_and_lands(tmp_path, monkeypatch):
    """A tilt limit below what the attitude relays swing (they are sized to about 7 deg from
    their first period, so a larger relay asked for no longer reaches a wide limit). The
    relay guard, which stops a relay test short of the limit, is off here (test_timeliness)."""
    from mrft_gcs.flight import safety
    from mrft_gcs.profiles import load_profile

    monkeypatch.setattr(safety, "RELAY_GUARD_FRACTION", 10.0)
    limits = load_profile("sitl").safety.with_overrides(max_tilt_deg=3.0)
    with SitlProcess(vehicle="qdrone", port=None, seed=5) as sitl:
        with pytest.raises(LimitExceeded, match="tilt") as err:
            tune(sitl.connection_string, "sitl", backup_dir=tmp_path, relay=RELAY,
                 identifier=_truth("qdrone"), limits=limits)
        assert err.value.exit_code == 5
        with VehicleLink.connect(sitl.connection_string) as link:  # the vehicle was told to land
            deadline = time.monotonic() + 2.0
            while (link.heartbeat.custom_mode >> 16) & 0xFF != 4 and time.monotonic() < deadline:
                time.sleep(0.05)
            assert (link.heartbeat.custom_mode >> 16) & 0xFF == 4  # AUTO (LAND)
    assert err.value.partial_result.parameters == ()


def test_dry_link_refuses_to_arm(tmp_path, capsys):
    with SitlProcess(vehicle="qdrone", port=None) as sitl:
        code = main(["tune", "-c", sitl.connection_string, "--profile", "sitl", "--dry-link",
                     "--backup-dir", str(tmp_path), "--report", str(tmp_path / "r.json")])
        with VehicleLink.connect(sitl.connection_string) as link:
            armed = bool(link.heartbeat.base_mode & 128)
    assert code == 0 and not armed
    assert json.loads((tmp_path / "r.json").read_text())["status"] == "dry-link"


def _bundled_ready() -> str | None:
    """Why the bundled-classifier tests cannot run yet (None when they can)."""
    from mrft_gcs.identify import relay_settings

    if not MODELS.exists():
        return "bundled classifiers (models/) not built yet"
    try:
        relay_settings(LoopKind.ATTITUDE), relay_settings(LoopKind.ALTITUDE)
    except Exception as err:  # noqa: BLE001 - a half-written or older models/ folder
        return f"bundled classifiers incomplete: {err!r}"
    if not list((MODELS.parent / "side").glob("shape_*/classifier.onnx")):
        return "bundled side classifiers not built yet"
    return None


@pytest.fixture(scope="module")
def bundled(tmp_path_factory):
    """One live tune of the SITL with the bundled classifiers (shared by the tests below)."""
    why = _bundled_ready()
    if why:
        pytest.skip(why)
    def flight():
        folder = tmp_path_factory.mktemp("bundled")  # each flight its own backups and log
        with SitlProcess(vehicle="qdrone", port=None, seed=6) as sitl:
            return tune(sitl.connection_string, "sitl", backup_dir=folder,
                        tlog_path=folder / "session.tlog"), folder

    return again_if_host_stalled(flight)


def test_tune_with_bundled_classifiers(bundled):
    from mrft_gcs.flight.scoring import score_gains
    from mrft_gcs.sitl import load_airframe

    result, _ = bundled
    assert result.status == "ok" and result.duration_s < 20
    assert not any("worker process failed" in n for n in result.notes), result.notes
    gains = {lp: lr.gains for lp, lr in result.loops.items()}
    scores = score_gains(load_airframe("qdrone").linear_models(), gains)
    for lp in Loop:
        assert scores[lp].stable and scores[lp].J_pct < 25, (lp, scores[lp])
    assert not math.isnan(result.max_tilt_deg)
    # the tilt of every phase the tune flew, from the samples the stream acted on (the
    # safety monitor's maximum also sees the last sample before the hand-over)
    phases = result.max_tilt_by_phase
    assert {"take-off", "side MRFT", "hover"} <= set(phases), phases
    assert max(phases.values()) <= result.max_tilt_deg + 1e-9
    assert any(n.startswith("largest tilt by phase: take-off") for n in result.notes)
    for lp in (Loop.ROLL, Loop.PITCH, Loop.ALTITUDE, Loop.X, Loop.Y):
        assert result.loops[lp].band > 0  # relay noise band from the measured noise


def test_a_worker_that_dies_in_flight_leaves_identification_to_the_tune(tmp_path, monkeypatch):
    """The identification worker killed before its first identification: the tune goes on
    identifying in its own process and says so."""
    import mrft_gcs.flight.api as api

    why = _bundled_ready()
    if why:
        pytest.skip(why)

    class Dying(api.IdentificationWorker):
        def call(self, op, *args, **kw):
            self._proc.kill()
            self._proc.wait()
            return super().call(op, *args, **kw)

    monkeypatch.setattr(api, "IdentificationWorker", Dying)
    with SitlProcess(vehicle="qdrone", port=None, seed=3) as sitl:
        result = tune(sitl.connection_string, "sitl", backup_dir=tmp_path, relay=RELAY,
                      loops=["altitude"], residuals=False)
    assert result.status == "ok", result.notes
    assert result.loops[Loop.ALTITUDE].state == "tuned"
    assert sum("worker process failed (the identification worker exited" in n
               for n in result.notes) == 1, [n for n in result.notes if "worker" in n]


def test_dry_run_replays_the_live_tlog(bundled):
    """dry-run on the session's .tlog reproduces the live identification of every loop.

    Roll, pitch, x and y: the replay recovers the samples the live cycle detector saw and
    the relay output paired with each (mrft-tune's commands carry the yaw hold's and, once
    altitude is tuned, the altitude PD's answer to the sample they answered; x and y come
    from inverting the GCS attitude PDs), so the live cycles cut from the replayed record
    identify to the live class and gains, up to the float32 rounding of the wire, which the
    identification's harmonic fits carry into the gains at up to ~1e-4.
    x and y: where the thrust tells nothing (clipped, or before the altitude PD runs) file
    order decides, so now and then a position sample differs (3 % allowed; seen: 1 in
    700), and the complementary filter carries such a difference for ~60 samples (2e-3 of
    the amplitude allowed). Roll and pitch: where the yaw torque tells nothing,
    file order decides likewise (seen once in CI: 230 of 231 samples). The gains agree to
    1e-5..1e-4 as a rule, but identify() makes discrete choices (harmonics at the usable-sd
    cut-off), so 5e-2 is allowed. dry-run's own x/y identification also runs on the
    replayed attitude identification, and parameters combine two gains (twice the
    tolerance). dry-run itself identifies the last steady cycles before each relay stopped;
    the live tune, the cycles that were steady when its main thread looked, the same
    ones unless that thread was busy past a later steady cycle (loading a classifier,
    identifying the other side loop): then the live window must be one the replayed
    detector found steady, and where the windows agree the replay's own class and written
    gains must be the live ones.
    Altitude: no command depends continuously on position during the altitude test, so
    which of two position samples 2 ms apart a command answered cannot always be told
    (up to one sample in eight differs); asserted: period within 3 %, written gains within
    15 % (measured on 12 tunes: identified gains on the live's cycles within 6 %).
    """
    import numpy as np

    from mrft_gcs.dryrun import _retarget_delay, _steady_rises, dry_run
    from mrft_gcs.flight.sequence import SIDE_INNER, SequenceConfig
    from mrft_gcs.identify import identify
    from mrft_gcs.profiles import PDGains, gains_to_params, load_profile

    result, folder = bundled
    prof = load_profile("sitl")
    dr = dry_run(folder / "session.tlog", profile=prof)
    found = {r.loop: r for r in dr.loops}
    assert set(found) == set(Loop), dr.explanation()
    cfg = SequenceConfig()
    n_steady = dict(zip(LoopKind, cfg.steady_periods, strict=True))
    relax = dict(zip(LoopKind, cfg.relax_after_cycles, strict=True))
    for lp in Loop:
        live, rep = result.loops[lp], found[lp]
        li, seg = live.identification, rep.segment
        assert rep.identification is not None, (lp, rep.notes)
        assert seg.beta == pytest.approx(live.beta, abs=1e-9)
        assert seg.h == pytest.approx(live.h, rel=1e-3)
        # the GCS delay re-targeted out of the written gains: the live tune measures it on
        # its receive and send times, dry-run on the .tlog's stamps of the same frames (over
        # the live cycles: dry-run's own may be later ones). The two stamp a frame at
        # different moments, and each takes the link offset as a running minimum (live: up
        # to the identification; dry-run: the whole log): within 0.1-0.55 ms in 12 quiet
        # tunes, 0.78 ms once in CI, 1.29 ms once in CI since roll and pitch may be
        # identified sooner (relaxed cycle detector: a shorter running minimum); a pairing
        # error would be a whole period (4 ms)
        tol = 2e-3
        assert math.isfinite(live.gcs_delay_s) == (lp.kind is not LoopKind.SIDE), lp
        if lp.kind is not LoopKind.SIDE:
            # the live estimate holds the link's TIMESYNC round trip too (dry-run: ages
            # only); what is written may be held back from it (the margin check)
            assert live.retarget is not None and live.retarget.gcs.measured, lp
            ages = live.retarget.gcs.estimate_s - live.retarget.gcs.round_trip_s
            assert 0 < ages < 3 * 0.004, lp
            dry, measured = _retarget_delay(seg, live.cycles[0])
            assert measured, lp
            if lp is Loop.ALTITUDE:
                # which position sample a command answered is not always known (see below):
                # file order pairs it with one logged just before, which it may not have
                # seen yet (received while the command was computed): never older
                assert ages - 0.004 - tol <= dry <= ages + tol
            else:
                assert dry == pytest.approx(ages, abs=tol), lp
            assert math.isfinite(rep.gcs_delay_s), lp
        if lp is Loop.ALTITUDE:
            assert rep.identification.period_s == pytest.approx(li.period_s, rel=0.03)
            for g in ("Kc", "Kd"):
                assert getattr(rep.gains, g) == pytest.approx(getattr(live.gains, g), rel=0.15)
            continue
        lt, lu, ly = live.cycles
        inner = result.loops[SIDE_INNER[lp]].identification if lp in SIDE_INNER else None
        inside = (seg.t >= lt[0] - 1e-6) & (seg.t <= lt[-1] + 1e-6)
        # the very samples, relay output and angle; where the yaw torque tells nothing
        # (see dryrun._answer_order) file order decides, so now and then a sample differs
        # (CI saw roll/pitch 230 of 231; a box kept busy by another process once more than
        # 1 %, not reproduced in 5 runs: 3 % allowed); x and y: the filtered positions agree
        common, i_rep, i_live = np.intersect1d(np.round(seg.t[inside], 6),
                                               np.round(lt, 6), return_indices=True)
        odd = (np.setdiff1d(np.round(lt, 6), common), np.setdiff1d(np.round(seg.t[inside], 6),
                                                                   common))
        assert common.size >= 0.97 * max(lt.size, inside.sum()), (
            lp, common.size, lt.size, int(inside.sum()), "live/replay only", odd)
        np.testing.assert_allclose(seg.u[inside][i_rep], lu[i_live], atol=1e-3 * live.h)
        np.testing.assert_allclose(seg.y[inside][i_rep], ly[i_live],
                                   atol=(1e-4 if inner is None else 2e-3) * li.amplitude,
                                   err_msg=lp.value)
        # identify() makes discrete choices (a harmonic at the usable-sd cut-off is in or
        # out, the refinement is trusted or not): a float32-level change can move the gains
        # by a few % (seen once in ~15 runs: roll Kd 3.1 % on identical samples); typical
        # agreement is 1e-5..1e-4
        rel = 5e-2
        again = identify(lp.kind, seg.t[inside], seg.u[inside], seg.y[inside], beta=seg.beta,
                         h=seg.h, inner=inner,
                         tilt=None if seg.tilt is None else seg.tilt[inside])
        assert again.class_index == li.class_index, lp
        for g in ("Kc", "Kd"):
            assert getattr(again.gains, g) == pytest.approx(getattr(li.gains, g), rel=rel), lp
        own = rep.cycles[0]
        same = abs(own[0] - lt[0]) < 1e-6 and abs(own[-1] - lt[-1]) < 1e-6
        if lp in SIDE_INNER:  # the side classifier depends on the attitude identification
            inner_own = found[SIDE_INNER[lp]].cycles[0]
            inner_lt = result.loops[SIDE_INNER[lp]].cycles[0]
            same &= abs(inner_own[-1] - inner_lt[-1]) < 1e-6
        if same:
            assert rep.identification.class_index == li.class_index, lp
            for g in ("Kc", "Kd"):
                assert getattr(rep.gains, g) == pytest.approx(getattr(live.gains, g),
                                                              rel=rel * 2), (lp, g)
            if lp in (Loop.ROLL, Loop.PITCH):
                want = gains_to_params(prof, {lp: PDGains(live.gains.Kc, live.gains.Kd)}, 0.5)
                for name, value in want.items():
                    if name in dr.parameters:
                        assert dr.parameters[name] == pytest.approx(value, rel=2 * rel), name
        else:
            tol = getattr(cfg, "side_period_tol", cfg.period_tol) if inner else cfg.period_tol
            rises, steady = _steady_rises(seg.t, seg.u, seg.y, n_steady[lp.kind], tol, 0.08,
                                          relax[lp.kind], cfg.relaxed_tol)
            assert np.isclose(seg.t[rises[steady]], lt[-1], atol=1e-6).any(), lp


def test_dry_run_of_a_session_runs_the_tune_s_own_sequence(bundled):
    """dry-run of this tool's own session .tlog replays it through the tune's sequence
    driver with the bundled identification (``ReplayVehicle`` + ``SequenceDriver``), so it
    identifies the loops the live tune did because it runs the same code.

    The log is taken for a session only because the replayed sequence reproduces the logged
    commands from take-off to the side tests (float32 on the wire: to 1e-4 of full scale).
    Roll, pitch, altitude: the replay hands over the live cycle window (to the sample) and
    identifies it to the live class; identified gains within 5e-2, as in the test above
    (the replay's relay output is the logged float32 command, the live one its own float64
    value; identify()'s discrete choices can turn that into a few %, as a rule 1e-5).
    x, y: the side relays start a tick or so apart from live (docs/pipeline.md), so the
    window may be up to two cycles earlier: same class, period within 5 % (the cycle
    detector's own steadiness tolerance), identified gains within 10 %. Written gains: the
    inner loops' re-target delay is measured on the log's stamps rather than the live
    link's clock (within 2 ms, see above): within 10 %.
    """
    from mrft_gcs.dryrun import dry_run
    from mrft_gcs.profiles import load_profile

    result, folder = bundled
    dr = dry_run(folder / "session.tlog", profile=load_profile("sitl"))
    found = {r.loop: r for r in dr.loops}
    assert set(found) == set(Loop), dr.explanation()
    for lp in Loop:
        live, rep = result.loops[lp], found[lp]
        li, ri = live.identification, rep.identification
        assert li is not None and ri is not None, (lp, rep.notes)
        assert rep.segment.beta_from == "session", (lp, rep.notes)
        assert any("replaying the session" in n for n in rep.notes), rep.notes
        assert ri.class_index == li.class_index, lp
        assert rep.segment.beta == live.beta and rep.segment.h == live.h, lp
        if lp.kind is LoopKind.SIDE:
            assert ri.period_s == pytest.approx(li.period_s, rel=0.05), lp
            rel = 0.10
        else:
            assert rep.cycles[0][0] == pytest.approx(live.cycles[0][0], abs=1e-6), lp
            assert rep.cycles[0][-1] == pytest.approx(live.cycles[0][-1], abs=1e-6), lp
            rel = 5e-2
            for g in ("Kc", "Kd"):
                assert getattr(rep.gains, g) == pytest.approx(getattr(live.gains, g),
                                                              rel=0.10), (lp, g)
        for g in ("Kc", "Kd"):
            assert getattr(ri.gains, g) == pytest.approx(getattr(li.gains, g), rel=rel), (lp, g)
        print(lp.value, ri.class_index, ri.gains, li.gains, rep.gains, live.gains,
              rep.cycles[0][[0, -1]], live.cycles[0][[0, -1]])


def test_dry_run_of_another_log_finds_the_relay_segments(roll_relay_tlog):
    """A .tlog whose commands the tune's sequence does not reproduce (here a synthetic
    relay test: no take-off) goes through the relay-segment search, as before."""
    from mrft_gcs.dryrun import dry_run

    why = _bundled_ready()
    if why:
        pytest.skip(why)
    dr = dry_run(roll_relay_tlog)
    assert [r.loop for r in dr.loops] == [Loop.ROLL], dr.explanation()
    assert dr.loops[0].segment.beta_from != "session"
    assert not any("replaying the session" in n for n in dr.loops[0].notes)


def test_attitude_path_tunes_altitude_x_and_y(tmp_path):
    """SET_ATTITUDE_TARGET: the SITL keeps its own attitude loop (PX4 v1.13 defaults); x and
    y are tuned behind it, measured from their own relays; only MPC_* parameters change."""
    why = _bundled_ready()
    if why:
        pytest.skip(why)
    from mrft_gcs.flight.scoring import score_gains
    from mrft_gcs.plant import PD
    from mrft_gcs.profiles import load_profile, params_to_gains
    from mrft_gcs.sitl import load_airframe
    from mrft_gcs.sitl.onboard import PARAM_SPECS

    prof = load_profile("sitl")
    with SitlProcess(vehicle="qdrone", port=None, seed=2) as sitl:
        result = tune(sitl.connection_string, prof, actuation="attitude", backup_dir=tmp_path,
                      hover_check_s=2.0)
        with VehicleLink.connect(sitl.connection_string) as link:
            values = {n: p.value for n, p in
                      ParamClient(link).read_many(prof.parameter_names()).items()}
            mode = link.heartbeat.custom_mode
    assert result.status == "ok" and result.actuation == "attitude"
    assert result.hover_error_m < 0.3 and (mode >> 16) & 0xFF == 3  # POSCTL on the gains
    assert result.max_tilt_deg < 35
    rep = report_dict(result)
    json.dumps(rep, allow_nan=False)
    for lp in ("roll", "pitch"):
        loop = rep["loops"][lp]
        assert loop["state"] == "left alone" and loop["gains"] is None
        assert "autopilot keeps its own attitude loop" in loop["note"]
        assert "closed loop was measured" in loop["note"]
    for lp in ("altitude", "x", "y"):
        assert rep["loops"][lp]["state"] == "tuned" and rep["loops"][lp]["gains"]["Kc"] > 0
    assert set(rep["loops"]["x"]["model"]) == {"K", "T2", "tau"}
    names = {c.name for c in result.parameters}
    assert {"MPC_XY_P", "MPC_XY_VEL_P_ACC", "MPC_Z_P", "MPC_Z_VEL_P_ACC"} <= names
    assert not any(n.startswith("MC_") for n in names)  # the autopilot's attitude loop
    for c in result.parameters:
        assert values[c.name] == pytest.approx(c.new, rel=1e-6, abs=1e-9)
    # J of the written x/y gains on the true cascade: the SITL's own attitude loop
    px4 = {k: s.default for k, s in PARAM_SPECS.items()} | {
        k: v for k, v in values.items() if k.startswith("MC_")}
    written = params_to_gains(prof, values)
    scores = score_gains(load_airframe("qdrone").linear_models(),
                         {lp: PD(written[lp].Kc, written[lp].Kd) for lp in (Loop.X, Loop.Y)},
                         attitude_params=px4)
    for lp in (Loop.X, Loop.Y):
        assert scores[lp].stable and scores[lp].J_pct < 10.0, (lp, scores[lp])
