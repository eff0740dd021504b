"""The documented CSV format."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mrft_gcs.errors import InputFileError
from mrft_gcs.logs import read_csv_metadata, read_log

SAMPLE = Path(__file__).resolve().parent / "data" / "sample.csv"


def test_sample():
    log = read_log(SAMPLE)
    assert set(log.loops) == {"roll", "altitude"}
    roll = log.loops["roll"]
    assert roll.shape == (100, 3)  # the nan row is dropped
    np.testing.assert_allclose(roll[:, 2], 0.1 * np.sin(2 * np.pi * roll[:, 0]), atol=1e-6)
    assert read_csv_metadata(SAMPLE) == {"beta": "-0.3", "h": "0.1", "vehicle": "sample"}


def test_any_column_order_extra_columns_crlf_bom_and_sorting(tmp_path):
    p = tmp_path / "x.csv"
    p.write_bytes("\ufeff# a=1\r\nY, Loop ,t,u,note\r\n0.2,PITCH,1.0,-0.1,b\r\n"
                  "0.1,pitch,0.5,0.1,a\r\n\r\n".encode())
    log = read_log(p)
    np.testing.assert_array_equal(log.loops["pitch"], [[0.5, 0.1, 0.1], [1.0, -0.1, 0.2]])


@pytest.mark.parametrize(
    "text, problem",
    [
        ("t,loop,u\n0,roll,1\n", "lacks column(s) y"),
        ("# only comments\n\n", "no header line"),
        ("t,loop,u,y\n", "no data rows"),
        ("t,loop,u,y\n0,roll,1\n", "line 2: 3 fields"),
        ("t,loop,u,y\n0,yaw,1,2\n", "unknown loop 'yaw'"),
        ("t,loop,u,y\n0,roll,one,2\n", "line 2: t, u and y must be numbers"),
    ],
)
def test_errors(tmp_path, text, problem):
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(InputFileError) as e:
        read_log(p)
    assert str(p) in str(e.value) and problem in str(e.value) and "\n" not in str(e.value)


def test_not_text(tmp_path):
    p = tmp_path / "bad.csv"
    p.write_bytes(b"t,loop,u,y\n\xff\xfe\x00")
    with pytest.raises(InputFileError, match="not UTF-8 text"):
        read_log(p)
