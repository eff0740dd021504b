"""The .tlog reader and writer: committed sample, pymavlink as a reference, damage."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np
import pytest

from mrft_gcs.errors import InputFileError, UsageError
from mrft_gcs.logs import LogFormat, TlogWriter, detect_format, read_log

DATA = Path(__file__).resolve().parent / "data"
SAMPLE = DATA / "sample.tlog"


def _records(path: Path) -> list[tuple[int, bytes]]:
    """(time stamp us, frame) of each record, with pymavlink delimiting the frames."""
    from pymavlink import mavutil

    conn = mavutil.mavlink_connection(str(path), dialect="common", notimestamps=False)
    out = []
    while (m := conn.recv_msg()) is not None:
        if m.get_type() != "BAD_DATA":
            out.append((round(m._timestamp * 1e6), m.get_msgbuf()))
    conn.close()
    return out


def test_sample_values():
    log = read_log(SAMPLE)
    t = log.attitude[:, 0]
    assert len(log.attitude) == 100  # the gimbal's ATTITUDE (component 154) is not the vehicle's
    np.testing.assert_allclose(t, 12.0 + 0.02 * np.arange(100), atol=1e-9)
    np.testing.assert_allclose(log.attitude[:, 1], 0.1 * np.sin(2 * np.pi * (t - 12.0)), atol=1e-6)
    np.testing.assert_allclose(log.attitude[:, 2], -0.05, atol=1e-7)
    np.testing.assert_allclose(log.position[:, 1], 1.0 + (log.position[:, 0] - 12.0), atol=1e-5)
    assert set(np.round(log.actuator[:, 1], 6)) == {-0.1, 0.1}
    np.testing.assert_allclose(log.actuator[:, 4], 0.55, atol=1e-6)
    np.testing.assert_allclose(log.attitude_target[:, 1:5], [[1, 0, 0, 0]] * 100)
    assert log.params == {"MC_ROLL_P": 6.5, "SYS_AUTOSTART": 7.0, "MC_PITCH_P": 6.0}
    assert [s.text for s in log.status] == ["Relay test done"]
    assert log.status[0].severity == 4
    assert len(log.heartbeats) == 5 and all(h.autopilot == 12 for h in log.heartbeats)
    assert log.heartbeats[0].armed


def test_ground_station_commands_land_on_the_vehicle_clock():
    log = read_log(SAMPLE)
    # commands were logged 1 ms after the attitude sample's boot time mapped to wall time,
    # which arrives 2 ms late: so 1 ms before the sample on the vehicle clock
    np.testing.assert_allclose(log.actuator[:, 0], log.attitude[:, 0] - 0.001, atol=1e-5)
    # the relay switches with the sign of roll
    roll = log.attitude[:, 1]
    np.testing.assert_array_equal(log.actuator[:, 1] > 0, roll < 0)


def test_agrees_with_pymavlink():
    from pymavlink import mavutil

    conn = mavutil.mavlink_connection(str(SAMPLE), dialect="common")
    att = []
    while (m := conn.recv_match(type="ATTITUDE")) is not None:
        if m.get_srcComponent() == 1:
            att.append((m.roll, m.pitch, m.yaw, m.rollspeed, m.pitchspeed, m.yawspeed))
    conn.close()
    np.testing.assert_array_equal(read_log(SAMPLE).attitude[:, 1:], np.array(att))


def _rewrite(path: Path, records: list[tuple[int, bytes]]) -> None:
    path.write_bytes(b"".join(struct.pack(">Q", t) + f for t, f in records))


def test_bad_crc_frame_is_dropped_and_the_rest_read(tmp_path):
    records = _records(SAMPLE)
    i = next(k for k, (_, f) in enumerate(records) if f[7] == 30 and f[0] == 0xFD)
    t, frame = records[i]
    bad = bytearray(frame)
    bad[12] ^= 0xFF  # a payload byte: the CRC no longer matches
    records[i] = (t, bytes(bad))
    p = tmp_path / "crc.tlog"
    _rewrite(p, records)
    assert len(read_log(p).attitude) == 99


def test_garbage_between_records_is_skipped(tmp_path):
    data = SAMPLE.read_bytes()
    p = tmp_path / "junk.tlog"
    p.write_bytes(data[:3000] + b"\x00\x01junk\xfd\x00" * 7 + data[3000:])
    log = read_log(p)
    assert len(log.attitude) >= 98 and len(log.position) >= 98


def test_truncated_log_reads_up_to_the_cut(tmp_path):
    data = SAMPLE.read_bytes()
    p = tmp_path / "cut.tlog"
    p.write_bytes(data[: len(data) // 2 + 7])
    log = read_log(p)
    assert 40 < len(log.attitude) < 60


def test_v1_frames_are_read(tmp_path):
    records = _records(SAMPLE)
    assert any(f[0] == 0xFE for _, f in records)
    v1_only = [(t, f) for t, f in records if f[0] == 0xFE]
    p = tmp_path / "v1.tlog"
    _rewrite(p, v1_only)
    assert len(read_log(p).attitude) == 10


@pytest.mark.parametrize(
    "content, problem",
    [
        (b"", "empty file"),
        (b"hello world, not a log at all", "no MAVLink frames"),
        (bytes(range(256)) * 4, "no valid ATTITUDE"),
    ],
)
def test_not_a_tlog(tmp_path, content, problem):
    p = tmp_path / "x.tlog"
    p.write_bytes(content)
    with pytest.raises(InputFileError) as e:
        read_log(p)
    msg = str(e.value)
    assert str(p) in msg and problem in msg and "\n" not in msg


def test_missing_file(tmp_path):
    with pytest.raises(InputFileError, match="no such file"):
        read_log(tmp_path / "nope.tlog")


def test_detected_by_content_whatever_the_extension(tmp_path):
    p = tmp_path / "session.dat"
    p.write_bytes(SAMPLE.read_bytes())
    assert detect_format(p) is LogFormat.TLOG
    assert len(read_log(p).attitude) == 100


# --- writer ---------------------------------------------------------------------------------

def test_writer_round_trip(tmp_path):
    records = _records(SAMPLE)
    p = tmp_path / "copy.tlog"
    with TlogWriter(p) as w:
        for t, frame in records:
            w.write(frame, t * 1e-6)
    assert w.closed and w.frames == len(records)
    assert p.read_bytes() == SAMPLE.read_bytes()


def test_writer_flushes_each_frame(tmp_path):
    t, frame = _records(SAMPLE)[0]
    p = tmp_path / "live.tlog"
    w = TlogWriter(p)
    w.write(frame, t * 1e-6)
    assert p.stat().st_size == 8 + len(frame)  # visible before close
    w.close()
    w.close()  # idempotent


def test_writer_refuses_to_overwrite(tmp_path):
    p = tmp_path / "a.tlog"
    p.write_bytes(b"keep")
    with pytest.raises(UsageError, match="already exists"):
        TlogWriter(p)
    assert p.read_bytes() == b"keep"
    TlogWriter(p, overwrite=True).close()
    assert p.read_bytes() == b""


def test_writer_bad_folder(tmp_path):
    with pytest.raises(UsageError, match="cannot create"):
        TlogWriter(tmp_path / "no" / "such" / "dir.tlog")


@pytest.mark.parametrize("frame, t", [(b"\x00" * 20, 1.0), (b"\xfd", 1.0),
                                      (b"\xfd" + b"\x00" * 20, math.nan), (b"\xfe" * 20, -1.0)])
def test_writer_rejects_bad_input(tmp_path, frame, t):
    with TlogWriter(tmp_path / "w.tlog") as w, pytest.raises(ValueError):
        w.write(frame, t)


def test_writer_closed(tmp_path):
    w = TlogWriter(tmp_path / "w.tlog")
    w.close()
    with pytest.raises(ValueError, match="closed"):
        w.write(b"\xfe" * 20, 1.0)


def test_file_order_follows_the_rows_it_was_logged_with():
    """``file_order``: where each ATTITUDE, LOCAL_POSITION_NED and SET_ row was logged; it
    stays with its row when cleaning drops non-finite rows and sorts by time."""
    from mrft_gcs.logs import decode_log

    d = decode_log(SAMPLE)
    for name in ("attitude", "position", "actuator"):
        assert len(d.file_order[name]) == len(getattr(d, name)), name
    clean = d.cleaned()
    assert all(np.all(np.diff(clean.file_order[k]) > 0) for k in ("attitude", "actuator"))
    bad = d.attitude.copy()
    bad[3, 1] = np.nan
    from dataclasses import replace

    dropped = replace(d, attitude=bad).cleaned()
    assert len(dropped.file_order["attitude"]) == len(dropped.attitude) == len(d.attitude) - 1
    assert d.file_order["attitude"][3] not in dropped.file_order["attitude"]


def test_sink_queues_frames_while_the_file_is_stuck(tmp_path):
    """The stream's ticks log their frames through the sink: a write to disk that blocks
    (a journal commit, dirty-page throttling) must hold up the writer thread, not them."""
    import threading

    from mrft_gcs.link.tlog import TlogSink

    sink = TlogSink(tmp_path / "s.tlog", every_s=0.001)
    real = sink._writer
    stuck, entered = threading.Event(), threading.Event()

    class StuckFile:  # the real writer behind a write that blocks until released
        def write(self, frame, t, flush=True):
            entered.set()
            stuck.wait()
            real.write(frame, t, flush=flush)

        def flush(self):
            real.flush()

        def close(self):
            real.close()

    sink._writer = StuckFile()
    frames = [bytes.fromhex("fe09") + bytes([k]) + bytes.fromhex("0101000000000002030451040300")
              for k in range(100)]
    sink.write(frames[0])
    assert entered.wait(5.0)  # the writer thread is now stuck inside the file write
    writer = threading.Thread(target=lambda: [sink.write(f) for f in frames[1:]])
    writer.start()
    writer.join(5.0)
    assert not writer.is_alive()  # every write returned while the file was stuck
    stuck.set()
    sink.close()
    data = (tmp_path / "s.tlog").read_bytes()
    assert sink.frames == 100 and len(data) == 100 * (8 + len(frames[0]))
    assert [data[k * 25 + 10] for k in range(100)] == list(range(100))  # in order


def test_sink_frames_reach_the_file_before_close(tmp_path):
    import time

    from mrft_gcs.link.tlog import TlogSink

    t, frame = _records(SAMPLE)[0]
    sink = TlogSink(tmp_path / "live.tlog")
    sink.write(frame)
    deadline = time.monotonic() + 5.0
    while (tmp_path / "live.tlog").stat().st_size == 0 and time.monotonic() < deadline:
        time.sleep(0.005)
    assert (tmp_path / "live.tlog").stat().st_size == 8 + len(frame)  # a crash keeps it
    sink.close()
    sink.close()  # idempotent
    sink.write(frame)  # after close: dropped, no error
    assert sink.frames == 1


def test_sink_that_cannot_write_stops_logging_and_says_why(tmp_path):
    """A full disk must not stop the flight whose frames it logs: the sink keeps taking
    frames, drops them, and keeps the reason (the tune puts it in its notes)."""
    from mrft_gcs.link.tlog import TlogSink

    t, frame = _records(SAMPLE)[0]
    sink = TlogSink(tmp_path / "full.tlog", every_s=0.001)
    real = sink._writer

    class FullDisk:
        def write(self, frame, t, flush=True):
            raise OSError(28, "No space left on device")

        def flush(self):
            pass

        def close(self):
            real.close()

    sink._writer = FullDisk()
    for _ in range(50):
        sink.write(frame)
    sink.close()
    assert sink.error == "No space left on device" and sink.frames == 0
    sink.write(frame)  # still no error to the caller
