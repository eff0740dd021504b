"""What the link sustains, measured before arming, and whether a relay test fits in it.

A relay test closes the loop through the link: telemetry down at the rate the
relay switches on, setpoints up at the streamer rate. The bytes that takes
(MAVLink 2 frames, 10 bits a byte on a UART) are known in advance, so a serial
link too slow for the test is refused before anything is measured; on any link
the achieved telemetry rate and round-trip time are measured and checked.

The round trip is timed with TIMESYNC, which PX4 and ArduPilot answer as soon as it
arrives. A parameter read is not a fair probe: ArduPilot answers PARAM_REQUEST_READ
only from its parameter stream (~100 ms a read on any link). A peer that does not
answer TIMESYNC (the bundled SITL) is timed with PARAM_REQUEST_READ instead.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mrft_gcs.errors import LinkError
from mrft_gcs.link.vehicle import ParamReport, TimesyncReply, VehicleLink
from mrft_gcs.telemetry import Attitude, LocalPosition

__all__ = [
    "LinkQuality",
    "LinkNeeds",
    "link_needs",
    "measure_link",
    "require_relay_capable",
    "check_serial_baud",
    "STANDARD_BAUDS",
    "RTT_TIMESYNC",
    "RTT_PARAM_READ",
]

RTT_TIMESYNC = "TIMESYNC"
RTT_PARAM_READ = "PARAM_REQUEST_READ"

# MAVLink 2 frame = 10 header + payload + 2 CRC (+ 13 when signed); payloads at full length.
_FRAME_OVERHEAD = 12
_SIGNATURE = 13
_PAYLOAD = {"ATTITUDE": 28, "LOCAL_POSITION_NED": 28, "SET_ACTUATOR_CONTROL_TARGET": 43,
            "SET_ATTITUDE_TARGET": 39, "HEARTBEAT": 9}
STANDARD_BAUDS = (57600, 115200, 230400, 460800, 921600, 1500000, 3000000)
_UART_BITS_PER_BYTE = 10
_HEADROOM = 1.25  # leave a quarter of the link for parameters, status text, retries


@dataclass(frozen=True)
class LinkNeeds:
    """Bytes per second a relay test puts on the link, each way, and the baud that carries it."""

    down_bytes_s: float
    up_bytes_s: float
    min_baud: int  # smallest standard UART baud with headroom

    def describe(self) -> str:
        return (f"{self.down_bytes_s / 1000:.1f} kB/s down and {self.up_bytes_s / 1000:.1f} kB/s "
                f"up (a serial link of at least {self.min_baud} baud, or UDP/TCP over Ethernet "
                f"or Wi-Fi)")


def link_needs(telemetry_hz: float = 250.0, setpoint_hz: float = 250.0,
               actuation: str = "torque", signed: bool = False) -> LinkNeeds:
    """Bytes a relay test needs: ATTITUDE + LOCAL_POSITION_NED down, setpoints up.

    >>> link_needs(250, 250).min_baud
    460800
    """
    sig = _SIGNATURE if signed else 0
    down = telemetry_hz * (_PAYLOAD["ATTITUDE"] + _PAYLOAD["LOCAL_POSITION_NED"]
                           + 2 * _FRAME_OVERHEAD)
    setpoint = "SET_ACTUATOR_CONTROL_TARGET" if actuation == "torque" else "SET_ATTITUDE_TARGET"
    up = setpoint_hz * (_PAYLOAD[setpoint] + _FRAME_OVERHEAD + sig)
    need_bps = max(down, up) * _UART_BITS_PER_BYTE * _HEADROOM
    baud = next((b for b in STANDARD_BAUDS if b >= need_bps), STANDARD_BAUDS[-1])
    return LinkNeeds(down, up, baud)


@dataclass(frozen=True)
class LinkQuality:
    """Measured link figures.

    ``attitude_hz``/``position_hz`` are achieved after asking for ``requested_hz``;
    round-trip times in milliseconds, timed with ``rtt_method`` (TIMESYNC, or
    PARAM_REQUEST_READ -> PARAM_VALUE where the peer does not answer TIMESYNC).
    """

    requested_hz: float
    attitude_hz: float
    position_hz: float
    rtt_p50_ms: float
    rtt_max_ms: float
    rtt_lost: int
    pings: int
    window_s: float
    baud_bps: int = 0
    rtt_method: str = RTT_PARAM_READ
    rtt_p90_ms: float = math.nan

    @property
    def telemetry_hz(self) -> float:
        return min(self.attitude_hz, self.position_hz)

    def line(self) -> str:
        return (f"telemetry {self.attitude_hz:.0f} Hz ATTITUDE, {self.position_hz:.0f} Hz "
                f"LOCAL_POSITION_NED (asked {self.requested_hz:g} Hz); round trip "
                f"({self.rtt_method}) p50 {self.rtt_p50_ms:.1f} ms, p90 {self.rtt_p90_ms:.1f} ms, "
                f"max {self.rtt_max_ms:.1f} ms, {self.rtt_lost}/{self.pings} lost")


def timesync_rtts(link: VehicleLink, pings: int = 10, timeout_s: float = 0.25,
                  give_up_after: int = 2) -> tuple[list[float], int]:
    """Round trips (ms) of ``pings`` TIMESYNC requests, and how many got no answer.

    Returns ``([], n)`` when the first ``give_up_after`` requests all go unanswered
    (a peer that does not serve TIMESYNC).
    """
    rtts: list[float] = []
    lost = 0

    def answers(sent: int) -> Callable[[TimesyncReply], bool]:
        return lambda e: e.ts1_ns == sent

    with link.subscribe(TimesyncReply) as sub:
        for i in range(pings):
            ts1 = time.monotonic_ns()
            link.send_timesync(ts1)
            if sub.wait_for(answers(ts1), timeout_s) is None:
                lost += 1
                if not rtts and i + 1 >= give_up_after:
                    return [], lost
            else:
                rtts.append((time.monotonic_ns() - ts1) * 1e-6)
    return rtts, lost


def _param_read_rtts(link: VehicleLink, pings: int) -> tuple[list[float], int]:
    rtts: list[float] = []
    lost = 0
    with link.subscribe(ParamReport) as sub:
        for _ in range(pings):
            t = time.monotonic()
            link.send_param_request_read(index=0)
            if sub.wait_for(lambda e: e.index == 0, 0.5) is None:
                lost += 1
            else:
                rtts.append((time.monotonic() - t) * 1e3)
    return rtts, lost


def measure_link(link: VehicleLink, rate_hz: float = 250.0, window_s: float = 1.0,
                 pings: int = 10, settle_s: float = 0.3) -> LinkQuality:
    """Ask for ATTITUDE and LOCAL_POSITION_NED at ``rate_hz``, count what arrives over
    ``window_s``, then time ``pings`` round trips: TIMESYNC, or parameter reads
    (PARAM_REQUEST_READ index 0) where the first TIMESYNC requests go unanswered.

    Raises
    ------
    LinkError
        If the vehicle does not acknowledge the message-interval requests.
    """
    for name in ("ATTITUDE", "LOCAL_POSITION_NED"):
        link.request_message_interval(name, rate_hz)
    with link.subscribe(Attitude, LocalPosition) as sub:
        time.sleep(settle_s)
        while sub.get(0.0) is not None:  # drop what queued while the rate changed
            pass
        t_att: list[float] = []
        t_pos: list[float] = []
        start = time.monotonic()
        end = start + window_s
        while (left := end - time.monotonic()) > 0:
            e = sub.get(left)
            if isinstance(e, Attitude):
                t_att.append(e.t_s)
            elif isinstance(e, LocalPosition):
                t_pos.append(e.t_s)
    method = RTT_TIMESYNC
    rtts, lost = timesync_rtts(link, pings)
    if not rtts:
        method = RTT_PARAM_READ
        rtts, lost = _param_read_rtts(link, pings)
    rtt = np.asarray(rtts) if rtts else np.asarray([np.inf])
    return LinkQuality(
        requested_hz=rate_hz, attitude_hz=len(t_att) / window_s, position_hz=len(t_pos) / window_s,
        rtt_p50_ms=float(np.median(rtt)), rtt_max_ms=float(rtt.max()), rtt_lost=lost,
        pings=pings, window_s=window_s, baud_bps=link.spec.baud_bps, rtt_method=method,
        rtt_p90_ms=float(np.percentile(rtt, 90)))


def require_relay_capable(quality: LinkQuality, *, min_telemetry_hz: float = 200.0,
                          max_rtt_ms: float = 50.0, setpoint_hz: float = 250.0,
                          actuation: str = "torque", signed: bool = False) -> None:
    """Refuse a relay test the measured link cannot carry.

    The defaults follow from the method: the relay switches on telemetry, and the
    fastest inner-loop oscillations have periods of a few tens of milliseconds, so
    fewer than about 200 samples a second (or a round trip longer than the ~50 ms
    delay the classifiers were trained with) distort the cycle the model is read from.

    Raises
    ------
    LinkError
        Naming what was measured and what link is needed.
    """
    needs = link_needs(quality.requested_hz, setpoint_hz, actuation, signed)
    if quality.baud_bps and quality.baud_bps < needs.min_baud:
        raise LinkError(f"a {quality.baud_bps}-baud serial link cannot carry a relay test: it "
                        f"needs {needs.describe()}")
    problems = []
    if quality.telemetry_hz < min_telemetry_hz:
        problems.append(f"telemetry arrives at {quality.telemetry_hz:.0f} Hz "
                        f"(needs >= {min_telemetry_hz:g} Hz)")
    if quality.rtt_lost > quality.pings // 2 or quality.rtt_p50_ms > max_rtt_ms:
        problems.append(f"round trip ({quality.rtt_method}) {quality.rtt_p50_ms:.0f} ms with "
                        f"{quality.rtt_lost}/{quality.pings} lost (needs <= {max_rtt_ms:g} ms)")
    if problems:
        raise LinkError(f"this link cannot carry a relay test: {'; '.join(problems)}; use a "
                        f"link that carries {needs.describe()}")


def check_serial_baud(baud_bps: int, telemetry_hz: float = 250.0, setpoint_hz: float = 250.0,
                      actuation: str = "torque", signed: bool = False) -> None:
    """Refuse, before connecting, a serial baud too slow for the test (LinkError)."""
    needs = link_needs(telemetry_hz, setpoint_hz, actuation, signed)
    if baud_bps < needs.min_baud:
        raise LinkError(f"a {baud_bps}-baud serial link cannot carry a relay test at "
                        f"{telemetry_hz:g} Hz: it needs {needs.describe()}")
