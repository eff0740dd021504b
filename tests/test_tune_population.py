"""benchmarks/tune_population.py: one lockstep tune per outcome path, scored and printed."""

from __future__ import annotations

import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import pytest  # noqa: E402
import structure_loss as sl  # noqa: E402
import tune_population as tp  # noqa: E402

from mrft_gcs.loops import Loop  # noqa: E402
from mrft_gcs.sitl import domain_check, random_airframe  # noqa: E402


def test_slow_link_is_refused_before_take_off():
    seed = next(s for s in range(100) if random_airframe(s).telemetry_max_hz < 150)
    r = tp.run_lockstep(seed)
    assert r["outcome"] == "refused" and "telemetry" in r["reason"]
    assert r["category"] == "out-of-domain" and "loops" not in r
    assert "refused" in tp.line(r)


def test_a_tune_ends_in_one_of_the_outcomes_with_every_written_loop_scored():
    seed = 38  # an in-domain vehicle (the tune's outcome is what the test reports)
    assert domain_check(random_airframe(seed)).category == "in-domain"
    r = tp.run_lockstep(seed)
    assert r["outcome"] in ("completed", "refused", "aborted")
    if r["outcome"] == "completed":
        assert set(r["loops"]) == {"roll", "pitch", "altitude", "x", "y"}
        for fig in r["loops"].values():
            assert math.isfinite(fig["onboard_pm_deg"]) and math.isfinite(fig["gcs_pm_deg"])
            # the second figure: the written gains against the best of the vehicle's structure
            floor, vs = fig["structure_floor_J_pct"], fig["onboard_J_vs_structure_pct"]
            assert floor is not None and vs is not None and floor >= 0.0
            assert 1 + fig["onboard_J_pct"] / 100 == pytest.approx(
                (1 + vs / 100) * (1 + floor / 100))
        assert 0 < r["time_to_tune_s"] < 60 and r["written"]
        # the per-phase times add up to the time to tune, in the order the phases run
        pt = r["phase_times_s"]
        assert 0 < pt["takeoff"] < pt["inner"] < r["time_to_tune_s"]
        assert pt["inner"] + pt["side"] == pytest.approx(r["time_to_tune_s"], abs=1e-6)
        for name, lp in pt["loops"].items():
            assert lp["start"] < lp["cycles_from"] < lp["cycles_to"] <= lp["tuned"], name
            assert lp["retries"] >= 0 and lp["resizes"] >= 0 and lp["raises"] >= 0
        assert max(pt["loops"][n]["tuned"] for n in ("x", "y")) == pytest.approx(
            r["time_to_tune_s"], abs=1e-6)
        # where the J of each written loop went, re-designed from the record
        f = sl.breakdown(r, Loop.ROLL)
        assert f["written"][0] == pytest.approx(r["loops"]["roll"]["onboard_J_pct"])
        assert {"floor", "no range", "no cap", "at d*", "cause"} <= set(f)
        assert (f["cause"] == "") == (f["written"][0] <= 10)
    lines = tp.summary([r])
    assert any(ln.startswith("in-domain tuned:") for ln in lines)
    if r["outcome"] == "completed":
        assert any(ln.startswith("time by phase") for ln in lines)


def test_cpu_hog_processes_end_with_the_block():
    with tp.CpuHog(1, limit_s=30.0) as hog:
        procs = list(hog._p)
        assert all(p.poll() is None for p in procs)
    assert all(p.poll() is not None for p in procs)
