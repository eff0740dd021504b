"""A log cut short is read (its whole records) and reported as truncated: one warning line."""

from __future__ import annotations

from pathlib import Path

import pytest

from mrft_gcs.cli import main
from mrft_gcs.logs import decode_log, log_truncation

DATA = Path(__file__).parent / "data"
SHARED = Path(__file__).resolve().parents[2] / "shared" / "logs"
WHOLE = [SHARED / "px4-sample-flight.ulg", DATA / "sample.tlog"]


def _cut(src: Path, dst: Path, fraction: float = 0.6) -> Path:
    data = src.read_bytes()
    dst.write_bytes(data[:int(len(data) * fraction) + 1])
    return dst


@pytest.mark.parametrize("src", WHOLE, ids=lambda p: p.name)
def test_whole_log_is_not_truncated_and_a_cut_copy_is(src, tmp_path):
    if not src.exists():
        pytest.skip(f"{src} not found")
    assert log_truncation(src) is None
    for fraction in (0.6, 0.97):
        cut = _cut(src, tmp_path / f"cut{src.suffix}", fraction)
        line = log_truncation(cut)
        assert line is not None and "truncated" in line and str(cut) in line, fraction
        assert "\n" not in line
        decode_log(cut)  # the whole records before the cut are still read


def test_csv_whose_last_row_lacks_fields_is_truncated(tmp_path):
    text = (DATA / "sample.csv").read_text()
    assert log_truncation(DATA / "sample.csv") is None
    cut = tmp_path / "cut.csv"
    cut.write_text(text[:text.index(",roll,", len(text) // 2) + 4])  # "...,ro"
    assert "truncated" in (log_truncation(cut) or "")
    decode_log(cut)


def test_dataflash_cut_inside_a_record_is_reported():
    # make_samples.py ends sample.bin with a record cut by the end of the file;
    # the shared ArduPilot sample is the first 64 KiB of a longer log
    assert "truncated" in (log_truncation(DATA / "sample.bin") or "")
    shared = SHARED / "ardupilot-sample.bin"
    if shared.exists():
        assert "truncated" in (log_truncation(shared) or "")


def test_dry_run_of_a_cut_tlog_warns_once_and_goes_on(tmp_path, capsys):
    cut = _cut(DATA / "sample.tlog", tmp_path / "cut.tlog", 0.8)
    report = tmp_path / "r.json"
    code = main(["dry-run", str(cut), "--report", str(report)])
    err = capsys.readouterr().err
    warnings = [ln for ln in err.splitlines() if ln.startswith("warning:")]
    assert len(warnings) == 1 and "truncated" in warnings[0] and str(cut) in warnings[0]
    whole = main(["dry-run", str(DATA / "sample.tlog")])
    assert code == whole  # the warning does not change the outcome
    assert "warning:" not in capsys.readouterr().err
    import json

    assert json.loads(report.read_text())["warnings"] == [warnings[0][len("warning: "):]]
