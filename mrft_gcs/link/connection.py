"""Opening a MAVLink connection: connection strings, heartbeat, autopilot family.

Connection strings follow pymavlink (docs/link-and-stream.md):

=======================  =====================================================
``udp:HOST:PORT``        listen on HOST:PORT (same as ``udpin:``); PX4 SITL
                         sends to 127.0.0.1:14540
``udpin:HOST:PORT``      listen on HOST:PORT
``udpout:HOST:PORT``     send to HOST:PORT (the vehicle listens)
``tcp:HOST:PORT``        connect to a TCP server (ArduPilot SITL: 5760)
``tcpin:HOST:PORT``      listen for one TCP client
``/dev/ttyUSB0``         serial device; baud from ``--baud`` or ``DEVICE,BAUD``
=======================  =====================================================

The string is validated before anything is opened, so a typo fails at once with
one line that lists the accepted forms.
"""

from __future__ import annotations

import enum
import os
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mrft_gcs.errors import LinkError, UsageError
from mrft_gcs.telemetry import AutopilotFamily, Heartbeat

__all__ = [
    "LinkKind",
    "ConnectionSpec",
    "ACCEPTED_FORMS",
    "parse_connection_string",
    "open_mavlink",
    "wait_vehicle_heartbeat",
    "autopilot_family",
    "load_signing_key",
    "mavlink_module",
    "DEFAULT_SERIAL_BAUD",
]

ACCEPTED_FORMS = (
    "udp:HOST:PORT, udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT, tcpin:HOST:PORT, "
    "or a serial device such as /dev/ttyUSB0 (with --baud) or /dev/ttyUSB0,921600"
)
#: a telemetry radio's usual rate: enough for ``params``, too slow for a relay test
#: (:func:`mrft_gcs.link.quality.check_serial_baud` says so before the test)
DEFAULT_SERIAL_BAUD = 57600

# MAV_AUTOPILOT values (common.xml) and MAV_TYPE values that are never the vehicle.
_MAV_AUTOPILOT_GENERIC = 0
_MAV_AUTOPILOT_ARDUPILOTMEGA = 3
_MAV_AUTOPILOT_INVALID = 8
_MAV_AUTOPILOT_PX4 = 12
_MAV_TYPE_GCS = 6
# GCS, ONBOARD_CONTROLLER, GIMBAL, ADSB
_NOT_A_VEHICLE_TYPES = frozenset({_MAV_TYPE_GCS, 18, 26, 27})


class LinkKind(enum.Enum):
    """Transport named by a connection string."""

    UDP_IN = "udpin"
    UDP_OUT = "udpout"
    TCP = "tcp"
    TCP_IN = "tcpin"
    SERIAL = "serial"


@dataclass(frozen=True)
class ConnectionSpec:
    """A validated connection string.

    ``host``/``port`` are set for network links; ``device``/``baud_bps`` for serial.
    """

    text: str
    kind: LinkKind
    host: str = ""
    port: int = 0
    device: str = ""
    baud_bps: int = 0

    @property
    def is_serial(self) -> bool:
        return self.kind is LinkKind.SERIAL

    def pymavlink_device(self) -> str:
        """The device string pymavlink expects."""
        if self.is_serial:
            return self.device
        return f"{self.kind.value}:{self.host}:{self.port}"


_NET = re.compile(r"^(udp|udpin|udpout|tcp|tcpin):([^:\s]+):(\d{1,5})$")
_SERIAL = re.compile(r"^((?:/dev/|/)[^\s,:]+|COM\d+)(?:,(\d+))?$", re.IGNORECASE)


def parse_connection_string(text: str, baud: int | None = None) -> ConnectionSpec:
    """Validate a connection string (docs/link-and-stream.md).

    Parameters
    ----------
    text : str
        For example ``udp:127.0.0.1:14540`` or ``/dev/ttyUSB0,921600``.
    baud : int, optional
        Serial baud rate (``--baud``); overrides a ``,BAUD`` suffix.

    Raises
    ------
    LinkError
        If the string is none of the accepted forms.

    Examples
    --------
    >>> parse_connection_string("udp:127.0.0.1:14540").kind
    <LinkKind.UDP_IN: 'udpin'>
    >>> parse_connection_string("/dev/ttyUSB0,921600").baud_bps
    921600
    """
    text = text.strip()
    m = _NET.match(text)
    if m:
        scheme, host, port_s = m.groups()
        port = int(port_s)
        if not 0 < port < 65536:
            raise LinkError(f"port {port} in '{text}' is out of range 1-65535")
        kind = {"udp": LinkKind.UDP_IN, "udpin": LinkKind.UDP_IN, "udpout": LinkKind.UDP_OUT,
                "tcp": LinkKind.TCP, "tcpin": LinkKind.TCP_IN}[scheme]
        if baud is not None:
            raise LinkError(f"--baud applies to serial devices only, not to '{text}'")
        return ConnectionSpec(text=text, kind=kind, host=host, port=port)
    m = _SERIAL.match(text)
    if m:
        device, suffix = m.groups()
        rate = baud if baud is not None else int(suffix) if suffix else DEFAULT_SERIAL_BAUD
        if rate <= 0:
            raise LinkError(f"baud rate {rate} is not positive")
        return ConnectionSpec(text=text, kind=LinkKind.SERIAL, device=device, baud_bps=rate)
    raise LinkError(f"cannot read connection string '{text}': use {ACCEPTED_FORMS}")


def mavlink_module() -> Any:
    """pymavlink's ``mavutil`` with the MAVLink 2 wire protocol selected.

    MAVLink 2 is required for signing and for message ids above 255. pymavlink picks
    the wire protocol from the ``MAVLINK20`` environment variable when a dialect is set,
    so it is set here (once) before any connection object is built.
    """
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink import mavutil

    if not mavutil.mavlink20():  # imported elsewhere before MAVLINK20 was set
        os.environ["MAVLINK20"] = "1"
    if getattr(mavutil.mavlink, "WIRE_PROTOCOL_VERSION", "1.0") != "2.0":
        mavutil.set_dialect(mavutil.current_dialect)
    return mavutil


def open_mavlink(spec: ConnectionSpec, source_system: int = 255,
                 source_component: int = 190) -> Any:
    """Open the pymavlink connection object for ``spec`` (component 190: MISSIONPLANNER).

    Raises
    ------
    LinkError
        If the port cannot be opened (in use, no such device, permission).
    """
    mavutil = mavlink_module()
    try:
        if spec.is_serial:
            return mavutil.mavlink_connection(
                spec.device, baud=spec.baud_bps, source_system=source_system,
                source_component=source_component, autoreconnect=False)
        return mavutil.mavlink_connection(
            spec.pymavlink_device(), source_system=source_system,
            source_component=source_component, retries=0)
    except OSError as err:
        raise LinkError(f"cannot open {spec.text}: {err.strerror or err}; check that the device "
                        f"exists and the port is free") from err
    except Exception as err:  # pyserial's SerialException, tcp refusals wrapped by pymavlink
        raise LinkError(f"cannot open {spec.text}: {err}") from err


def autopilot_family(autopilot: int) -> AutopilotFamily:
    """Map HEARTBEAT.autopilot (MAV_AUTOPILOT) to a family."""
    if autopilot == _MAV_AUTOPILOT_PX4:
        return AutopilotFamily.PX4
    if autopilot == _MAV_AUTOPILOT_ARDUPILOTMEGA:
        return AutopilotFamily.ARDUPILOT
    if autopilot == _MAV_AUTOPILOT_GENERIC:
        return AutopilotFamily.GENERIC
    return AutopilotFamily.OTHER


def _is_vehicle_heartbeat(msg: Any) -> bool:
    return msg.autopilot != _MAV_AUTOPILOT_INVALID and msg.type not in _NOT_A_VEHICLE_TYPES


def wait_vehicle_heartbeat(conn: Any, spec: ConnectionSpec, timeout_s: float = 5.0,
                           on_message: Any = None) -> tuple[Heartbeat, int, int]:
    """Wait for the first heartbeat from a vehicle; returns it with (sysid, compid).

    The GCS sends its own heartbeat once a second while waiting, so that peers which
    only answer a known GCS (``udpout:``, ``tcp:``, ArduPilot's GCS port) start sending.
    ``on_message(msg)`` sees every message received (used to log them to the tlog).

    Raises
    ------
    LinkError
        If no vehicle heartbeat arrives within ``timeout_s``.
    """
    deadline = time.monotonic() + timeout_s
    next_beat = 0.0
    while True:
        now = time.monotonic()
        if now >= deadline:
            break
        if now >= next_beat:
            try:
                conn.mav.heartbeat_send(_MAV_TYPE_GCS, _MAV_AUTOPILOT_INVALID, 0, 0, 0)
            except OSError:
                pass  # udpin has no peer address yet
            next_beat = now + 1.0
        msg = conn.recv_match(blocking=True, timeout=min(0.1, max(deadline - now, 0.001)))
        if msg is None or msg.get_type() == "BAD_DATA":
            continue
        if on_message is not None:
            on_message(msg)
        if msg.get_type() == "HEARTBEAT" and _is_vehicle_heartbeat(msg):
            beat = Heartbeat(t_s=0.0, autopilot=int(msg.autopilot), vehicle_type=int(msg.type),
                             base_mode=int(msg.base_mode), custom_mode=int(msg.custom_mode),
                             system_status=int(msg.system_status))
            return beat, int(msg.get_srcSystem()), int(msg.get_srcComponent())
    where = "sending to this port" if spec.kind is LinkKind.UDP_IN else "reachable at that address"
    if spec.is_serial:
        where = f"connected at {spec.baud_bps} baud"
    raise LinkError(f"no heartbeat from {spec.text} within {timeout_s:g} s: is the vehicle on and "
                    f"{where}?")


def load_signing_key(value: str | os.PathLike[str]) -> bytes:
    """Read a MAVLink 2 signing key: a 32-byte binary file, a file holding 64 hex digits,
    or 64 hex digits given directly.

    Raises
    ------
    UsageError
        If the value is none of these.
    """
    text = str(value)
    path = Path(text)
    if path.is_file():
        raw = path.read_bytes()
        if len(raw) == 32:
            return raw
        stripped = raw.strip()
        if re.fullmatch(rb"[0-9a-fA-F]{64}", stripped):
            return bytes.fromhex(stripped.decode())
        raise UsageError(f"signing key file {text} holds {len(raw)} bytes: it must hold the "
                         f"32-byte key, raw or as 64 hex digits")
    if re.fullmatch(r"[0-9a-fA-F]{64}", text):
        return bytes.fromhex(text)
    raise UsageError(f"signing key '{text}' is neither a file nor 64 hex digits: give the file "
                     f"that holds the vehicle's 32-byte key")
