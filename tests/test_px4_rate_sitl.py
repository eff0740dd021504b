"""PX4's rate loop as a torque channel, on the real PX4 SITL (SIH quad-x).

The profile's ``[rate_path]`` test parameters go in through the tool's own parameter client
(backup, read-back), the vehicle takes off and hovers with all attitude control on a
ground-station PD sent as body rates (benchmarks/probe_px4_rate.py), PX4's own log shows every
torque equal to ``FF x`` the rate set point, and the backup puts every value back.
Skips without a PX4 SITL build (docs/px4-sitl.md). Timing-sensitive: run it alone
(``flock /tmp/team/live.lock``) on a loaded host.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import pytest

from mrft_gcs.errors import UsageError
from mrft_gcs.flight.api import tune
from mrft_gcs.link.vehicle import VehicleLink
from mrft_gcs.params import ParamClient
from mrft_gcs.profiles import load_profile
from mrft_gcs.sitl.px4sitl import Px4Sitl, free_instance, why_not

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"
pytestmark = pytest.mark.skipif(why_not() is not None, reason=str(why_not()))


@pytest.fixture(scope="module")
def px4():
    with Px4Sitl.start(free_instance(), Path(tempfile.mkdtemp(prefix="px4rate_t_"))) as sitl:
        yield sitl


def test_profile_rate_path_flies_px4_on_the_feed_forward_and_restores(px4, tmp_path):
    sys.path.insert(0, str(BENCH))
    import probe_px4_rate as probe

    rp = load_profile("px4").rate_path
    assert rp is not None
    names = list(rp.test_params)
    with VehicleLink.connect(px4.offboard, timeout_s=20) as link:
        client = ParamClient(link)
        stock = {n: p.value for n, p in client.read_many(names).items()}
        written = client.write(rp.test_params, tmp_path, label="rate-test")
        back = {n: p.value for n, p in client.read_many(names).items()}
    assert back == pytest.approx(dict(rp.test_params))
    # the stock cascade is not already the test one: the write changed the rate loop
    assert stock["MC_ROLLRATE_P"] > 0 and stock["MC_ROLLRATE_FF"] != rp.k[0]

    try:
        res = probe.probe_flight(px4, {}, rp.k, alt=2.0, hover_s=5.0, loss_s=0.0)
        print(res)
        assert res["arm_ack"] == 0 and res["offboard_ack"] == 0
        hover = res["hover"]
        assert hover["armed_all"] and hover["mode_main"] == [probe.OFFBOARD_MAIN]
        assert hover["max_abs_roll_deg"] < 3 and hover["max_abs_pitch_deg"] < 3
        assert 1.5 < hover["alt_mean_m"] < 2.5
        assert res["landed_on_gcs_loop"]
        log = res["ulog"]
        assert "error" not in log, log
        # PX4's attitude controller is off in body-rate OFFBOARD: the rate set points are ours
        assert log["attitude_ctrl_in_offboard"] == [0]
        # PX4's torque is FF x a rate set point we sent (bitwise, all three axes), mostly one
        # 4 ms SITL step later; the rest falls where the log has gaps in the set points
        match = log["torque_equals_ff_setpoint"]
        assert match["offboard_torque_samples"] > 500
        assert match["equal_share"] > 0.85, match
        assert max(match["lag_ms_counts"]) <= 12 and max(match["lag_ms_counts"].values()) > (
            0.5 * match["offboard_torque_samples"])
        assert log["rate_integrator_max_abs"] == 0.0
    finally:
        # every value back from the backup, also when the flight checks failed
        with VehicleLink.connect(px4.offboard, timeout_s=20) as link:
            client = ParamClient(link)
            client.restore(written.backup_path, tmp_path)
            again = {n: p.value for n, p in client.read_many(names).items()}

    assert again == pytest.approx(stock)


def test_rate_actuation_on_px4_is_refused_before_anything_is_written(px4, tmp_path):
    """`--actuation rate` on the real PX4 stops at the firmware check with the reason, before
    a backup or a write (no .params file), the vehicle still disarmed."""
    with pytest.raises(UsageError, match="not built for PX4"):
        tune(px4.offboard, "px4", actuation="rate", backup_dir=tmp_path,
             heartbeat_timeout_s=20)
    assert not list(tmp_path.glob("*.params"))
    with VehicleLink.connect(px4.offboard, timeout_s=20) as link:
        stock = ParamClient(link).read("MC_ROLLRATE_P").value
    assert stock == pytest.approx(0.15)
