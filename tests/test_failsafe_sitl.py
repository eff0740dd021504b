"""The link-loss guard on the real ArduCopter (its SITL build, 4.7.0-dev), over TCP.

Runs when the build of ``../shared/external/ardupilot-sitl/build.sh`` is present and skips,
saying why, when it is not (see test_ardupilot_sitl.py). One SITL boot with Lua scripting on
(SCR_ENABLE 1, a defaults file passed to start.sh) is shared by the module; the tool flies on
SERIAL0 and an observer watches on SERIAL1 under MAVLink system id 254, which is not the
vehicle's ground-station id, so its own heartbeats cannot keep the guard quiet.
``ARDUPILOT_SITL_INSTANCE=N`` picks the instance (default: the first free one from 31).
"""

from __future__ import annotations

import os
import re
import time

import pytest

from mrft_gcs.errors import LinkError
from mrft_gcs.link import VehicleLink
from mrft_gcs.link.failsafe import (
    GUARD_FILE,
    GuardFailed,
    GuardRefused,
    install_link_loss_guard,
    rate_path_guard,
    remove_link_loss_guard,
)
from mrft_gcs.link.ftp import list_dir
from mrft_gcs.link.modes import ARDUPILOT_COPTER_MODES
from mrft_gcs.params import ParamClient
from mrft_gcs.sitl.arducopter import ArduCopterSitl, fly_level, free_instance, why_not
from mrft_gcs.telemetry import Heartbeat, StatusText

pytestmark = pytest.mark.skipif(why_not() is not None, reason=str(why_not()))

OBSERVER_SYSID = 254
GUIDED_NOGPS = ARDUPILOT_COPTER_MODES["offboard"]
LAND = ARDUPILOT_COPTER_MODES["land"]


@pytest.fixture(scope="module")
def copter(tmp_path_factory):
    """``(serial0, serial1)`` of a booted ArduCopter SITL with Lua scripting running."""
    instance = int(os.environ.get("ARDUPILOT_SITL_INSTANCE", "0")) or free_instance()
    try:
        sitl = ArduCopterSitl.start(instance, tmp_path_factory.mktemp("arducopter-lua"),
                                    {"SCR_ENABLE": 1}, require_ready=True)
    except LinkError as err:
        pytest.fail(str(err))
    with sitl:
        yield sitl.serial0, sitl.serial1


def _guard_files(link: VehicleLink) -> list[str]:
    return [e.name for e in list_dir(link, "scripts") or () if e.name == GUARD_FILE]


def test_refused_with_what_to_set_when_scripting_is_off(copter, tmp_path):
    """SCR_ENABLE 0 is read before anything is uploaded; the message says what to set and that
    a reboot is needed. (Set on the running SITL: the tool reads the parameter, as it would on
    a vehicle that booted with it.)"""
    serial0, _ = copter
    with VehicleLink.connect(serial0, timeout_s=10) as link:
        client = ParamClient(link)
        backup = client.write({"SCR_ENABLE": 0}, tmp_path).backup_path
        try:
            with pytest.raises(GuardRefused) as info:
                install_link_loss_guard(link, {"ATC_RAT_RLL_P": 0.135}, 1.0)
            msg = str(info.value)
            print(msg)
            assert "SCR_ENABLE 1" in msg and "reboot" in msg and "\n" not in msg
            assert info.value.exit_code == 2
            assert link.counters.sent.get("FILE_TRANSFER_PROTOCOL", 0) == 0  # nothing sent
            assert _guard_files(link) == []
        finally:
            client.restore(backup, tmp_path)
        assert client.read("SCR_ENABLE").value == 1


def test_a_parameter_the_firmware_lacks_fails_the_install_and_leaves_nothing(copter):
    serial0, _ = copter
    with VehicleLink.connect(serial0, timeout_s=10) as link:
        with pytest.raises(GuardFailed, match="no param NO_SUCH_PARAM"):
            install_link_loss_guard(link, {"ATC_RAT_RLL_P": 0.135, "NO_SUCH_PARAM": 1.0}, 1.0)
        assert _guard_files(link) == []
        assert link.heartbeat_period_s == 1.0


def test_silent_ground_station_restores_the_gains_and_lands(copter, tmp_path):
    """Guard installed, take-off in GUIDED_NOGPS, ATC_RAT_RLL_P zeroed in flight, then the
    tool's link closes. Seen from the observer: the guard reports within the silence time plus
    a margin, the vehicle is in LAND, the gain is back, it lands and disarms."""
    serial0, serial1 = copter
    silence_s = 0.5  # the default: what the zero-gain window needs
    with VehicleLink.connect(serial1, timeout_s=10, source_system=OBSERVER_SYSID) as obs:
        obs_params = ParamClient(obs)
        rll_p = obs_params.read("ATC_RAT_RLL_P").value
        assert rll_p > 0
        with obs.subscribe(StatusText, Heartbeat) as events:
            link = VehicleLink.connect(serial0, timeout_s=10)
            try:
                t = time.monotonic()
                guard = install_link_loss_guard(link, {"ATC_RAT_RLL_P": rll_p}, silence_s)
                print(f"guard {guard.guard_id} installed at {guard.path} in "
                      f"{time.monotonic() - t:.1f} s")
                assert link.heartbeat_period_s == pytest.approx(silence_s / 4)
                assert _guard_files(link) == []  # runs from memory: nothing stale on the card
                link.request_message_interval("LOCAL_POSITION_NED", 50.0)
                link.set_mode(GUIDED_NOGPS)
                link.arm()
                alt = fly_level(link, 30.0, until_m=1.5)  # 2 s arming delay, then ~1 s climb
                assert alt > 1.5, f"did not take off ({alt:.2f} m, armed {link.heartbeat.armed})"
                ParamClient(link).write({"ATC_RAT_RLL_P": 0.0}, tmp_path)
                alt = fly_level(link, 2.0)  # still guarded, still flying: the guard must stay quiet
                assert obs.heartbeat.custom_mode == GUIDED_NOGPS.main and obs.heartbeat.armed
                assert obs_params.read("ATC_RAT_RLL_P").value == 0.0
            finally:
                link.close()  # the ground station falls silent: no heartbeat, no setpoint
            t_silent = time.monotonic()
            print(f"link closed at {alt:.2f} m")
            report = events.wait_for(lambda e: isinstance(e, StatusText)
                                     and e.text.startswith(f"mrftguard {guard.guard_id} silent "),
                                     silence_s + 5.0)
            assert report is not None, "the guard said nothing"
            t_report = time.monotonic() - t_silent
            print(f"after {t_report:.2f} s: {report.text!r}")
            silent_ms = int(report.text.split()[3].removesuffix("ms"))
            assert silence_s * 1000 < silent_ms <= silence_s * 1000 + 500, report.text
            assert report.text.endswith("1/1 back LAND"), report.text
            # wall clock: the last beat (0.25 s before closing) and a SITL slowed by a loaded host
            assert t_report <= silence_s + 2.0, t_report
            landing = events.wait_for(lambda e: isinstance(e, Heartbeat)
                                      and e.custom_mode == LAND.main, 3.0)
            assert landing is not None, f"mode {obs.heartbeat.custom_mode}, not LAND"
        assert obs_params.read("ATC_RAT_RLL_P").value == pytest.approx(rll_p)
        end = time.monotonic() + 40
        while time.monotonic() < end and obs.heartbeat.armed:  # LAND disarms on touch-down
            time.sleep(0.2)
        assert not obs.heartbeat.armed, "still armed 40 s after the guard's LAND"
    with VehicleLink.connect(serial0, timeout_s=10) as link:
        remove_link_loss_guard(link, guard)
        assert _guard_files(link) == [] and link.heartbeat_period_s == 1.0
        assert ParamClient(link).read("ATC_RAT_RLL_P").value == pytest.approx(rll_p)


def test_the_rate_path_hook_guards_after_arming_and_ends_at_the_hand_over(copter, tmp_path):
    """As the rate path does: armed on the ground, a test parameter written (backed up), the
    hook installs the guard for that backup. Take-off, a new gain written, hand-over to
    LOITER: the guard says it is off, and a silence in a later GUIDED_NOGPS stretch neither
    reverts the gain nor lands (the observer lands it)."""
    serial0, serial1 = copter
    with VehicleLink.connect(serial1, timeout_s=10, source_system=OBSERVER_SYSID) as obs:
        obs_params = ParamClient(obs)
        rll_p = obs_params.read("ATC_RAT_RLL_P").value
        tuned = round(rll_p * 1.1, 4)
        with obs.subscribe(StatusText) as texts:
            link = VehicleLink.connect(serial0, timeout_s=10)
            try:
                link.request_message_interval("LOCAL_POSITION_NED", 50.0)
                link.set_mode(GUIDED_NOGPS)
                link.arm()
                client = ParamClient(link)
                backup = client.write({"ATC_RAT_RLL_P": round(rll_p * 0.9, 4)}, tmp_path)
                note = rate_path_guard(link, client, backup.backup_path)
                print(note)
                found = re.search(r"mrftguard ([0-9a-f]{6}) on the vehicle", note)
                assert found is not None, note
                tag = f"mrftguard {found.group(1)}"
                assert link.heartbeat.armed and _guard_files(link) == []
                alt = fly_level(link, 30.0, until_m=1.5)
                assert alt > 1.5, f"did not take off ({alt:.2f} m, armed {link.heartbeat.armed})"
                client.write({"ATC_RAT_RLL_P": tuned}, tmp_path)
                link.set_mode(ARDUPILOT_COPTER_MODES["position"])  # LOITER: the hand-over
                off = texts.wait_for(lambda e: e.text == f"{tag} off", 3.0)
                assert off is not None, "the guard did not end itself on the hand-over"
                link.set_mode(GUIDED_NOGPS)  # a later offboard stretch, no longer guarded
                fly_level(link, 1.0)
            finally:
                link.close()
            fired = texts.wait_for(lambda e: e.text.startswith(f"{tag} "), 0.5 + 2.0)
            assert fired is None, fired
        assert obs.heartbeat.custom_mode == GUIDED_NOGPS.main and obs.heartbeat.armed
        assert obs_params.read("ATC_RAT_RLL_P").value == pytest.approx(tuned)
        obs.set_mode(LAND)
        end = time.monotonic() + 40
        while time.monotonic() < end and obs.heartbeat.armed:
            time.sleep(0.2)
        assert not obs.heartbeat.armed
        ParamClient(obs).write({"ATC_RAT_RLL_P": rll_p}, tmp_path)


def test_the_rate_path_hook_says_why_link_loss_stays_unprotected(copter, tmp_path):
    serial0, _ = copter
    with VehicleLink.connect(serial0, timeout_s=10) as link:
        client = ParamClient(link)
        backup = client.write({"SCR_ENABLE": 0}, tmp_path).backup_path
        try:
            note = rate_path_guard(link, client, backup)
        finally:
            client.restore(backup, tmp_path)
        assert note.startswith("rate path: link loss in the zero-gain window is unprotected")
        assert "SCR_ENABLE 1" in note and "reboot" in note
