"""The PX4 ULog reader, on a real flight log written by PX4 (../shared/logs)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mrft_gcs.errors import InputFileError
from mrft_gcs.logs import LogFormat, detect_format, read_log
from mrft_gcs.logs.ulog import quaternion_to_euler

SHARED = Path(__file__).resolve().parents[2] / "shared" / "logs"
ULG = SHARED / "px4-sample-flight.ulg"
needs_shared = pytest.mark.skipif(
    not ULG.exists(), reason=f"real PX4 log not found at {ULG} (../shared beside the clone)")


@needs_shared
def test_real_px4_log_reads_cleanly():
    assert detect_format(ULG) is LogFormat.ULOG
    log = read_log(ULG)
    assert len(log.attitude) == 1298  # every vehicle_attitude sample
    assert len(log.position) == 636
    assert len(log.actuator) == 1812  # actuator_controls_0
    assert len(log.attitude_target) == 65
    assert len(log.params) == 980 and "MC_ROLL_P" in log.params
    assert [s.text for s in log.status][0] == "[commander] Takeoff detected"
    assert all(s.severity == 6 for s in log.status)
    t = log.attitude[:, 0]
    assert 20.0 < t[0] < t[-1] < 27.0 and np.all(np.diff(t) >= 0)
    # angles and rates plausible for a short hop: small tilt, rates well under 1 rad/s
    assert np.abs(log.attitude[:, 1:3]).max() < 0.3
    assert np.abs(log.attitude[:, 4:7]).max() < 1.0
    assert np.all(np.abs(log.actuator[:, 1:4]) <= 1.0)
    assert np.all((log.actuator[:, 4] >= 0) & (log.actuator[:, 4] <= 1))
    q = log.attitude_target[:, 1:5]
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-5)


@needs_shared
def test_rates_match_gyro_topic():
    from pyulog import ULog

    ulog = ULog(str(ULG), ["vehicle_angular_velocity"])
    d = ulog.get_dataset("vehicle_angular_velocity").data
    log = read_log(ULG)
    t = log.attitude[:, 0]
    ref = np.interp(t, d["timestamp"] * 1e-6, d["xyz[2]"])
    np.testing.assert_allclose(log.attitude[:, 6], ref, atol=1e-6)


def test_quaternion_to_euler_round_trip():
    from mrft_gcs.logs.dataflash import euler_to_quaternion

    rng = np.random.default_rng(0)
    rpy = np.column_stack([rng.uniform(-1.5, 1.5, 50), rng.uniform(-1.4, 1.4, 50),
                           rng.uniform(-3.1, 3.1, 50)])
    np.testing.assert_allclose(quaternion_to_euler(euler_to_quaternion(rpy)), rpy, atol=1e-9)


def test_bad_magic(tmp_path):
    p = tmp_path / "x.ulg"
    p.write_bytes(b"not a ulog file at all")
    with pytest.raises(InputFileError) as e:
        read_log(p)
    assert str(e.value) == (f"{p}: not a ULog file (bad magic); "
                            "dry-run reads .tlog, .ulg, .bin and .csv")


@needs_shared
@pytest.mark.parametrize("keep", [7, 16, 100, 3000, 400_000])
def test_truncated(tmp_path, keep):
    p = tmp_path / "cut.ulg"
    p.write_bytes(ULG.read_bytes()[:keep])
    try:
        log = read_log(p)
    except InputFileError as e:
        assert str(p) in str(e)
    else:
        assert len(log.attitude) <= 1298
