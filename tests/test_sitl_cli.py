"""``mrft-tune sitl``: help, usage errors, and a real run stopped by SIGTERM."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

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
    proc = subprocess.Popen(
        [sys.executable, "-m", "mrft_gcs.cli", "sitl", "--port", str(port), "--effect",
         "sensor_lpf=30"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "COLUMNS": "200"})
    try:
        lines = []
        end = time.monotonic() + 20
        while time.monotonic() < end:
            line = proc.stdout.readline()
            lines.append(line)
            if "connect with" in line:
                break
        assert f"udp:127.0.0.1:{port}" in "".join(lines), lines
        assert "sensor_lpf=30" in "".join(lines)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(10) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
