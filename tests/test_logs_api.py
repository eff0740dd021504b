"""One interface over every format: detection, replay == read, describe_log."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mrft_gcs.errors import InputFileError
from mrft_gcs.logs import (
    LogFormat,
    LoopSample,
    collect_log,
    describe_log,
    detect_format,
    open_log,
    read_log,
    summarize_log,
)
from mrft_gcs.telemetry import Attitude, EndOfStream, TelemetryLog, TelemetrySource

DATA = Path(__file__).resolve().parent / "data"
SHARED = Path(__file__).resolve().parents[2] / "shared" / "logs"
SAMPLES = [DATA / "sample.tlog", DATA / "sample.bin", DATA / "sample.csv",
           SHARED / "px4-sample-flight.ulg", SHARED / "ardupilot-sample.bin"]


def _existing(paths):
    return [pytest.param(p, id=p.name, marks=pytest.mark.skipif(
        not p.exists(), reason=f"{p} not found (../shared beside the clone)")) for p in paths]


def _same(a: TelemetryLog, b: TelemetryLog) -> None:
    for name in ("attitude", "position", "actuator", "attitude_target"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert a.params == b.params and a.status == b.status and a.heartbeats == b.heartbeats
    assert a.loops.keys() == b.loops.keys()
    for k in a.loops:
        np.testing.assert_array_equal(a.loops[k], b.loops[k])


@pytest.mark.parametrize("path", _existing(SAMPLES))
def test_replay_equals_read(path):
    source = open_log(path)
    assert isinstance(source, TelemetrySource)
    _same(collect_log(source, str(path)), read_log(path))
    with pytest.raises(EndOfStream):
        source.next_sample()


@pytest.mark.parametrize("path", _existing(SAMPLES))
def test_replay_is_time_ordered_and_typed(path):
    with open_log(path) as source:
        t = [s.t_s for s in source]
    assert len(t) > 0 and all(b >= a for a, b in zip(t, t[1:], strict=False))


def test_replay_yields_typed_samples_and_rewinds():
    source = open_log(DATA / "sample.tlog")
    first = [source.next_sample() for _ in range(3)]
    assert any(isinstance(s, Attitude) for s in first) or len(source) > 3
    source.reset()
    assert source.next_sample() == first[0]
    source.close()
    with pytest.raises(EndOfStream):
        source.next_sample()
    csv = list(open_log(DATA / "sample.csv"))
    assert all(isinstance(s, LoopSample) for s in csv) and len(csv) == 200


@pytest.mark.parametrize("name, fmt", [("sample.tlog", LogFormat.TLOG),
                                       ("sample.bin", LogFormat.DATAFLASH),
                                       ("sample.csv", LogFormat.CSV)])
def test_content_beats_extension(tmp_path, name, fmt):
    p = tmp_path / "renamed.ulg"
    p.write_bytes((DATA / name).read_bytes())
    assert detect_format(p) is fmt
    read_log(p)


def test_unknown_format(tmp_path):
    p = tmp_path / "notes.txt"
    p.write_text("hello\n")
    with pytest.raises(InputFileError) as e:
        read_log(p)
    assert str(e.value) == (f"{p}: unknown log format (neither its first bytes nor its extension "
                            "say .tlog, .ulg, .bin or .csv); "
                            "dry-run reads .tlog, .ulg, .bin and .csv")


@pytest.mark.parametrize("suffix", [".tlog", ".ulg", ".bin", ".csv", ".xyz"])
def test_empty_file(tmp_path, suffix):
    p = tmp_path / f"empty{suffix}"
    p.touch()
    with pytest.raises(InputFileError, match=r"empty file \(0 bytes\)"):
        read_log(p)


def test_directory(tmp_path):
    with pytest.raises(InputFileError, match="is a directory"):
        read_log(tmp_path)


def test_describe_log():
    log = read_log(DATA / "sample.tlog")
    text = describe_log(log)
    assert "attitude         100 samples  50.0 Hz" in text
    assert "parameters       3" in text and text.startswith(str(DATA / "sample.tlog"))
    s = summarize_log(log)
    assert s.found() == ("attitude", "position", "actuator", "attitude target")
    assert s.duration_s == pytest.approx(1.981, abs=1e-3)
    empty = describe_log(TelemetryLog())
    assert "no telemetry samples" in empty and "attitude         none" in empty
    assert "loop roll" in describe_log(read_log(DATA / "sample.csv"))
