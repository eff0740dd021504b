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


def test_a_bad_connection_string_is_refused_before_the_take_off_question(capsys, monkeypatch):
    asked = []
    monkeypatch.setattr("typer.confirm", lambda *a, **k: asked.append(a) or True)
    assert main(["tune", "--connect", "bogus:foo"]) == 3
    assert not asked
    assert "cannot read connection string" in capsys.readouterr().err


def test_answering_no_to_the_take_off_question_exits_non_zero(capsys, monkeypatch):
    monkeypatch.setattr("typer.confirm", lambda *a, **k: False)
    assert main(["tune", "--connect", "udp:127.0.0.1:14599"]) == 130
    assert "nothing done" in capsys.readouterr().err
