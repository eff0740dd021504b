"""The hold figures of ``benchmarks/tune_ardupilot.py``: roll/pitch against their target at
the same vehicle time, the hold's verdict and the parameter sets of ``--compare``."""

import json
import math
import sys
from pathlib import Path

import numpy as np

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(BENCH))

import tune_ardupilot as ta  # noqa: E402


def _stream(rate_deg_s: float, lag_s: float) -> dict[str, np.ndarray]:
    """25 Hz ATTITUDE and ATTITUDE_TARGET: roll follows a target ramping at ``rate_deg_s``
    ``lag_s`` late; each target message goes out 30 ms before the ATTITUDE of its tick
    (stamped with its own time)."""
    t = np.arange(0.0, 10.0, 0.04)
    r = math.radians(rate_deg_s)
    tgt = np.column_stack((t - 0.03, r * (t - 0.03), np.zeros_like(t)))
    att = np.column_stack((t, r * (t - lag_s), np.zeros_like(t)))
    err = att[:, 1:] - tgt[:, 1:]  # paired with the latest target
    n = len(t)
    return {"pos": np.column_stack((np.zeros(n), np.zeros(n), np.ones(n), np.zeros(n))),
            "att": att[:, 1:], "thr": np.full((n, 1), 50.0), "err": err, "att_t": att,
            "tgt_t": tgt}


def test_tracking_against_the_target_at_the_same_time_not_the_latest_message():
    """A fast target counts its motion since the latest message as error; at the same
    vehicle time only the loop's own lag is left."""
    slow, fast = ta.hold_figures(_stream(1.0, 0.0)), ta.hold_figures(_stream(8.0, 0.0))
    assert fast["att_err_rms_deg"] > 7 * slow["att_err_rms_deg"] > 0.01
    assert fast["att_err_sync_rms_deg"] < 1e-9 and slow["att_err_sync_rms_deg"] < 1e-9
    assert abs(fast["target_rate_rms_deg_s"] - 8.0) < 0.01
    lag = ta.hold_figures(_stream(8.0, 0.01))  # 10 ms behind an 8 deg/s target
    assert abs(lag["att_err_sync_rms_deg"] - 0.08) < 1e-3


def test_hold_judged_on_tracking_and_extra_lean_reported():
    base = {"alt_spread_m": 0.08, "alt_std_m": 0.017, "max_drift_m": 0.4,
            "throttle_saturated": 0.0, "att_err_sync_rms_deg": 0.025, "tilt_std_deg": 0.4,
            "target_rate_rms_deg_s": 1.3}
    stiff = dict(base, max_drift_m=0.08, tilt_std_deg=1.1, target_rate_rms_deg_s=6.5)
    assert ta.worse_in(base, stiff) == []
    assert "tilt std 0.40 -> 1.10" in ta.effort_in(base, stiff)
    # more error on a target moving 5 x faster, the same lag per unit of its motion: not worse
    assert ta.worse_in(base, dict(stiff, att_err_sync_rms_deg=0.12)) == []
    assert ta.worse_in(base, dict(stiff, att_err_sync_rms_deg=0.2)) == ["att_err_sync_rms_deg"]
    assert ta.worse_in(base, dict(base, att_err_sync_rms_deg=0.14)) == ["att_err_sync_rms_deg"]
    assert ta.effort_in(base, base) == ""


def test_compare_splits_the_written_values_into_attitude_and_position(tmp_path):
    src = tmp_path / "run.json"
    src.write_text(json.dumps({"runs": [{"written": {
        "ATC_RAT_RLL_P": [0.135, 0.23], "ATC_RAT_RLL_I": [0.135, 0.0],
        "PSC_VELXY_P": [2.0, 7.7]}}]}))
    c = ta.compare_configs(src, 0, ["withI=tuned:ATC_RAT_RLL_I=1.4"])
    assert c["stock"] == {"ATC_RAT_RLL_P": 0.135, "ATC_RAT_RLL_I": 0.135, "PSC_VELXY_P": 2.0}
    assert c["attitude"] == {"ATC_RAT_RLL_P": 0.23, "ATC_RAT_RLL_I": 0.0, "PSC_VELXY_P": 2.0}
    assert c["position"] == {"ATC_RAT_RLL_P": 0.135, "ATC_RAT_RLL_I": 0.135,
                             "PSC_VELXY_P": 7.7}
    assert c["withI"] == dict(c["tuned"], ATC_RAT_RLL_I=1.4)
