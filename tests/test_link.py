"""The MAVLink link over real UDP sockets: strings, silent vehicles, the SITL, the streamer,
the watchdog, signing, and the .tlog of both directions."""

from __future__ import annotations

import os
import socket
import time

import pytest

from mrft_gcs.cli import main
from mrft_gcs.errors import LinkError, SafetyAbort, UsageError
from mrft_gcs.link import (
    PX4_MODES,
    LinkKind,
    SetpointStreamer,
    VehicleLink,
    check_serial_baud,
    link_needs,
    load_signing_key,
    measure_link,
    parse_connection_string,
    period_stats,
    require_relay_capable,
)
from mrft_gcs.telemetry import ActuatorTarget, Attitude, AutopilotFamily, TelemetrySource

KEY = bytes(range(32))


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _sitl(port: int, signing_key: bytes | None = None):
    sitl = pytest.importorskip("mrft_gcs.sitl", reason="SITL not built yet")
    if not hasattr(sitl, "SitlProcess"):
        pytest.skip("SitlProcess not built yet")
    return sitl.SitlProcess(vehicle="qdrone", port=port, speedup=1.0, seed=0,
                            signing_key=signing_key)


# ---------------------------------------------------------------- connection strings
@pytest.mark.parametrize("text, kind, where", [
    ("udp:127.0.0.1:14540", LinkKind.UDP_IN, ("127.0.0.1", 14540)),
    ("udpin:0.0.0.0:14550", LinkKind.UDP_IN, ("0.0.0.0", 14550)),
    ("udpout:192.168.1.10:14555", LinkKind.UDP_OUT, ("192.168.1.10", 14555)),
    ("tcp:localhost:5760", LinkKind.TCP, ("localhost", 5760)),
    ("tcpin:0.0.0.0:5760", LinkKind.TCP_IN, ("0.0.0.0", 5760)),
])
def test_network_strings(text, kind, where):
    spec = parse_connection_string(text)
    assert spec.kind is kind and (spec.host, spec.port) == where
    assert spec.pymavlink_device().endswith(f"{where[0]}:{where[1]}")


def test_serial_strings_and_baud():
    assert parse_connection_string("/dev/ttyUSB0").baud_bps == 57600
    assert parse_connection_string("/dev/ttyACM0,921600").baud_bps == 921600
    assert parse_connection_string("/dev/ttyACM0,921600", baud=115200).baud_bps == 115200
    assert parse_connection_string("COM3", baud=57600).device == "COM3"


@pytest.mark.parametrize("text", ["udp:127.0.0.1", "udp::14540", "14540", "udp:host:99999",
                                  "http://127.0.0.1:14540", "", "tcp:127.0.0.1:port"])
def test_bad_strings_say_the_accepted_forms(text):
    with pytest.raises(LinkError) as err:
        parse_connection_string(text)
    assert "\n" not in str(err.value)
    if "99999" not in text:
        assert "udpout:HOST:PORT" in str(err.value)


def test_bad_string_via_cli_is_one_line_exit_3(capsys):
    assert main(["params", "show", "--connect", "udp:127.0.0.1"]) == 3
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "udp:HOST:PORT" in err


def test_silent_vehicle_times_out_with_link_error():
    port = free_udp_port()
    t = time.monotonic()
    with pytest.raises(LinkError, match=rf"no heartbeat from udp:127.0.0.1:{port} within 0.5 s"):
        VehicleLink.connect(f"udp:127.0.0.1:{port}", timeout_s=0.5)
    assert time.monotonic() - t < 1.5


def test_silent_vehicle_via_cli_exit_3(capsys):
    port = free_udp_port()
    assert main(["params", "show", "-c", f"udp:127.0.0.1:{port}", "--timeout", "0.3"]) == 3
    assert "is the vehicle on" in capsys.readouterr().err


# ---------------------------------------------------------------- signing keys, link budget
def test_signing_key_forms(tmp_path):
    raw = tmp_path / "raw.key"
    raw.write_bytes(KEY)
    hexfile = tmp_path / "hex.key"
    hexfile.write_text(KEY.hex() + "\n")
    assert load_signing_key(raw) == load_signing_key(hexfile) == load_signing_key(KEY.hex()) == KEY
    short = tmp_path / "short.key"
    short.write_bytes(b"123")
    with pytest.raises(UsageError, match="32-byte"):
        load_signing_key(short)
    with pytest.raises(UsageError, match="neither a file nor 64 hex"):
        load_signing_key("no-such-file")


def test_a_57600_radio_cannot_carry_250_hz():
    with pytest.raises(LinkError, match=r"57600-baud .* at least 460800 baud"):
        check_serial_baud(57600)
    check_serial_baud(921600)
    assert link_needs(50, 50).min_baud <= 115200


def test_period_stats_from_send_times():
    t = 0.004 * __import__("numpy").arange(251)
    s = period_stats(t, 250.0)
    assert s.rate_hz_achieved == pytest.approx(250.0)
    assert s.jitter_p99_ms == pytest.approx(0.0, abs=1e-9)


def test_spin_margin_follows_late_wakeups_within_bounds():
    import numpy as np

    from mrft_gcs.link.streamer import spin_margin_s

    period = 0.004
    assert spin_margin_s(np.full(250, np.nan), period) == pytest.approx(0.0004)  # nothing yet
    prompt = np.full(250, 0.00005)  # a kernel that wakes within 50 us: the floor
    assert spin_margin_s(prompt, period) == pytest.approx(0.0004)
    late = prompt.copy()
    late[:10] = 0.003  # 4 % of sleeps 3 ms late: the 99th percentile is 3 ms
    assert spin_margin_s(late, period) == pytest.approx(0.0032)
    worse = np.full(250, 0.010)  # later than a period: still sleeps 10 % of it
    assert spin_margin_s(worse, period) == pytest.approx(0.9 * period)


# ---------------------------------------------------------------- against the SITL
def _tlog_frames(path):
    """(sysid, msgid) of every frame in a .tlog (8-byte stamp, then the frame)."""
    data = path.read_bytes()
    out, i = [], 0
    while i < len(data):
        i += 8
        if data[i] == 0xFD:
            n = 12 + data[i + 1] + (13 if data[i + 2] & 1 else 0)
            out.append((data[i + 5], int.from_bytes(data[i + 7:i + 10], "little")))
        else:
            n = 8 + data[i + 1]
            out.append((data[i + 3], data[i + 5]))
        i += n
    return out


def test_link_with_sitl_telemetry_quality_tlog(tmp_path):
    port = free_udp_port()
    tlog = tmp_path / "session.tlog"
    with _sitl(port), VehicleLink.connect(f"udp:127.0.0.1:{port}", tlog_path=tlog) as link:
        assert isinstance(link, TelemetrySource)
        assert link.family is AutopilotFamily.PX4
        q = measure_link(link, rate_hz=250.0, window_s=1.0)
        require_relay_capable(q)  # loopback carries 250 Hz
        assert q.attitude_hz >= 200 and q.position_hz >= 200, q.line()
        assert q.rtt_p50_ms < 50 and q.rtt_lost == 0
        seen = [link.next_sample(1.0) for _ in range(50)]
        assert any(isinstance(s, Attitude) for s in seen)
        assert link.counters.nonfinite_dropped == 0
    frames = _tlog_frames(tlog)
    sent = [m for sys_id, m in frames if sys_id == 255]
    got = [m for sys_id, m in frames if sys_id != 255]
    assert 76 in sent and 111 in sent and 111 in got  # COMMAND_LONG, TIMESYNC out; TIMESYNC in
    assert got.count(30) >= 200 and 77 in got  # ATTITUDE, COMMAND_ACK in


def test_streamer_rate_and_watchdog_when_telemetry_stops():
    port = free_udp_port()
    sitl = _sitl(port)
    with sitl, VehicleLink.connect(f"udp:127.0.0.1:{port}") as link:
        link.request_message_interval("ATTITUDE", 250)
        streamer = SetpointStreamer(link, lambda t: ActuatorTarget(t, 0.0, 0.0, 0.0, 0.0))
        streamer.start()
        time.sleep(1.5)
        assert streamer.abort_reason is None
        stats = streamer.stats()
        # the rate it keeps, not its timing quality: that is measured by
        # benchmarks/streamer_jitter.py (a loaded 2-core CI box skips a few ticks)
        assert stats.rate_hz_achieved == pytest.approx(250.0, rel=0.15), stats.line()
        assert abs(stats.period_p50_ms - 4.0) < 0.5, stats.line()
        sitl.__exit__(None, None, None)  # the vehicle goes silent mid-stream
        t_stop = time.monotonic()
        assert streamer.wait(3.0)
        assert time.monotonic() - t_stop < 1.5
        assert streamer.landing_commanded
        assert link.counters.sent["COMMAND_LONG"] >= 2  # NAV_LAND and the land mode
        with pytest.raises(SafetyAbort, match="no telemetry .* landing commanded"):
            streamer.raise_if_aborted()


def test_modes_and_arming_on_sitl():
    port = free_udp_port()
    with _sitl(port), VehicleLink.connect(f"udp:127.0.0.1:{port}") as link:
        link.set_mode(PX4_MODES["position"])
        link.arm()
        assert link.next_sample(1.0) is not None
        link.land()
        link.set_mode(PX4_MODES["land"])


def test_signing_gcs_signs_and_the_keyed_sitl_accepts(tmp_path):
    keyfile = tmp_path / "link.key"
    keyfile.write_bytes(KEY)
    port = free_udp_port()
    with _sitl(port, signing_key=KEY):
        with VehicleLink.connect(f"udp:127.0.0.1:{port}", signing_key=keyfile) as link:
            assert link.signed
            link.request_message_interval("ATTITUDE", 100)  # acknowledged: signature accepted
        with VehicleLink.connect(f"udp:127.0.0.1:{port}") as unsigned:
            with pytest.raises(LinkError, match="did not acknowledge"):
                unsigned.command(511, (30, 1e4), timeout_s=0.3, retries=1)


def test_links_speak_mavlink2():  # signing needs it
    from mrft_gcs.link.connection import mavlink_module
    assert mavlink_module().mavlink.WIRE_PROTOCOL_VERSION == "2.0"


class _NullSink:
    """A link that takes setpoints and always has fresh telemetry (stream timing tests)."""

    def send_setpoint(self, target):
        pass

    def telemetry_age_s(self):
        return 0.0

    def land(self, **kw):
        pass


def test_streamer_shortens_the_switch_interval_only_while_it_runs():
    import sys

    before = sys.getswitchinterval()
    a = SetpointStreamer(_NullSink(), lambda t: None, watchdog_s=None).start()
    b = SetpointStreamer(_NullSink(), lambda t: None, watchdog_s=None).start()
    time.sleep(0.1)
    assert sys.getswitchinterval() == pytest.approx(min(before, 0.0005))
    a.stop()
    assert sys.getswitchinterval() == pytest.approx(min(before, 0.0005))  # b still streams
    b.stop()
    assert sys.getswitchinterval() == pytest.approx(before)


def test_stream_workers_are_pinned_to_two_cpus_where_there_are_two(monkeypatch):
    import os

    from mrft_gcs.link.streamer import stream_cpus

    allowed = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
    assert stream_cpus(1) == [None]
    two = stream_cpus(2)
    if len(allowed) >= 2:
        assert two == allowed[-2:] and two[0] != two[1]
    else:
        assert two == [None]
    monkeypatch.setenv("MRFT_STREAM_WORKERS", "1")
    assert stream_cpus() == [None]
    monkeypatch.setenv("MRFT_STREAM_WORKERS", "3")
    with pytest.raises(ValueError, match="1 or 2"):
        stream_cpus()


def test_two_stream_workers_send_each_tick_once():
    """The workers race for every tick: one sends it, the other skips it."""
    import threading

    sent: list[tuple[float, str]] = []

    class Sink:
        def send_setpoint(self, target):
            sent.append((target, threading.current_thread().name))

        def telemetry_age_s(self):
            return 0.0

        def land(self, **kw):
            pass

    s = SetpointStreamer(Sink(), lambda t: t, watchdog_s=None, workers=2)
    with s:
        time.sleep(1.0)
    stats = s.stats()
    assert stats.sent == len(sent)
    assert all(b > a for (a, _), (b, _) in zip(sent, sent[1:], strict=False))  # in order
    # one second: 250 ticks, each sent once or skipped (both sending would make ~500)
    assert len(sent) + stats.skipped == pytest.approx(250, rel=0.05)
    if s.workers == 2:
        assert {name for _, name in sent} == {"setpoint-streamer-0", "setpoint-streamer-1"}


def test_latency_hints_need_no_privilege():
    import sys
    import threading

    from mrft_gcs.link.latency import latency_hints

    got: list[str] = []
    t = threading.Thread(target=lambda: got.extend(latency_hints()))
    t.start()
    t.join()
    if sys.platform.startswith("linux"):
        assert "timer slack 1 us" in got  # prctl works for any user
    else:
        assert got == []


def test_cpu_wake_latency_request_is_written_held_and_released(tmp_path, monkeypatch):
    import struct

    from mrft_gcs.link.latency import CpuWakeLatency

    dev = tmp_path / "qos"
    dev.write_bytes(b"")
    q = CpuWakeLatency(us=20, path=str(dev))
    assert q.acquire() == "CPU wake-up latency <= 20 us" and q.held
    assert struct.unpack("i", dev.read_bytes()) == (20,)  # the kernel's binary s32 form
    fd = q._fd
    q.release()
    assert not q.held
    with pytest.raises(OSError):
        os.fstat(fd)  # closing the file is what ends the request
    missing = CpuWakeLatency(us=0, path=str(tmp_path / "none"))
    assert missing.acquire().startswith("CPU wake-up latency not bounded") and not missing.held
    assert not missing.denied
    monkeypatch.setenv("MRFT_CPU_LATENCY_US", "off")
    off = CpuWakeLatency(path=str(dev))
    assert "MRFT_CPU_LATENCY_US=off" in off.acquire() and not off.held
    monkeypatch.setenv("MRFT_CPU_LATENCY_US", "-1")
    with pytest.raises(UsageError, match=">= 0"):
        CpuWakeLatency(path=str(dev))
    monkeypatch.setenv("MRFT_CPU_LATENCY_US", "fast")
    with pytest.raises(UsageError, match="whole microseconds"):
        CpuWakeLatency(path=str(dev))


@pytest.mark.skipif(not hasattr(os, "geteuid"), reason="POSIX file permissions")
def test_cpu_wake_latency_without_permission_says_how_to_grant_it(tmp_path):
    import subprocess
    import sys

    dev = tmp_path / "qos"
    dev.write_bytes(b"")
    dev.chmod(0o444)
    # root writes anywhere: the child drops to nobody first (the device's usual refusal)
    code = ("import os\nfrom mrft_gcs.link.latency import CpuWakeLatency as Q\n"
            "if os.geteuid() == 0: os.setuid(65534)\n"
            f"q = Q(us=0, path={str(dev)!r}); print(q.acquire()); print(q.denied, q.held)")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    said, flags = run.stdout.strip().splitlines()
    assert "no write access" in said and "run as root or grant it" in said
    assert flags == "True False"


@pytest.mark.skipif(not os.access("/dev/cpu_dma_latency", os.W_OK),
                    reason="needs write access to /dev/cpu_dma_latency")
def test_stream_bounds_cpu_wake_latency_only_while_it_runs():
    import struct

    def current() -> int:
        fd = os.open("/dev/cpu_dma_latency", os.O_RDONLY)
        try:
            return struct.unpack("i", os.read(fd, 4))[0]
        finally:
            os.close(fd)

    before = current()
    s = SetpointStreamer(_NullSink(), lambda t: None, watchdog_s=None).start()
    try:
        assert s.hints[0] == "CPU wake-up latency <= 0 us"
        assert current() == 0
    finally:
        s.stop()
    assert current() == before


def test_bad_cpu_latency_setting_fails_one_line_before_connecting(capsys, monkeypatch):
    monkeypatch.setenv("MRFT_CPU_LATENCY_US", "fast")
    port = free_udp_port()  # nothing listens: connecting first would fail with exit 3
    assert main(["tune", "-c", f"udp:127.0.0.1:{port}", "-p", "sitl", "--yes",
                 "--timeout", "0.3"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "MRFT_CPU_LATENCY_US='fast'" in err
