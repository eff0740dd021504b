"""Flight modes as (main, sub) custom-mode numbers, per autopilot family.

PX4 packs its custom mode as ``main << 16 | sub << 24`` in HEARTBEAT.custom_mode
and takes ``(main, sub)`` as params 2 and 3 of MAV_CMD_DO_SET_MODE; ArduPilot uses
the mode number itself in both places. Profiles name the numbers to use
(``profiles/*.toml``, ``[modes]``); the constants here are the defaults.
"""

from __future__ import annotations

from dataclasses import dataclass

from mrft_gcs.telemetry import AutopilotFamily

__all__ = ["CustomMode", "PX4_MODES", "ARDUPILOT_COPTER_MODES", "encode_custom_mode",
           "mode_matches"]


@dataclass(frozen=True)
class CustomMode:
    """A custom flight mode: ``main`` number and, for PX4, ``sub`` number."""

    name: str
    main: int
    sub: int = 0


PX4_MODES = {
    "offboard": CustomMode("OFFBOARD", 6),
    "position": CustomMode("POSCTL", 3),
    "land": CustomMode("AUTO.LAND", 4, 6),
}
ARDUPILOT_COPTER_MODES = {
    "offboard": CustomMode("GUIDED_NOGPS", 20),
    "position": CustomMode("LOITER", 5),
    "land": CustomMode("LAND", 9),
}


def encode_custom_mode(family: AutopilotFamily, mode: CustomMode) -> int:
    """HEARTBEAT.custom_mode value a vehicle reports once it is in ``mode``.

    >>> encode_custom_mode(AutopilotFamily.PX4, PX4_MODES["land"])
    100925440
    >>> encode_custom_mode(AutopilotFamily.ARDUPILOT, ARDUPILOT_COPTER_MODES["land"])
    9
    """
    if family is AutopilotFamily.ARDUPILOT:
        return mode.main
    return (mode.main << 16) | (mode.sub << 24)


def mode_matches(family: AutopilotFamily, mode: CustomMode, custom_mode: int) -> bool:
    """True if HEARTBEAT.custom_mode shows ``mode`` (PX4: main and, if given, sub)."""
    if family is AutopilotFamily.ARDUPILOT:
        return custom_mode == mode.main
    main = (custom_mode >> 16) & 0xFF
    sub = (custom_mode >> 24) & 0xFF
    return main == mode.main and (mode.sub == 0 or sub == mode.sub)
