"""Link-loss protection on the vehicle: an ArduPilot Lua guard the tool uploads for one tune.

While the tool flies a stock ArduCopter through its rate feed-forward path, the onboard gains
are zero: if the ground station falls silent nothing holds the attitude, and the last body
rate commanded keeps being fed forward (GUID_TIMEOUT, 3 s) as a constant torque. ArduPilot's
own GCS failsafe (FS_GCS_ENABLE) would land on the zeroed gains, seconds later. The guard is
a Lua script (``linkloss_guard.lua``, package data) generated with the backed-up parameter
values written into its text: while armed in the offboard mode (GUIDED_NOGPS) it watches
``gcs:last_seen()`` (the last heartbeat from MAV_GCS_SYSID) and, after ``silence_s`` without
one, writes the values back (saved) and switches to LAND, with a STATUSTEXT saying so. Once
the vehicle, armed in that mode, leaves it (the hand-over, a landing, a pilot) or disarms, the
guard ends itself: restoring later would undo the gains the tune wrote.
docs/link-and-stream.md has what it was measured to save.

Why the values live in the script text: SCR_USER1..6 hold six floats and no names; the text
holds any number of name/value pairs, needs no parameter writes to arm, and the script refuses
to start (so the install fails) if a name is unknown to the firmware.

Once the guard reports running the tool deletes its file: it runs from memory until scripting
restarts or the vehicle reboots, so a tool that dies mid-tune leaves nothing on the card to
fire in a later flight.

Call order in a tune (the lead wires it into :mod:`mrft_gcs.flight.api`)::

    backup = ...read the parameters the test will change...        # before any write
    guard = install_link_loss_guard(link, backup, silence_s=0.5)   # disarmed, before arming
    try:
        ...write test params, arm, take off, relay tests, write gains...
    finally:
        ...restore test params...
        remove_link_loss_guard(link, guard)                          # after landing / hand-over

Install only on ArduPilot with SCR_ENABLE 1 (a reboot is needed after setting it: the tool
never reboots a vehicle). Detection is heartbeat-based: the link's heartbeat goes to
``4 / silence_s`` Hz while the guard is installed. The guard watches the link, not the
setpoint stream: a tool whose streamer stopped but whose link lives is not caught. Another
ground station with the same MAVLink system id (QGroundControl and Mission Planner also use
255) keeps the guard from seeing the tool fall silent.
"""

from __future__ import annotations

import hashlib
import math
import re
import time
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from string import Template

from mrft_gcs.errors import LinkError, ParameterError, UsageError
from mrft_gcs.link.ftp import list_dir, put_file, remove_file
from mrft_gcs.link.modes import ARDUPILOT_COPTER_MODES
from mrft_gcs.link.vehicle import VehicleLink
from mrft_gcs.params import ParamClient, read_params_file
from mrft_gcs.telemetry import AutopilotFamily, StatusText

__all__ = ["GuardRefused", "GuardFailed", "LinkLossGuard", "guard_script",
           "install_link_loss_guard", "remove_link_loss_guard", "rate_path_guard",
           "GUARD_FILE", "DEFAULT_SILENCE_S"]

GUARD_FILE = "mrft_linkloss_guard.lua"
#: where ArduPilot loads scripts from: flight controllers (SD card), then SITL and Linux
#: boards (relative to the working directory)
SCRIPT_DIRS = ("/APM/scripts", "scripts")
MAV_CMD_SCRIPTING = 42701
SCRIPTING_CMD_STOP_AND_RESTART = 3
ARDUCOPTER_GUIDED_NOGPS = ARDUPILOT_COPTER_MODES["offboard"].main
ARDUCOPTER_LAND = ARDUPILOT_COPTER_MODES["land"].main
#: the guard's own check period (ms): a fraction of the shortest silence it accepts
GUARD_PERIOD_MS = 50
MIN_SILENCE_S, MAX_SILENCE_S = 0.3, 30.0
#: the zero-gain window's default (docs/link-and-stream.md has what 1.0, 0.5 and 0.3 s saved)
DEFAULT_SILENCE_S = 0.5
#: keeps the guard's report within one 50-character STATUSTEXT
MAX_PARAMS = 99
_NAME = re.compile(r"^[A-Z][A-Z0-9_]{0,15}$")


class GuardRefused(UsageError):
    """The vehicle cannot run the guard as it is configured (exit 2): the message says what
    to set."""


class GuardFailed(LinkError):
    """Upload, scripting restart or the guard's start report failed (exit 3)."""


@dataclass(frozen=True, slots=True)
class LinkLossGuard:
    """An installed guard: where it lives and what it restores.

    Attributes
    ----------
    path : str
        Where the script was uploaded (MAVLink FTP); deleted once it runs from memory.
    guard_id : str
        6 hex digits of the script's hash; its STATUSTEXTs start ``mrftguard <id>``.
    silence_s : float
        Seconds without a GCS heartbeat before it restores and lands.
    names : tuple of str
        Parameters it writes back.
    heartbeat_period_s : float
        The link's heartbeat period before the install (put back on removal), s.
    """

    path: str
    guard_id: str
    silence_s: float
    names: tuple[str, ...]
    heartbeat_period_s: float


def guard_script(restore: dict[str, float], silence_s: float, *,
                 offboard_mode: int = ARDUCOPTER_GUIDED_NOGPS,
                 land_mode: int = ARDUCOPTER_LAND) -> tuple[str, str]:
    """The guard's Lua text for ``restore`` (parameter name -> value) and its id.

    Parameters
    ----------
    restore : dict of str to float
        Values written back on link loss (the tool's backup of what the test changes).
    silence_s : float
        Seconds without a ground-station heartbeat before it acts, 0.3 to 30.
    offboard_mode, land_mode : int
        ArduCopter mode numbers: the one it guards, the one it switches to.

    Returns
    -------
    (str, str)
        The script and its 6-hex-digit id.

    Raises
    ------
    UsageError
        No parameters, a malformed name, a non-finite value, or a silence out of range.
    """
    if not restore:
        raise UsageError("the link-loss guard needs the backed-up parameters to restore")
    if len(restore) > MAX_PARAMS:
        raise UsageError(f"the link-loss guard restores at most {MAX_PARAMS} parameters, "
                         f"not {len(restore)}: restore only what the test changes")
    if not MIN_SILENCE_S <= silence_s <= MAX_SILENCE_S or not math.isfinite(silence_s):
        raise UsageError(f"link-loss silence {silence_s} s: use {MIN_SILENCE_S:g} to "
                         f"{MAX_SILENCE_S:g} s")
    for name, value in restore.items():
        if not _NAME.match(name):
            raise UsageError(f"{name!r} is not an ArduPilot parameter name (A-Z, 0-9, _, "
                             f"at most 16 characters)")
        if not math.isfinite(value):
            raise UsageError(f"cannot restore {name} to {value}: back up a finite value")
    rows = "\n".join(f"  {{'{n}', {float(v)!r}}}," for n, v in sorted(restore.items()))
    template = Template(resources.files(__package__).joinpath("linkloss_guard.lua")
                        .read_text(encoding="utf-8"))
    fields = dict(silence_ms=int(round(silence_s * 1000)), offboard_mode=int(offboard_mode),
                  land_mode=int(land_mode), period_ms=GUARD_PERIOD_MS, restore_rows=rows)
    guard_id = hashlib.sha256(template.substitute(fields, guard_id="").encode()).hexdigest()[:6]
    return template.substitute(fields, guard_id=guard_id), guard_id


def install_link_loss_guard(link: VehicleLink, restore: dict[str, float],
                            silence_s: float = DEFAULT_SILENCE_S, *,
                            confirm_timeout_s: float = 10.0,
                            allow_armed: bool = False) -> LinkLossGuard:
    """Upload the guard for ``restore``, restart scripting, wait until it reports running.

    Call it disarmed, before arming, once the parameters the test changes are backed up
    (``restore`` = those backed-up values), and remove it with :func:`remove_link_loss_guard`
    when the tune has ended (also on abort). It raises the link's heartbeat rate to
    ``4 / silence_s`` Hz (at least 1 Hz) until removed.

    Parameters
    ----------
    link : VehicleLink
        Open link to an ArduCopter.
    restore : dict of str to float
        Parameter name -> value to write back on link loss.
    silence_s : float
        Seconds without a ground-station heartbeat before the guard acts (0.3 to 30). During
        the zero-gain window every 0.1 s counts (the last rate command keeps turning the
        vehicle); a stall of the tool's reader thread this long lands the vehicle.
    confirm_timeout_s : float
        How long to wait for the guard's start report after restarting scripting, s.
    allow_armed : bool
        Install on an armed vehicle too: only on the ground (restarting scripting stops the
        vehicle's other scripts for a moment), e.g. right after arming as the rate path does.

    Raises
    ------
    GuardRefused
        Not ArduPilot, armed, scripting off (SCR_ENABLE 0, or not compiled in), the scripts
        directory disabled, or the tool's MAVLink id is not the vehicle's ground-station id.
    GuardFailed
        Scripting not running (set but not rebooted), upload failed, or no start report.
    """
    script, guard_id = guard_script(restore, silence_s, offboard_mode=link.modes["offboard"].main,
                                    land_mode=link.modes["land"].main)
    _check_vehicle(link, allow_armed)
    folder = _scripts_dir(link)
    path = f"{folder}/{GUARD_FILE}"
    try:
        put_file(link, path, script.encode())
    except LinkError as err:
        raise GuardFailed(f"cannot upload the link-loss guard to {path}: {err}") from err
    period = link.heartbeat_period_s
    link.heartbeat_period_s = min(period, silence_s / 4)
    guard = LinkLossGuard(path, guard_id, float(silence_s), tuple(sorted(restore)), period)
    try:
        _confirm(link, guard, confirm_timeout_s)
        _delete(link, path)  # running from memory now: nothing stale survives a reboot
    except LinkError:
        _undo(link, guard)
        raise
    return guard


def rate_path_guard(link: VehicleLink, client: ParamClient, backup: Path) -> str:
    """The rate path's link-loss hook (``mrft_gcs.flight.ratepath.LINK_LOSS_GUARD``): install
    the guard for the test parameters' backup, right after they were written on the ground.

    Returns the report's note: the guard's id and what it does, or why link loss stays
    unprotected (scripting off, no card ...: the tune goes on, as on a firmware without Lua).
    The guard ends itself at the hand-over out of GUIDED_NOGPS; :func:`remove_link_loss_guard`
    is not needed (a vehicle reboot or scripting restart also ends it).
    """
    restore = {e.param.name: e.param.value for e in read_params_file(backup)}
    try:
        guard = install_link_loss_guard(link, restore, DEFAULT_SILENCE_S, allow_armed=True)
    except (GuardRefused, GuardFailed) as err:
        return f"rate path: link loss in the zero-gain window is unprotected onboard: {err}"
    return (f"rate path: link-loss guard mrftguard {guard.guard_id} on the vehicle: after "
            f"{guard.silence_s:g} s without a ground-station heartbeat it restores the "
            f"{len(restore)} backed-up parameters and lands; it ends at the hand-over")


def _confirm(link: VehicleLink, guard: LinkLossGuard, timeout_s: float) -> None:
    """Restart scripting and wait for the guard's own start report."""
    tag = f"mrftguard {guard.guard_id}"
    lua_errors: list[str] = []
    with link.subscribe(StatusText) as sub:
        _restart_scripting(link)
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            text = sub.get(left)
            if not isinstance(text, StatusText):
                continue
            if text.text.startswith(f"{tag} on "):
                return
            if text.text.startswith(tag):
                raise GuardFailed(f"the link-loss guard refused to start ('{text.text}': a "
                                  f"backed-up parameter this firmware lacks); it was removed")
            if text.text.startswith("Lua:"):
                lua_errors.append(text.text)
    said = f" (vehicle said: {'; '.join(lua_errors)})" if lua_errors else ""
    raise GuardFailed(f"the link-loss guard did not report running within {timeout_s:g} s of "
                      f"restarting scripting{said}: check the vehicle's messages (e.g. "
                      f"SCR_HEAP_SIZE too small); it was removed")


def remove_link_loss_guard(link: VehicleLink, guard: LinkLossGuard) -> None:
    """Stop the guard (restart scripting: it runs from memory, its file is already deleted)
    and put the link's heartbeat rate back. Call it after the tune, also on abort; a reboot
    of the vehicle stops the guard too.

    Raises
    ------
    GuardFailed
        Scripting did not report its restart (the guard may still run until the vehicle
        reboots: it acts only armed in GUIDED_NOGPS with the ground station silent).
    """
    link.heartbeat_period_s = guard.heartbeat_period_s
    _delete(link, guard.path)  # only there if an install was cut short
    _restart_scripting(link, confirm_s=5.0)


def _delete(link: VehicleLink, path: str) -> None:
    folder, _, name = path.rpartition("/")
    left = list_dir(link, folder)
    if left is not None and not any(e.name == name for e in left):
        return
    remove_file(link, path)
    left = list_dir(link, folder)
    if left is None or any(e.name == name for e in left):
        raise GuardFailed(f"could not delete the link-loss guard {path} from the vehicle: "
                          f"delete it with a ground station's MAVLink FTP before flying "
                          f"GUIDED_NOGPS again")


def _undo(link: VehicleLink, guard: LinkLossGuard) -> None:
    link.heartbeat_period_s = guard.heartbeat_period_s
    try:
        remove_file(link, guard.path)
        _restart_scripting(link)
    except LinkError:
        pass  # the failure being reported matters more


def _restart_scripting(link: VehicleLink, confirm_s: float = 0.0) -> None:
    """MAV_CMD_SCRIPTING stop-and-restart; with ``confirm_s``, wait for ArduPilot's
    "Scripting: restarted"."""
    with link.subscribe(StatusText) as sub:
        try:
            link.command(MAV_CMD_SCRIPTING, (SCRIPTING_CMD_STOP_AND_RESTART,), timeout_s=2.0)
        except LinkError as err:
            raise GuardFailed(f"cannot restart the vehicle's Lua scripting: {err}") from err
        if confirm_s > 0 and sub.wait_for(lambda t: t.text == "Scripting: restarted",
                                          confirm_s) is None:
            raise GuardFailed(f"the vehicle did not report restarting Lua scripting within "
                              f"{confirm_s:g} s: the link-loss guard may run until it reboots")


def _param(client: ParamClient, *names: str) -> float | None:
    """The first of ``names`` the vehicle has (firmware versions rename), or None."""
    for name in names:
        try:
            return client.read(name).value
        except ParameterError:
            continue
    return None


def _check_vehicle(link: VehicleLink, allow_armed: bool) -> None:
    if link.family is not AutopilotFamily.ARDUPILOT:
        raise GuardRefused("the link-loss guard is an ArduPilot Lua script: this vehicle is "
                           "not ArduPilot")
    if link.heartbeat.armed and not allow_armed:
        raise GuardRefused("install the link-loss guard while disarmed (restarting scripting "
                           "in flight would stop every script): land and disarm first")
    client = ParamClient(link)
    enable = _param(client, "SCR_ENABLE")
    if enable is None:
        raise GuardRefused("this firmware has no Lua scripting (no SCR_ENABLE): link loss "
                           "cannot be guarded on the vehicle; use a firmware built with "
                           "scripting")
    if int(enable) != 1:
        raise GuardRefused(f"Lua scripting is off (SCR_ENABLE {int(enable)}): set SCR_ENABLE 1 "
                           f"and reboot the vehicle (needed for it to take effect), then run "
                           f"again")
    dir_disable = _param(client, "SCR_DIR_DISABLE")
    if dir_disable is not None and int(dir_disable) & 2:
        raise GuardRefused(f"scripts on the card are disabled (SCR_DIR_DISABLE "
                           f"{int(dir_disable)}): clear bit 1 (value 2) and reboot the vehicle, "
                           f"then run again")
    gcs_id = _param(client, "MAV_GCS_SYSID", "SYSID_MYGCS")
    gcs_hi = _param(client, "MAV_GCS_SYSID_HI")
    me = link.source_ids[0]
    if gcs_id is not None:
        lo = int(gcs_id)
        hi = int(gcs_hi) if gcs_hi is not None and int(gcs_hi) >= lo else lo
        if not lo <= me <= hi:
            raise GuardRefused(f"the tool's MAVLink system id {me} is not the vehicle's "
                               f"ground-station id (MAV_GCS_SYSID {lo}): the guard could not "
                               f"hear it; set MAV_GCS_SYSID {me}")


def _scripts_dir(link: VehicleLink) -> str:
    for folder in SCRIPT_DIRS:
        if list_dir(link, folder) is not None:
            return folder
    raise GuardFailed("the vehicle has no scripts directory (" + " or ".join(SCRIPT_DIRS)
                      + "): scripting is not running; if SCR_ENABLE was just set to 1, reboot "
                        "the vehicle, then run again")
