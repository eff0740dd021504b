"""The MAVLink link: connection strings, the vehicle, the setpoint stream, link quality.

Nothing outside this subpackage touches raw MAVLink messages (STYLE 6).
"""

from mrft_gcs.link.connection import (
    ACCEPTED_FORMS,
    ConnectionSpec,
    LinkKind,
    autopilot_family,
    load_signing_key,
    parse_connection_string,
)
from mrft_gcs.link.modes import ARDUPILOT_COPTER_MODES, PX4_MODES, CustomMode
from mrft_gcs.link.quality import (
    LinkNeeds,
    LinkQuality,
    check_serial_baud,
    link_needs,
    measure_link,
    require_relay_capable,
)
from mrft_gcs.link.streamer import SetpointStreamer, StreamStats, period_stats
from mrft_gcs.link.vehicle import CommandAck, ParamReport, Subscription, VehicleLink

__all__ = [
    "ACCEPTED_FORMS",
    "ConnectionSpec",
    "LinkKind",
    "autopilot_family",
    "load_signing_key",
    "parse_connection_string",
    "CustomMode",
    "PX4_MODES",
    "ARDUPILOT_COPTER_MODES",
    "LinkNeeds",
    "LinkQuality",
    "check_serial_baud",
    "link_needs",
    "measure_link",
    "require_relay_capable",
    "SetpointStreamer",
    "StreamStats",
    "period_stats",
    "CommandAck",
    "ParamReport",
    "Subscription",
    "VehicleLink",
]
