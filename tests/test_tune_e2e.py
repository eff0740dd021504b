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
from flight_sim import ALT_RELAY, ATT_RELAY, SIDE_RELAY, truth_identifier  # noqa: E402

from mrft_gcs.cli import main  # noqa: E402
from mrft_gcs.errors import SafetyAbort  # noqa: E402
from mrft_gcs.flight import tune  # noqa: E402
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
    folder = tmp_path_factory.mktemp("tune")
    with SitlProcess(vehicle="qdrone", port=None, seed=3) as sitl:
        result = tune(sitl.connection_string, "sitl", backup_dir=folder, relay=RELAY,
                      identifier=_truth("qdrone"), hover_check_s=2.0)
        with VehicleLink.connect(sitl.connection_string) as link:
            readback = ParamClient(link).read_many([c.name for c in result.parameters])
            mode = link.heartbeat.custom_mode
    return result, readback, mode, folder


def test_tune_over_udp_report_and_readback(tuned):
    result, readback, mode, folder = tuned
    assert result.status == "ok"
    assert 0 < result.duration_s < 25
    assert result.max_tilt_deg < 35
    assert result.hover_error_m < 0.3  # stable POSCTL hover on the written gains
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
    assert set(rep["loops"]["x"]["model"]) == {"K", "T2", "tau"}
    assert set(rep["loops"]["roll"]["model"]) == {"K", "T_prop", "T1", "tau"}
    assert rep["vehicle"] == {"connection": result.connection, "autopilot": "px4",
                              "profile": "sitl", "actuation": "torque"}
    assert rep["parameters"][0].keys() == {"name", "old", "new"}
    assert write_report(result, folder / "r.json").is_file()
    png = plot_cycles(result, folder / "cycles.png")
    assert png.read_bytes()[:4] == b"\x89PNG"


def test_telemetry_cut_mid_test_lands_with_exit_code_5(tmp_path):
    with SitlProcess(vehicle="qdrone", port=None, seed=4) as sitl:
        def cut():
            time.sleep(4.0)  # after arming, in the air
            sitl.stop()

        threading.Thread(target=cut, daemon=True).start()
        with pytest.raises(SafetyAbort) as err:
            tune(sitl.connection_string, "sitl", backup_dir=tmp_path, relay=RELAY,
                 identifier=_truth("qdrone"))
    assert err.value.exit_code == 5
    assert "no telemetry" in str(err.value) and "landing command" in str(err.value)
    partial = err.value.partial_result
    assert partial.status.startswith("error:5") and partial.parameters == ()
    assert partial.stream.sent > 100


def test_tilt_limit_aborts_and_lands(tmp_path):
    from mrft_gcs.identify import RelaySettings
    from mrft_gcs.profiles import load_profile

    huge = {**RELAY, LoopKind.ATTITUDE: RelaySettings(beta=-0.2, h=0.6)}
    limits = load_profile("sitl").safety.with_overrides(max_tilt_deg=15.0)
    with SitlProcess(vehicle="qdrone", port=None, seed=5) as sitl:
        with pytest.raises(LimitExceeded, match="tilt") as err:
            tune(sitl.connection_string, "sitl", backup_dir=tmp_path, relay=huge,
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


@pytest.mark.skipif(not MODELS.exists(), reason="bundled classifiers (models/) not built yet")
def test_tune_with_bundled_classifiers(tmp_path):
    from mrft_gcs.errors import IdentificationError
    from mrft_gcs.flight.scoring import score_gains
    from mrft_gcs.identify import relay_settings
    from mrft_gcs.sitl import load_airframe

    try:
        relay_settings(LoopKind.ATTITUDE), relay_settings(LoopKind.ALTITUDE)
    except IdentificationError as err:
        pytest.skip(f"bundled classifiers incomplete: {err}")

    with SitlProcess(vehicle="qdrone", port=None, seed=6) as sitl:
        result = tune(sitl.connection_string, "sitl", backup_dir=tmp_path)
    assert result.status == "ok" and result.duration_s < 20
    gains = {lp: lr.gains for lp, lr in result.loops.items()}
    scores = score_gains(load_airframe("qdrone").linear_models(), gains)
    for lp in Loop:
        assert scores[lp].stable and scores[lp].J_pct < 25, (lp, scores[lp])
    assert not math.isnan(result.max_tilt_deg)
