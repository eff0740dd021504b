"""Which autopilot firmware is on the other end, and what it can carry.

After connecting, the ground station asks for AUTOPILOT_VERSION (MAV_CMD_REQUEST_MESSAGE,
else MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES) and reads the HEARTBEAT's autopilot and
vehicle type. ``flight_sw_version`` packs major, minor, patch and a FIRMWARE_VERSION_TYPE
(dev, alpha, beta, rc, official) in its four bytes, high to low, on PX4 and ArduPilot
alike. A peer that does not answer still has a family (from its heartbeat); the
parameter set then tells the naming (:func:`mrft_gcs.profiles.fit_profile`).

What the firmware cannot carry is refused here, before arming: torque setpoints
(SET_ACTUATOR_CONTROL_TARGET) have no handler in ArduPilot and were removed from
PX4's MAVLink offboard in v1.14.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from mrft_gcs.link.connection import autopilot_family
from mrft_gcs.link.vehicle import AutopilotVersion, VehicleLink
from mrft_gcs.telemetry import AutopilotFamily, Heartbeat

__all__ = ["Firmware", "decode_sw_version", "firmware_from", "detect_firmware",
           "torque_path_refusal", "VERSION_TYPES"]

#: FIRMWARE_VERSION_TYPE (common.xml) -> the suffix firmware prints after its version
VERSION_TYPES = {0: "dev", 64: "alpha", 128: "beta", 192: "rc", 255: "official"}
#: MAV_TYPE values ArduPilot's Copter firmware announces (quad, coaxial, heli, hexa, octo,
#: tri, dodeca, deca)
_COPTER_TYPES = frozenset({2, 3, 4, 13, 14, 15, 29, 35})
_PLANE_TYPES = frozenset({1})


def decode_sw_version(value: int) -> tuple[int, int, int, str]:
    """``flight_sw_version`` as (major, minor, patch, type).

    >>> decode_sw_version((4 << 24) | (7 << 16) | (0 << 8) | 0)
    (4, 7, 0, 'dev')
    >>> decode_sw_version(0x010D00FF)
    (1, 13, 0, 'official')
    """
    v = int(value) & 0xFFFF_FFFF
    kind = v & 0xFF
    # types between the named ones (PX4 counts rc1, rc2... as 193, 194) keep the lower name
    name = VERSION_TYPES.get(kind) or VERSION_TYPES[max(k for k in VERSION_TYPES if k <= kind)]
    return (v >> 24) & 0xFF, (v >> 16) & 0xFF, (v >> 8) & 0xFF, name


@dataclass(frozen=True)
class Firmware:
    """The autopilot firmware as it reported itself.

    ``version`` is None when the peer did not answer AUTOPILOT_VERSION (or reported 0);
    ``source`` says where the figures came from.
    """

    family: AutopilotFamily
    vehicle_type: int  # HEARTBEAT.type (MAV_TYPE)
    version: tuple[int, int, int] | None = None
    version_type: str = ""
    capabilities: int | None = None
    source: str = "HEARTBEAT"

    @property
    def product(self) -> str:
        """``ArduCopter``, ``ArduPlane``, ``ArduPilot``, ``PX4`` or the family name."""
        if self.family is AutopilotFamily.ARDUPILOT:
            if self.vehicle_type in _COPTER_TYPES:
                return "ArduCopter"
            return "ArduPlane" if self.vehicle_type in _PLANE_TYPES else "ArduPilot"
        return "PX4" if self.family is AutopilotFamily.PX4 else self.family.value

    @property
    def name(self) -> str:
        """As people write it: ``ArduCopter 4.7.0-dev``, ``PX4 1.13.0``.

        >>> Firmware(AutopilotFamily.ARDUPILOT, 2, (4, 7, 0), "dev").name
        'ArduCopter 4.7.0-dev'
        >>> Firmware(AutopilotFamily.PX4, 2).name
        'PX4 (version not reported)'
        """
        if self.version is None:
            return f"{self.product} (version not reported)"
        text = ".".join(str(n) for n in self.version)
        suffix = "" if self.version_type in ("official", "") else f"-{self.version_type}"
        return f"{self.product} {text}{suffix}"

    def at_least(self, major: int, minor: int) -> bool | None:
        """Version >= major.minor, or None when the version is unknown."""
        if self.version is None:
            return None
        return self.version[:2] >= (major, minor)

    def as_dict(self) -> dict[str, Any]:
        """The report's ``vehicle.firmware`` (README's report schema)."""
        return {"name": self.name, "autopilot": self.family.value, "product": self.product,
                "vehicle_type": self.vehicle_type,
                "version": ".".join(str(n) for n in self.version) if self.version else None,
                "version_type": self.version_type or None, "capabilities": self.capabilities,
                "source": self.source}


def firmware_from(heartbeat: Heartbeat, version: AutopilotVersion | None) -> Firmware:
    """Combine the heartbeat and the AUTOPILOT_VERSION answer (None: not answered).

    >>> hb = Heartbeat(0.0, 3, 2, 0, 0, 3)
    >>> firmware_from(hb, AutopilotVersion(0, 0x04070000, 0, 0)).name
    'ArduCopter 4.7.0-dev'
    """
    family = autopilot_family(heartbeat.autopilot)
    if version is None or version.flight_sw_version == 0:
        return Firmware(family, heartbeat.vehicle_type,
                        capabilities=None if version is None else version.capabilities)
    major, minor, patch, kind = decode_sw_version(version.flight_sw_version)
    return Firmware(family, heartbeat.vehicle_type, (major, minor, patch), kind,
                    version.capabilities, "AUTOPILOT_VERSION")


def detect_firmware(link: VehicleLink, timeout_s: float = 1.0) -> Firmware:
    """Ask the vehicle for AUTOPILOT_VERSION and combine it with its heartbeat."""
    return firmware_from(link.heartbeat, link.request_autopilot_version(timeout_s))


def torque_path_refusal(fw: Firmware) -> str | None:
    """Why torque setpoints (SET_ACTUATOR_CONTROL_TARGET) cannot reach ``fw``; None if they can.

    >>> torque_path_refusal(Firmware(AutopilotFamily.PX4, 2, (1, 13, 3), "official")) is None
    True
    >>> torque_path_refusal(Firmware(AutopilotFamily.PX4, 2, (1, 14, 0), "official"))[:27]
    'PX4 1.14.0 has no MAVLink t'
    """
    if fw.family is AutopilotFamily.ARDUPILOT:
        return (f"{fw.name} has no handler for SET_ACTUATOR_CONTROL_TARGET (torque setpoints "
                f"are ignored)")
    if fw.family is AutopilotFamily.PX4 and fw.at_least(1, 14):
        return (f"{fw.name} has no MAVLink torque input (SET_ACTUATOR_CONTROL_TARGET was "
                f"removed from offboard in v1.14)")
    return None
