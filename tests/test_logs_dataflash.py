"""The DataFlash reader: committed Copter-style sample and a real ArduPilot log."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mrft_gcs.errors import InputFileError
from mrft_gcs.logs import LogFormat, detect_format, read_log

DATA = Path(__file__).resolve().parent / "data"
SAMPLE = DATA / "sample.bin"
SHARED = Path(__file__).resolve().parents[2] / "shared" / "logs"
BIN = SHARED / "ardupilot-sample.bin"


def test_sample_values():
    log = read_log(SAMPLE)
    t = log.attitude[:, 0]
    np.testing.assert_allclose(t, 2.0 + 0.02 * np.arange(100))
    np.testing.assert_allclose(log.attitude[:, 1], 0.1 * np.sin(2 * np.pi * (t - 2.0)), atol=1e-4)
    np.testing.assert_allclose(log.attitude[:, 2], np.deg2rad(-3.0))
    np.testing.assert_allclose(log.attitude[:, 3], -np.pi)  # 180 deg wraps to -pi
    # rates from RATE (deg/s -> rad/s), interpolated 100 us back to ATT times
    np.testing.assert_allclose(log.attitude[:, 4],
                               0.2 * np.pi * np.cos(2 * np.pi * (t - 2.0)), atol=2e-3)
    assert len(log.position) == 100  # EKF core 1 ignored
    np.testing.assert_allclose(log.position[:, 1], 1.0 + (log.position[:, 0] - 2.0002), atol=1e-5)
    np.testing.assert_allclose(log.actuator[:, 4], 0.5)
    assert set(np.round(log.actuator[:, 1], 6)) == {-0.1, 0.1}
    np.testing.assert_allclose(log.attitude_target[:, 5], 0.45)  # CTUN ThO
    assert log.params == pytest.approx({"ATC_RAT_RLL_P": 0.135, "ATC_ANG_RLL_P": 4.5})
    assert log.status[0].text == "ArduCopter V4.5.0 (sample)"


@pytest.mark.skipif(not BIN.exists(), reason=f"real ArduPilot log not found at {BIN}")
def test_real_ardupilot_log_matches_dfreader():
    from pymavlink import DFReader

    assert detect_format(BIN) is LogFormat.DATAFLASH
    log = read_log(BIN)
    ref = DFReader.DFReader_binary(str(BIN), zero_time_base=False)
    att, parm, msg, nkf = [], {}, [], []
    while (m := ref.recv_msg()) is not None:
        kind = m.get_type()
        if kind == "ATT":
            att.append((m.TimeUS * 1e-6, m.Roll, m.Pitch))
        elif kind == "PARM":
            parm[m.Name] = m.Value
        elif kind == "MSG":
            msg.append(m.Message)
        elif kind == "NKF1":
            nkf.append((m.PN, m.PE, m.PD))
    ref.close()
    att_a = np.array(att)
    np.testing.assert_allclose(log.attitude[:, 0], att_a[:, 0])
    np.testing.assert_allclose(np.rad2deg(log.attitude[:, 1:3]), att_a[:, 1:3], atol=1e-9)
    assert log.params == pytest.approx(parm)
    assert [s.text for s in log.status] == msg
    np.testing.assert_allclose(log.position[:, 1:4], np.array(nkf), atol=1e-6)
    # rates from the IMU gyro: plausible for a vehicle on the ground
    assert np.abs(log.attitude[:, 4:7]).max() < 1.0
    assert len(log.actuator) == 0  # ArduPlane: no RATE record


def test_bad_magic(tmp_path):
    p = tmp_path / "x.bin"
    p.write_bytes(b"\x00" * 100)
    with pytest.raises(InputFileError, match="not an ArduPilot DataFlash log"):
        read_log(p)


def test_truncated_and_garbage(tmp_path):
    data = SAMPLE.read_bytes()
    p = tmp_path / "cut.bin"
    p.write_bytes(data[: len(data) // 2])
    assert 30 < len(read_log(p).attitude) < 70
    p.write_bytes(data[:2000] + b"\xa3\x95\xff garbage" * 10 + data[2000:])
    assert len(read_log(p).attitude) >= 99
    p.write_bytes(data[:50])
    with pytest.raises(InputFileError, match="no valid FMT"):
        read_log(p)
