"""Parameters: the .params format, and backup / write / read-back / rollback / restore on the
SITL over real UDP."""

from __future__ import annotations

import socket

import pytest

from mrft_gcs.cli import main
from mrft_gcs.errors import InputFileError, ParameterError
from mrft_gcs.link import VehicleLink
from mrft_gcs.loops import Loop
from mrft_gcs.params import Param, ParamClient, read_params_file, write_params_file
from mrft_gcs.profiles import PDGains, gains_to_params, load_profile


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def sitl_port():
    sitl = pytest.importorskip("mrft_gcs.sitl", reason="SITL not built yet")
    if not hasattr(sitl, "SitlProcess"):
        pytest.skip("SitlProcess not built yet")
    port = free_udp_port()
    with sitl.SitlProcess(vehicle="qdrone", port=port, speedup=1.0, seed=0, signing_key=None):
        yield port


@pytest.fixture
def client(sitl_port):
    with VehicleLink.connect(f"udp:127.0.0.1:{sitl_port}") as link:
        yield ParamClient(link)


# ---------------------------------------------------------------- the .params file format
def test_params_file_is_qgc_format_and_round_trips(tmp_path):
    path = tmp_path / "b.params"
    params = [Param("MC_ROLL_P", 6.5), Param("MC_ROLLRATE_P", 0.15),
              Param("SYS_AUTOSTART", 4001, 6)]
    write_params_file(path, params, vehicle_id=1, component_id=1, stack="px4")
    lines = path.read_text().splitlines()
    assert lines[0] == "# Onboard parameters for Vehicle 1"
    assert "# Vehicle-Id Component-Id Name Value Type" in lines
    assert "1\t1\tMC_ROLL_P\t6.500000000000000000\t9" in lines
    assert "1\t1\tSYS_AUTOSTART\t4001\t6" in lines
    back = read_params_file(path)
    assert [e.param for e in back] == params
    assert {(e.vehicle_id, e.component_id) for e in back} == {(1, 1)}


@pytest.mark.parametrize("text, match", [
    ("1\t1\tMC_ROLL_P\t6.5\t9\n1\t1\tMC_PITCH_P\n", ":2:"),
    ("1\t1\tMC_ROLL_P\tabc\t9\n", ":1:"),
    ("1\t1\tMC_ROLL_P\tnan\t9\n", ":1:"),
    ("# only comments\n", "holds no parameters"),
])
def test_malformed_params_files(tmp_path, text, match):
    path = tmp_path / "bad.params"
    path.write_text(text)
    with pytest.raises(InputFileError, match=match):
        read_params_file(path)


def test_missing_params_file_via_cli_exit_2(tmp_path, capsys):
    assert main(["params", "restore", str(tmp_path / "none.params"), "-c",
                 "udp:127.0.0.1:1", "--yes"]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


# ---------------------------------------------------------------- on the SITL
def test_read_one_and_all(client):
    assert client.read("MC_ROLL_P").value == pytest.approx(6.5)
    everything = client.read_all()
    assert "MPC_THR_HOVER" in everything and len(everything) > 20


def test_backup_write_readback_restore(client, tmp_path):
    profile = load_profile("sitl")
    hover = client.read("MPC_THR_HOVER").value
    values = gains_to_params(profile, {Loop.ROLL: PDGains(Kc=1.2, Kd=0.2)}, hover)
    before = client.read_many(values)
    result = client.write(values, tmp_path)
    # backup first, with the old values, in QGC format
    backup = {e.param.name: e.param.value for e in read_params_file(result.backup_path)}
    assert backup == {n: pytest.approx(p.value) for n, p in before.items()}
    assert [c.name for c in result.changes] == list(values)
    assert client.read("MC_ROLL_P").value == pytest.approx(6.0, rel=1e-6)
    assert client.read("MC_ROLLRATE_I").value == 0.0
    restored = client.restore(result.backup_path)
    assert {c.name for c in restored.changes} == set(values)
    for name, p in before.items():
        assert client.read(name).value == pytest.approx(p.value)


def test_value_that_will_not_stick_is_rolled_back(client, tmp_path):
    old = client.read("MC_ROLL_P").value
    # the SITL refuses out-of-range values, as PX4 does for its bounded parameters
    with pytest.raises(ParameterError, match="MPC_THR_HOVER did not stick.*rolled back"):
        client.write({"MC_ROLL_P": old + 1.0, "MPC_THR_HOVER": 0.99}, tmp_path)
    assert client.read("MC_ROLL_P").value == pytest.approx(old)


def test_unknown_name_fails_before_any_write(client, tmp_path):
    old = client.read("MC_PITCH_P").value
    with pytest.raises(ParameterError, match="no parameter NO_SUCH_PARAM"):
        client.write({"MC_PITCH_P": old + 1.0, "NO_SUCH_PARAM": 1.0}, tmp_path)
    assert client.read("MC_PITCH_P").value == pytest.approx(old)
    assert not list(tmp_path.glob("*.params"))  # nothing to back up: nothing was written


def test_cli_restore(sitl_port, tmp_path, capsys):
    conn = f"udp:127.0.0.1:{sitl_port}"
    backup = tmp_path / "mine.params"
    write_params_file(backup, [Param("MC_YAW_P", 2.5)])
    assert main(["params", "restore", str(backup), "-c", conn, "--yes"]) == 0
    assert main(["params", "show", "MC_YAW_P", "-c", conn]) == 0
    assert "2.5" in capsys.readouterr().out
    assert list(tmp_path.glob("params-before-restore-*.params"))
