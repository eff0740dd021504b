"""The CLI is thin: usage errors and library errors become one line and an exit code."""

from __future__ import annotations

import subprocess
import sys

from mrft_gcs.cli import main


def test_help_lists_commands(capsys):
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    assert "demo" in out and "design" in out


def test_unknown_command_is_usage_error():
    assert main(["no-such-command"]) == 2


def test_console_script_runs_as_module():
    proc = subprocess.run(
        [sys.executable, "-m", "mrft_gcs.cli", "--help"], capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 0, proc.stderr
    assert "mrft-tune" in proc.stdout
