"""A connection that never answers: one line, exit code 3, no .tlog left behind, and the wait
is shown while it lasts."""

from __future__ import annotations

import socket

import pytest

from mrft_gcs.cli import main
from mrft_gcs.errors import LinkError


def _silent_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_failed_tune_connect_leaves_nothing_and_says_it_waited(tmp_path, capsys):
    port = _silent_udp_port()
    code = main(["tune", "-c", f"udp:127.0.0.1:{port}", "--dry-link", "--timeout", "1",
                 "--backup-dir", str(tmp_path)])
    assert code == LinkError.exit_code == 3
    err = capsys.readouterr().err
    assert f"connecting to udp:127.0.0.1:{port}: waiting up to 1 s for a vehicle heartbeat" in err
    errors = [ln for ln in err.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1 and "no heartbeat" in errors[0], err
    assert list(tmp_path.iterdir()) == []  # no .tlog, no backup


def test_failed_link_connect_removes_its_tlog(tmp_path):
    from mrft_gcs.link import VehicleLink

    tlog = tmp_path / "session.tlog"
    with pytest.raises(LinkError, match="no heartbeat"):
        VehicleLink.connect(f"udpout:127.0.0.1:{_silent_udp_port()}", timeout_s=1.5,
                            tlog_path=tlog)
    assert not tlog.exists()


def test_failed_params_connect_shows_the_wait(capsys):
    port = _silent_udp_port()
    assert main(["params", "show", "-c", f"udp:127.0.0.1:{port}", "--timeout", "0.5"]) == 3
    err = capsys.readouterr().err
    assert "waiting up to 0.5 s for a vehicle heartbeat" in err and "no heartbeat" in err
