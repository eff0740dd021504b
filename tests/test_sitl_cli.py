"""``mrft-tune sitl``: help, usage errors, and a real run stopped by SIGTERM."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest
from sitl_cli import start_sitl_cli

from mrft_gcs.cli import main
from mrft_gcs.sitl.process import free_udp_port


def test_help_has_example(capsys):
    assert main(["sitl", "--help"]) == 0
    out = capsys.readouterr().out
    assert "--vehicle" in out and "--effect" in out and "Example" in out


def test_bad_vehicle_is_usage_error(capsys):
    assert main(["sitl", "--vehicle", "nope"]) == 2
    err = capsys.readouterr().err
    assert "qdrone" in err and "racer250" in err


def test_bad_effect_is_usage_error(capsys):
    assert main(["sitl", "--effect", "warp=1"]) == 2
    assert main(["sitl", "--effect", "sensor_lpf"]) == 2


def test_runs_prints_connection_string_and_stops_on_sigterm():
    port = free_udp_port()
    proc, text = start_sitl_cli("--port", str(port), "--effect", "sensor_lpf=30")
    try:
        assert f"udp:127.0.0.1:{port}" in text, text
        assert "sensor_lpf=30" in text
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(10) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_sitl_process_runs_in_its_own_session_and_exits_with_its_parent():
    code = ("import time\n"
            "from mrft_gcs.sitl import SitlProcess\n"
            "s = SitlProcess(vehicle='qdrone', port=None).start()\n"
            "print(s._proc.pid, flush=True)\n"
            "time.sleep(60)\n")
    parent = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        pid = int(parent.stdout.readline())
        assert os.getsid(pid) == pid != os.getsid(parent.pid)  # a session of its own
    finally:
        parent.kill()
        parent.wait()
    end = time.monotonic() + 10
    while time.monotonic() < end:  # gone, or a zombie waiting for init to reap it
        try:
            with open(f"/proc/{pid}/stat") as f:
                if f.read().split(")")[1].split()[0] == "Z":
                    break
        except FileNotFoundError:
            break
        time.sleep(0.1)
    else:
        os.kill(pid, signal.SIGKILL)
        raise AssertionError("the SITL outlived its parent")
