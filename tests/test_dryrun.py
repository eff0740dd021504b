"""dry-run: relay tests found in logs, explained when absent; CLI; identification wiring."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mrft_gcs.cli import main
from mrft_gcs.dryrun import dry_run, find_relay_segments, infer_beta
from mrft_gcs.loops import Loop
from mrft_gcs.plant import InnerModel
from mrft_gcs.residual.synth import sitl_relay_record, write_relay_tlog
from mrft_gcs.telemetry import TelemetryLog

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "logs"
REAL = [SHARED / "px4-sample-flight.ulg", SHARED / "ardupilot-sample.bin"]
MODELS = ROOT / "models" / "manifest.json"


@pytest.fixture(scope="module")
def relay_tlog(tmp_path_factory):
    rec = sitl_relay_record("roll", effects={"sensor_lpf": 15.0}, seed=3, beta=-0.5, h=0.08,
                            duration_s=6.0)
    path = tmp_path_factory.mktemp("dry") / "relay.tlog"
    write_relay_tlog(path, "roll", rec.t, rec.u, rec.y)
    return path, rec


@pytest.mark.parametrize("path", REAL, ids=lambda p: p.name)
def test_real_logs_explain_that_no_relay_test_is_there(path):
    if not path.exists():
        pytest.skip(f"{path} not found")
    res = dry_run(path)
    assert not res.found
    text = res.explanation()
    assert "no relay test found" in text
    for loop in ("roll", "pitch", "altitude", "x", "y"):
        assert f"  {loop}: " in text
    assert "signals in the log" in text


@pytest.mark.parametrize("path", REAL, ids=lambda p: p.name)
def test_cli_on_real_logs_exits_cleanly(path, tmp_path, capsys):
    if not path.exists():
        pytest.skip(f"{path} not found")
    report = tmp_path / "r.json"
    assert main(["dry-run", str(path), "--report", str(report)]) == 0
    assert "no relay test found" in capsys.readouterr().out
    data = json.loads(report.read_text())
    assert data["loops"] == {} and data["status"] == "no_identification"


def test_relay_found_in_tlog_with_its_settings(relay_tlog):
    path, rec = relay_tlog
    res = dry_run(path, models={Loop.ROLL: rec.model})
    assert [r.loop for r in res.loops] == [Loop.ROLL]
    r = res.loops[0]
    assert r.segment.source == "actuator"
    assert r.segment.h == pytest.approx(0.08, rel=1e-3)
    assert r.segment.beta == pytest.approx(-0.5, abs=0.05)
    # Without bundled classifiers the known model is used for the residual.
    assert r.residual is not None and r.residual.effect == "sensor_lpf"
    assert "pitch" in res.searched and "constant" in res.searched["pitch"]


def test_metadata_beta_wins_and_csv_loops_are_read(tmp_path):
    rec = sitl_relay_record("roll", seed=2, beta=-0.3, h=0.06, duration_s=4.0)
    path = tmp_path / "relay.csv"
    rows = "\n".join(f"{t:.4f},roll,{u:.5f},{y:.6f}"
                     for t, u, y in zip(rec.t, rec.u, rec.y, strict=True))
    path.write_text(f"# mrft-gcs loop csv v1\n# beta=-0.3 h=0.06\nt,loop,u,y\n{rows}\n")
    res = dry_run(path, models={Loop.ROLL: rec.model})
    seg = res.loops[0].segment
    assert seg.source == "csv" and seg.beta_from == "metadata" and seg.beta == -0.3
    assert infer_beta(rec.u, rec.y) == pytest.approx(-0.3, abs=0.06)


def test_controller_output_is_not_a_relay():
    t = np.arange(0, 20, 0.004)
    rng = np.random.default_rng(0)
    att = np.column_stack([t, 0.05 * np.sin(3 * t), *(0 * t for _ in range(5))])
    act = np.column_stack([t, 0.1 * np.cos(3 * t) + 0.01 * rng.standard_normal(t.size),
                           0 * t, 0 * t, 0.5 + 0 * t])
    segs, why = find_relay_segments(TelemetryLog(attitude=att, actuator=act))
    assert segs == [] and "not a two-level relay" in why["roll"]


def test_identify_wiring_once_models_exist(tmp_path):
    if not MODELS.exists() or not list((MODELS.parent / "attitude").glob("*.onnx")):
        pytest.skip("the attitude classifier is not bundled yet (models/)")
    from mrft_gcs.identify import relay_settings
    from mrft_gcs.loops import LoopKind

    beta = relay_settings(LoopKind.ATTITUDE).beta
    rec = sitl_relay_record("roll", seed=4, beta=beta, h=0.08, duration_s=6.0)
    path = tmp_path / "tune.tlog"
    write_relay_tlog(path, "roll", rec.t, rec.u, rec.y)
    r = dry_run(path).loops[0]
    assert r.segment.beta == beta and r.segment.beta_from == "domain"
    assert r.identification is not None, r.notes
    assert isinstance(r.identification.model, InnerModel)
    assert r.identification.gains.Kc > 0 and r.identification.gains.Kd > 0
    assert r.residual is not None
