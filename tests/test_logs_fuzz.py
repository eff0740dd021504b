"""Fuzzing the readers: whatever the bytes, a TelemetryLog or one InputFileError line.

Random bytes, truncations and bit flips of valid sample files, under each
extension. Each read must finish quickly (the work is bounded by the file size).
"""

from __future__ import annotations

import tempfile
import time
from functools import cache
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mrft_gcs.errors import InputFileError
from mrft_gcs.logs import read_log
from mrft_gcs.logs.dataflash import DATAFLASH_MAGIC
from mrft_gcs.logs.ulog import ULOG_MAGIC
from mrft_gcs.telemetry import TelemetryLog

DATA = Path(__file__).resolve().parent / "data"
ULG = Path(__file__).resolve().parents[2] / "shared" / "logs" / "px4-sample-flight.ulg"
SUFFIXES = [".tlog", ".ulg", ".bin", ".csv", ".dat"]
MAX_SECONDS = 10.0  # a hang, not a slow machine

FUZZ = settings(max_examples=150, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


@cache
def _base(name: str) -> bytes:
    if name == "ulg":
        # the head of a real PX4 log: header, definitions, parameters, some data
        return ULG.read_bytes()[:120_000] if ULG.exists() else b""
    return (DATA / f"sample.{name}").read_bytes()


def _check(content: bytes, suffix: str) -> None:
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / f"fuzz{suffix}"
        p.write_bytes(content)
        start = time.perf_counter()
        try:
            log = read_log(p)
        except InputFileError as e:
            msg = str(e)
            assert str(p) in msg and "\n" not in msg
        else:
            assert isinstance(log, TelemetryLog)
        assert time.perf_counter() - start < MAX_SECONDS


@FUZZ
@given(st.binary(max_size=4096), st.sampled_from(SUFFIXES),
       st.sampled_from([b"", ULOG_MAGIC, DATAFLASH_MAGIC, b"\x00\x05\xf0\x00\x00\x00\x00\x00\xfd",
                        b"t,loop,u,y\n"]))
def test_random_bytes(content, suffix, prefix):
    _check(prefix + content, suffix)


def _bases():
    names = ["tlog", "bin", "csv"]
    if ULG.exists():
        names.append("ulg")
    return st.sampled_from(names)


@FUZZ
@given(_bases(), st.floats(0.0, 1.0), st.sampled_from(SUFFIXES))
def test_truncations(name, fraction, suffix):
    data = _base(name)
    _check(data[: int(len(data) * fraction)], suffix)


@FUZZ
@given(_bases(), st.lists(st.tuples(st.floats(0.0, 1.0, exclude_max=True), st.integers(0, 7)),
                          min_size=1, max_size=40))
def test_bit_flips(name, flips):
    data = bytearray(_base(name))
    for where, bit in flips:
        data[int(where * len(data))] ^= 1 << bit
    _check(bytes(data), "." + name)


@FUZZ
@given(_bases(), st.floats(0.0, 1.0), st.floats(0.0, 1.0), st.binary(max_size=64))
def test_spliced_garbage(name, a, b, junk):
    data = _base(name)
    i, j = sorted((int(a * len(data)), int(b * len(data))))
    _check(data[:i] + junk + data[j:], "." + name)


def test_ulog_head_is_a_real_log():
    if not ULG.exists():
        pytest.skip(f"{ULG} not found (../shared beside the clone)")
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "head.ulg"
        p.write_bytes(_base("ulg"))
        assert len(read_log(p).params) > 900
