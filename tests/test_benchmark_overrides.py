"""The benchmarks' ``--set NAME=VALUE`` (``benchmarks/overrides.py``), which README's A/B
comparisons are repeated with: its doctests, and that a benchmark refuses a typo at once."""

import doctest
import subprocess
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(BENCH))

import overrides  # noqa: E402


def test_overrides_doctests():
    assert doctest.testmod(overrides).failed == 0


def test_nested_and_tuple_values():
    from mrft_gcs.flight.sequence import SequenceConfig

    c = overrides.apply_overrides(SequenceConfig(), ["takeoff.settle_m=0.1", "h_max=0.3,0.25,0.12"])
    assert c.takeoff.settle_m == 0.1 and c.h_max == (0.3, 0.25, 0.12)
    assert SequenceConfig().takeoff.settle_m == 0.05  # the defaults are untouched


def test_a_benchmark_refuses_an_unknown_field_before_flying():
    r = subprocess.run([sys.executable, str(BENCH / "tune_stalls.py"), "--seeds", "1",
                        "--set", "relax_after=3"], capture_output=True, text=True, timeout=120)
    assert r.returncode != 0
    assert "SequenceConfig has no field 'relax_after'" in r.stderr
    assert "seed" not in r.stdout  # no tune ran
