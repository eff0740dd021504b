"""Fleet tuning (mrft_gcs.fleet): file validation, failure isolation, three SITL vehicles."""

from __future__ import annotations

import json
import time
from types import SimpleNamespace

import pytest

from mrft_gcs.errors import FleetError, LinkError, UsageError
from mrft_gcs.fleet import load_fleet, parse_fleet, tune_fleet


def _spec(tmp_path, body: str):
    f = tmp_path / "fleet.toml"
    f.write_text(body)
    return f


def test_parse_and_defaults(tmp_path):
    f = _spec(tmp_path, '[defaults]\nprofile = "sitl"\nmax_tilt_deg = 25\n\n'
                        '[[vehicle]]\nname = "a"\nconnect = "udp:127.0.0.1:1"\n\n'
                        '[[vehicle]]\nname = "b"\nconnect = "udp:127.0.0.1:2"\nprofile = "px4"\n')
    spec = load_fleet(f)
    assert [v.profile for v in spec.vehicles] == ["sitl", "px4"]
    assert spec.vehicles[0].limits == {"max_tilt_deg": 25.0}


@pytest.mark.parametrize("body", [
    "", '[[vehicle]]\nname = "a"\n', '[[vehicle]]\nconnect = "x"\nbogus = 1\n',
    '[[vehicle]]\nconnect = "x"\nmax_tilt_deg = -3\n',
    '[[vehicle]]\nname = "a"\nconnect = "x"\n[[vehicle]]\nname = "a"\nconnect = "y"\n',
    '[[vehicle]]\nconnect = "x"\nprofile = "nope"\n',
])
def test_bad_fleet_files(tmp_path, body):
    with pytest.raises(UsageError):
        load_fleet(_spec(tmp_path, body))


def _fake_tuner(connection, profile, **kw):
    if connection.endswith(":13"):
        raise LinkError("no heartbeat on udp:127.0.0.1:13: check the connection")
    if connection.endswith(":666"):
        raise RuntimeError("a bug")
    time.sleep(0.2)
    return SimpleNamespace(status="ok", error=None, parameters=())


@pytest.mark.parametrize("serial", [False, True])
def test_one_failure_does_not_stop_the_others(tmp_path, serial):
    spec = parse_fleet({"defaults": {"profile": "sitl", "backup_dir": str(tmp_path)},
                        "vehicle": [{"name": n, "connect": f"udp:127.0.0.1:{p}"}
                                    for n, p in (("a", 1), ("bad", 13), ("b", 2), ("bug", 666))]})
    events = []
    t = time.monotonic()
    res = tune_fleet(spec, serial=serial, tuner=_fake_tuner,
                     on_status=lambda n, e: events.append((n, e)))
    took = time.monotonic() - t
    assert [v.name for v in res.vehicles] == ["a", "bad", "b", "bug"]
    assert [v.ok for v in res.vehicles] == [True, False, True, False]
    assert res.vehicles[1].exit_code == LinkError.exit_code and "heartbeat" in res.vehicles[1].error
    assert res.vehicles[3].status == "error:1:internal"
    assert ("a", "done") in events and ("bad", "done") in events
    assert (took > 0.4) if serial else (took < 0.39)
    assert (tmp_path / "a").is_dir()


def test_three_sitl_vehicles_one_failing_cli(tmp_path):
    from mrft_gcs.cli import main
    from mrft_gcs.sitl import SitlProcess
    from mrft_gcs.sitl.process import free_udp_port

    dead = free_udp_port()  # nobody serves it: that vehicle never answers
    with SitlProcess("qdrone", port=None) as a, SitlProcess("racer250", port=None) as b:
        f = _spec(tmp_path, f'[defaults]\nprofile = "sitl"\ndry_link = true\n'
                            f'backup_dir = "{tmp_path}"\n\n'
                            f'[[vehicle]]\nname = "qd"\nconnect = "{a.connection_string}"\n\n'
                            f'[[vehicle]]\nname = "silent"\nconnect = "udp:127.0.0.1:{dead}"\n\n'
                            f'[[vehicle]]\nname = "racer"\nconnect = "{b.connection_string}"\n')
        out = tmp_path / "fleet.json"
        code = main(["fleet", str(f), "--json", str(out)])
    assert code == FleetError.exit_code
    data = json.loads(out.read_text())
    by = {v["name"]: v for v in data["vehicles"]}
    assert by["qd"]["status"] == "dry-link" and by["racer"]["status"] == "dry-link", by
    assert by["silent"]["exit_code"] == LinkError.exit_code
    assert by["qd"]["report"]["vehicle"]["connection"] == a.connection_string
    assert data["ok"] is False
