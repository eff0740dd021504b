"""The live vehicle link: typed telemetry in, commands and setpoints out, all logged.

:class:`VehicleLink` owns one pymavlink connection. A reader thread turns every wire
message into a typed value once (:mod:`mrft_gcs.telemetry` samples, plus
:class:`CommandAck` and :class:`ParamReport`), logs the frame to the session's
.tlog, and hands it to :meth:`VehicleLink.next_sample` (the
:class:`~mrft_gcs.telemetry.TelemetrySource` protocol) and to any
:meth:`~VehicleLink.subscribe` waiter. Senders (the CLI thread, the setpoint
streamer) share one lock, so frames and signing timestamps never interleave. The
GCS heartbeat goes out once a second (``heartbeat_period_s``) from the reader thread.
"""

from __future__ import annotations

import collections
import math
import os
import queue
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mrft_gcs.errors import LinkError
from mrft_gcs.link.connection import (
    ConnectionSpec,
    autopilot_family,
    load_signing_key,
    open_mavlink,
    parse_connection_string,
    wait_vehicle_heartbeat,
)
from mrft_gcs.link.latency import latency_hints
from mrft_gcs.link.modes import ARDUPILOT_COPTER_MODES, PX4_MODES, CustomMode, mode_matches
from mrft_gcs.link.tlog import TlogSink
from mrft_gcs.telemetry import (
    ActuatorTarget,
    Attitude,
    AttitudeSetpoint,
    AttitudeTarget,
    AutopilotFamily,
    Heartbeat,
    LocalPosition,
    ParamValue,
    PidTuning,
    RateTarget,
    Sample,
    StatusText,
    ThrottleReport,
    is_finite_sample,
)

__all__ = ["VehicleLink", "CommandAck", "ParamReport", "AutopilotVersion", "TimesyncReply",
           "FtpFrame", "Subscription", "LinkCounters"]

# Wire constants (common.xml), named once here.
MAV_CMD_NAV_LAND = 21
MAV_CMD_DO_SET_MODE = 176
MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_CMD_SET_MESSAGE_INTERVAL = 511
MAV_CMD_REQUEST_MESSAGE = 512
MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES = 520
MAVLINK_MSG_ID_AUTOPILOT_VERSION = 148
MAV_RESULT_ACCEPTED = 0
MAV_RESULT_IN_PROGRESS = 5
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
MAV_TYPE_GCS = 6
MAV_AUTOPILOT_INVALID = 8
MAV_STATE_ACTIVE = 4
FORCE_DISARM_MAGIC = 21196.0
ATTITUDE_TARGET_IGNORE_RATES = 0b0000_0111
ATTITUDE_TARGET_IGNORE_ATTITUDE = 0b1000_0000
MESSAGE_IDS = {"ATTITUDE": 30, "LOCAL_POSITION_NED": 32, "HIGHRES_IMU": 105}
_MAV_RESULT_NAMES = {0: "ACCEPTED", 1: "TEMPORARILY_REJECTED", 2: "DENIED", 3: "UNSUPPORTED",
                     4: "FAILED", 5: "IN_PROGRESS", 6: "CANCELLED"}
_COMMAND_NAMES = {MAV_CMD_NAV_LAND: "NAV_LAND", MAV_CMD_DO_SET_MODE: "DO_SET_MODE",
                  MAV_CMD_COMPONENT_ARM_DISARM: "COMPONENT_ARM_DISARM",
                  MAV_CMD_SET_MESSAGE_INTERVAL: "SET_MESSAGE_INTERVAL",
                  MAV_CMD_REQUEST_MESSAGE: "REQUEST_MESSAGE",
                  MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: "REQUEST_AUTOPILOT_CAPABILITIES"}


@dataclass(frozen=True, slots=True)
class CommandAck:
    """COMMAND_ACK: ``result`` is a MAV_RESULT value."""

    command: int
    result: int

    @property
    def accepted(self) -> bool:
        return self.result == MAV_RESULT_ACCEPTED


@dataclass(frozen=True, slots=True)
class ParamReport:
    """PARAM_VALUE with its wire type (MAV_PARAM_TYPE), as the parameter protocol needs."""

    name: str
    value: float
    param_type: int
    index: int
    count: int


@dataclass(frozen=True, slots=True)
class AutopilotVersion:
    """AUTOPILOT_VERSION: what the firmware says it is (decoded in :mod:`.firmware`).

    ``flight_sw_version`` packs major, minor, patch and FIRMWARE_VERSION_TYPE in its four
    bytes (high to low); ``capabilities`` is the MAV_PROTOCOL_CAPABILITY bit mask.
    """

    capabilities: int
    flight_sw_version: int
    vendor_id: int
    product_id: int


@dataclass(frozen=True, slots=True)
class TimesyncReply:
    """A TIMESYNC answer: ``tc1_ns`` the peer's clock, ``ts1_ns`` our request echoed."""

    tc1_ns: int
    ts1_ns: int


@dataclass(frozen=True, slots=True)
class FtpFrame:
    """FILE_TRANSFER_PROTOCOL addressed to this ground station: the 251-byte MAVLink FTP
    payload (header and data), for :mod:`mrft_gcs.link.ftp`."""

    payload: bytes


#: answers that go to subscribers only, never into the telemetry queue
_REPLIES = (CommandAck, AutopilotVersion, TimesyncReply, FtpFrame)
Event = (Sample | CommandAck | ParamReport | AutopilotVersion | TimesyncReply | AttitudeSetpoint
         | PidTuning | ThrottleReport | FtpFrame)


@dataclass
class LinkCounters:
    """What the link has seen and sent since it opened."""

    received: collections.Counter[str]
    sent: collections.Counter[str]
    nonfinite_dropped: int = 0
    overflow_dropped: int = 0
    bad_frames: int = 0


class Subscription:
    """Events of the given kinds, queued from the moment of subscribing.

    Subscribe *before* sending a request so that a fast answer is not missed.
    """

    def __init__(self, kinds: tuple[type, ...]) -> None:
        self.kinds = kinds
        self._q: queue.SimpleQueue[Event] = queue.SimpleQueue()

    def _offer(self, event: Event) -> None:
        if isinstance(event, self.kinds):
            self._q.put(event)

    def get(self, timeout_s: float) -> Event | None:
        """The next event, or None after ``timeout_s``."""
        try:
            return self._q.get(timeout=max(timeout_s, 0.0))
        except queue.Empty:
            return None

    def wait_for(self, predicate: Callable[[Any], bool], timeout_s: float) -> Any | None:
        """The first event that satisfies ``predicate`` within ``timeout_s``, else None."""
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            event = self.get(left)
            if event is not None and predicate(event):
                return event
        return None


class VehicleLink:
    """A MAVLink vehicle: implements :class:`~mrft_gcs.telemetry.TelemetrySource`.

    Use :meth:`connect`; close with :meth:`close` or a ``with`` block.

    Parameters
    ----------
    conn : pymavlink connection
        Already open, heartbeat already received.
    spec : ConnectionSpec
    heartbeat : Heartbeat
        The first vehicle heartbeat.
    target : (int, int)
        Vehicle system and component id.
    tlog : TlogSink, optional
        Where every frame in both directions goes.
    queue_size : int
        Telemetry samples kept for :meth:`next_sample` (oldest dropped first, counted).
    """

    #: messages whose arrival feeds the telemetry watchdog
    TELEMETRY_KINDS = (Attitude, LocalPosition)

    def __init__(self, conn: Any, spec: ConnectionSpec, heartbeat: Heartbeat,
                 target: tuple[int, int], tlog: TlogSink | None = None,
                 queue_size: int = 20_000, signed: bool = False) -> None:
        self._conn = conn
        self.spec = spec
        self.heartbeat = heartbeat
        self.target_system, self.target_component = target
        self.family: AutopilotFamily = autopilot_family(heartbeat.autopilot)
        self.signed = signed
        self._tlog = tlog
        self._send_lock = threading.Lock()
        #: held from logging a received sample to queuing it, and by a set-point stream from
        #: reading telemetry to sending its answer: the session log's order is then the
        #: order the stream saw (a replay pairs each command with the samples before it)
        self.order_lock = threading.Lock()
        self._samples: collections.deque[Sample] = collections.deque(maxlen=queue_size)
        self._samples_cv = threading.Condition()
        self._subs: list[Subscription] = []
        self._subs_lock = threading.Lock()
        self.counters = LinkCounters(collections.Counter(), collections.Counter())
        self._t0 = time.monotonic()
        self._last_telemetry = self._t0
        self._got_telemetry = False
        self._boot_s = 0.0
        #: the smallest receive time minus vehicle time over ATTITUDE and LOCAL_POSITION_NED
        #: so far (s, monotonic clock): the least-delayed sample's, which puts vehicle times
        #: on this clock as a .tlog reader does (``mrft_gcs.logs.tlog``)
        self.rx_offset_s = math.inf
        self._stop = threading.Event()
        #: mode numbers used by :meth:`land`; a profile replaces them
        #: (``link.modes = profile.modes``)
        self.modes: dict[str, CustomMode] = self.default_modes()
        #: seconds between GCS heartbeats; a firmware-side link-loss guard that watches them
        #: (:mod:`mrft_gcs.link.failsafe`) shortens it
        self.heartbeat_period_s = 1.0
        conn.mav.set_send_callback(self._on_sent)
        self._reader = threading.Thread(target=self._read_loop, name="mavlink-reader", daemon=True)
        self._reader.start()

    # ------------------------------------------------------------------ lifecycle
    @classmethod
    def connect(cls, connection: str, *, baud: int | None = None, timeout_s: float = 5.0,
                tlog_path: str | os.PathLike[str] | None = None,
                signing_key: str | os.PathLike[str] | bytes | None = None,
                source_system: int = 255) -> VehicleLink:
        """Open ``connection`` (docs/link-and-stream.md), wait for a vehicle heartbeat.

        Parameters
        ----------
        connection : str
            ``udp:127.0.0.1:14540``, ``tcp:HOST:5760``, ``/dev/ttyUSB0`` ...
        baud : int, optional
            Serial baud rate.
        timeout_s : float
            How long to wait for the first heartbeat.
        tlog_path : path, optional
            Write all traffic in both directions to this .tlog as it happens.
        signing_key : path, hex str or bytes, optional
            MAVLink 2 signing key: everything the GCS sends is signed with it.

        Raises
        ------
        LinkError
            Bad connection string, port that cannot be opened, or no heartbeat.
        """
        spec = parse_connection_string(connection, baud)
        key = None
        if signing_key is not None:
            key = signing_key if isinstance(signing_key, bytes) else load_signing_key(signing_key)
            if len(key) != 32:
                raise LinkError("a MAVLink 2 signing key has 32 bytes")
        conn = open_mavlink(spec, source_system=source_system)
        tlog = TlogSink(tlog_path) if tlog_path is not None else None
        try:
            if tlog is not None:
                conn.mav.set_send_callback(lambda msg: tlog.write(msg.get_msgbuf()))
            if key is not None:
                conn.setup_signing(key, sign_outgoing=True,
                                   allow_unsigned_callback=lambda _mav, _msg_id: True)
            beat, sysid, compid = wait_vehicle_heartbeat(
                conn, spec, timeout_s,
                on_message=(lambda m: tlog.write(m.get_msgbuf())) if tlog else None)
        except BaseException:
            if tlog is not None:
                tlog.close()
                # no vehicle answered: the file would hold only our own heartbeats
                tlog.path.unlink(missing_ok=True)
            conn.close()
            raise
        return cls(conn, spec, beat, (sysid, compid), tlog=tlog, signed=key is not None)

    def close(self) -> None:
        """Stop the reader, close the tlog and the port. Safe to call twice."""
        if self._stop.is_set():
            return
        self._stop.set()
        self._reader.join(timeout=2.0)
        if self._tlog is not None:
            self._tlog.close()
        try:
            self._conn.close()
        except OSError:
            pass

    def __enter__(self) -> VehicleLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def source_ids(self) -> tuple[int, int]:
        """This ground station's MAVLink system and component id."""
        return int(self._conn.source_system), int(self._conn.source_component)

    @property
    def tlog_path(self) -> Path | None:
        return self._tlog.path if self._tlog is not None else None

    @property
    def tlog_error(self) -> str | None:
        """Why the session log stopped being written (None: it is complete so far)."""
        return self._tlog.error if self._tlog is not None else None

    # ------------------------------------------------------------------ receiving
    def next_sample(self, timeout_s: float = 1.0) -> Sample | None:
        """Next telemetry sample (oldest first), or None if none arrives in ``timeout_s``."""
        with self._samples_cv:
            if not self._samples:
                self._samples_cv.wait_for(lambda: bool(self._samples) or self._stop.is_set(),
                                          timeout=timeout_s)
            return self._samples.popleft() if self._samples else None

    def drain(self) -> None:
        """Forget queued samples (e.g. before a measurement window)."""
        with self._samples_cv:
            self._samples.clear()

    def telemetry_age_s(self) -> float:
        """Seconds since the last finite ATTITUDE or LOCAL_POSITION_NED (since opening if none)."""
        return time.monotonic() - self._last_telemetry

    @property
    def alive(self) -> bool:
        return not self._stop.is_set() and self._reader.is_alive()

    @contextmanager
    def subscribe(self, *kinds: type) -> Iterator[Subscription]:
        """Receive events of ``kinds`` (sample classes, CommandAck, ParamReport) in a block."""
        sub = Subscription(tuple(kinds))
        with self._subs_lock:
            self._subs.append(sub)
        try:
            yield sub
        finally:
            with self._subs_lock:
                self._subs.remove(sub)

    def _read_loop(self) -> None:
        latency_hints()  # telemetry waiting here is delay in every relay loop
        next_beat = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_beat:
                next_beat = now + self.heartbeat_period_s
                try:
                    self._send(lambda mav: mav.heartbeat_send(
                        MAV_TYPE_GCS, MAV_AUTOPILOT_INVALID, 0, 0, MAV_STATE_ACTIVE), "HEARTBEAT")
                except LinkError:
                    pass  # port gone for a moment: the reader must outlive it (watchdog decides)
            try:
                msg = self._conn.recv_match(blocking=True, timeout=0.02)
            except (OSError, ValueError):
                if self._stop.is_set():
                    return
                time.sleep(0.01)
                continue
            if msg is not None:
                self._on_received(msg)

    def _on_received(self, msg: Any) -> None:
        if msg.get_type() == "BAD_DATA":
            self.counters.bad_frames += 1
            return
        rx = time.monotonic()  # before the lock: a wait for the stream is no link delay
        with self.order_lock:
            self._take(msg, rx)

    def _take(self, msg: Any, rx: float) -> None:
        kind = msg.get_type()
        if self._tlog is not None:
            self._tlog.write(msg.get_msgbuf())
        if msg.get_srcSystem() != self.target_system:
            return
        self.counters.received[kind] += 1
        event = self._to_event(kind, msg)
        if event is None:
            return
        if isinstance(event, _REPLIES):
            self._publish(event)
            return
        if isinstance(event, AttitudeSetpoint | PidTuning | ThrottleReport):  # subscribers only
            if is_finite_sample(event):  # type: ignore[arg-type]
                self._publish(event)
            return
        if isinstance(event, ParamReport):
            self._publish(event)
            event = ParamValue(self._boot_s, event.name, event.value, event.index, event.count)
        if not is_finite_sample(event):
            self.counters.nonfinite_dropped += 1
            return
        if isinstance(event, self.TELEMETRY_KINDS):
            self._last_telemetry = rx
            self._got_telemetry = True
            self.rx_offset_s = min(self.rx_offset_s, self._last_telemetry - event.t_s)
        if isinstance(event, Heartbeat):
            self.heartbeat = event
        with self._samples_cv:
            if len(self._samples) == self._samples.maxlen:
                self.counters.overflow_dropped += 1
            self._samples.append(event)
            self._samples_cv.notify_all()
        self._publish(event)

    def _publish(self, event: Event) -> None:
        with self._subs_lock:
            subs = list(self._subs)
        for sub in subs:
            sub._offer(event)

    def _to_event(self, kind: str, m: Any) -> Event | None:
        # The one place where wire messages become typed values.
        if kind == "ATTITUDE":
            self._boot_s = m.time_boot_ms * 1e-3
            return Attitude(self._boot_s, m.roll, m.pitch, m.yaw,
                            m.rollspeed, m.pitchspeed, m.yawspeed)
        if kind == "ATTITUDE_TARGET":
            r, p, y = _euler(m.q)
            return AttitudeSetpoint(m.time_boot_ms * 1e-3, r, p, y, m.thrust)
        if kind == "PID_TUNING":
            return PidTuning(time.monotonic(), int(m.axis), m.desired, m.achieved, m.FF, m.P,
                             m.I, m.D)
        if kind == "VFR_HUD":
            return ThrottleReport(self._boot_s, float(m.throttle))
        if kind == "LOCAL_POSITION_NED":
            self._boot_s = m.time_boot_ms * 1e-3
            return LocalPosition(self._boot_s, m.x, m.y, m.z, m.vx, m.vy, m.vz)
        if kind == "HEARTBEAT":
            if m.get_srcComponent() != self.target_component:
                return None
            return Heartbeat(self._boot_s, int(m.autopilot), int(m.type), int(m.base_mode),
                             int(m.custom_mode), int(m.system_status))
        if kind == "COMMAND_ACK":
            return CommandAck(int(m.command), int(m.result))
        if kind == "PARAM_VALUE":
            name = m.param_id.decode(errors="replace") if isinstance(m.param_id, bytes) \
                else str(m.param_id)
            return ParamReport(name.rstrip("\x00"), float(m.param_value), int(m.param_type),
                               int(m.param_index), int(m.param_count))
        if kind == "STATUSTEXT":
            text = m.text.decode(errors="replace") if isinstance(m.text, bytes) else str(m.text)
            return StatusText(self._boot_s, int(m.severity), text.rstrip("\x00"))
        if kind == "TIMESYNC":
            # tc1 0 is the peer's own request (ArduPilot sends some); only answers count
            return TimesyncReply(int(m.tc1), int(m.ts1)) if m.tc1 != 0 else None
        if kind == "FILE_TRANSFER_PROTOCOL":
            mine = (m.target_system == self._conn.source_system
                    and m.target_component == self._conn.source_component)
            return FtpFrame(bytes(m.payload)) if mine else None
        if kind == "AUTOPILOT_VERSION":
            return AutopilotVersion(int(m.capabilities), int(m.flight_sw_version),
                                    int(m.vendor_id), int(m.product_id))
        return None

    # ------------------------------------------------------------------ sending
    def _on_sent(self, msg: Any) -> None:
        if self._tlog is not None:
            self._tlog.write(msg.get_msgbuf())

    def _send(self, fn: Callable[[Any], None], kind: str) -> None:
        with self._send_lock:
            try:
                fn(self._conn.mav)
            except OSError as err:
                raise LinkError(f"cannot send {kind} on {self.spec.text}: {err}") from err
            self.counters.sent[kind] += 1

    def _boot_ms(self) -> int:
        return int((time.monotonic() - self._t0) * 1000) & 0xFFFFFFFF

    def command(self, command: int, params: Sequence[float] = (), *, timeout_s: float = 1.0,
                retries: int = 2, wait_ack: bool = True) -> CommandAck | None:
        """Send COMMAND_LONG and wait for its COMMAND_ACK (resent up to ``retries`` times).

        Raises
        ------
        LinkError
            No acknowledgement, or the vehicle refused (result other than ACCEPTED).
        """
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        name = _COMMAND_NAMES.get(command, str(command))

        def send(confirmation: int) -> None:
            self._send(lambda mav: mav.command_long_send(
                self.target_system, self.target_component, command, confirmation, *p),
                "COMMAND_LONG")

        with self.subscribe(CommandAck) as sub:
            for attempt in range(retries + 1):
                send(attempt)
                if not wait_ack:
                    return None
                ack = sub.wait_for(lambda e: e.command == command
                                   and e.result != MAV_RESULT_IN_PROGRESS, timeout_s)
                if ack is None:
                    continue
                if not ack.accepted:
                    result = _MAV_RESULT_NAMES.get(ack.result, str(ack.result))
                    raise LinkError(f"vehicle refused {name} ({result})")
                return ack
        raise LinkError(f"vehicle did not acknowledge {name} within "
                        f"{timeout_s * (retries + 1):g} s: check the link quality and that the "
                        f"vehicle supports the command")

    def request_message_interval(self, message: str | int, rate_hz: float, *,
                                 timeout_s: float = 1.0) -> None:
        """Ask for ``message`` (name or id) at ``rate_hz`` (MAV_CMD_SET_MESSAGE_INTERVAL).

        ``rate_hz`` 0 stops the stream. Raises :class:`LinkError` if not acknowledged.
        """
        msg_id = MESSAGE_IDS[message] if isinstance(message, str) else int(message)
        interval_us = -1.0 if rate_hz <= 0 else 1e6 / rate_hz
        self.command(MAV_CMD_SET_MESSAGE_INTERVAL, (msg_id, interval_us), timeout_s=timeout_s)

    def ask_message_interval(self, message: str | int, rate_hz: float, *,
                             timeout_s: float = 0.5) -> bool:
        """Ask for ``message`` (name or id) at ``rate_hz``, or back to the vehicle's default
        rate with 0; False where the vehicle refuses (no exception: a stream it will not
        send is no fault)."""
        msg_id = MESSAGE_IDS[message] if isinstance(message, str) else int(message)
        try:
            self.command(MAV_CMD_SET_MESSAGE_INTERVAL,
                         (float(msg_id), 1e6 / rate_hz if rate_hz > 0 else 0.0),
                         timeout_s=timeout_s)
        except LinkError:
            return False
        return True

    def arm(self, *, timeout_s: float = 1.0) -> None:
        """Arm (MAV_CMD_COMPONENT_ARM_DISARM 1); raises LinkError if refused."""
        self.command(MAV_CMD_COMPONENT_ARM_DISARM, (1.0,), timeout_s=timeout_s)

    def disarm(self, *, force: bool = False, timeout_s: float = 1.0) -> None:
        """Disarm; ``force`` disarms in flight (motors stop: for emergencies only)."""
        self.command(MAV_CMD_COMPONENT_ARM_DISARM, (0.0, FORCE_DISARM_MAGIC if force else 0.0),
                     timeout_s=timeout_s)

    def default_modes(self) -> dict[str, CustomMode]:
        """Mode numbers for this vehicle's family (profiles may override)."""
        return dict(ARDUPILOT_COPTER_MODES if self.family is AutopilotFamily.ARDUPILOT
                    else PX4_MODES)

    def set_mode(self, mode: CustomMode, *, timeout_s: float = 1.0, confirm_s: float = 2.0) -> None:
        """Switch flight mode (MAV_CMD_DO_SET_MODE) and wait until the heartbeat shows it.

        PX4 refuses OFFBOARD unless setpoints already stream (start the streamer first).
        """
        with self.subscribe(Heartbeat) as sub:
            try:
                self.command(MAV_CMD_DO_SET_MODE,
                             (MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, mode.main, mode.sub),
                             timeout_s=timeout_s)
            except LinkError as err:
                hint = " (PX4 needs the setpoint stream running first)" \
                    if mode.name == "OFFBOARD" else ""
                raise LinkError(f"cannot switch to {mode.name}: {err}{hint}") from err
            if mode_matches(self.family, mode, self.heartbeat.custom_mode):
                return
            if sub.wait_for(lambda b: mode_matches(self.family, mode, b.custom_mode), confirm_s):
                return
        raise LinkError(f"vehicle acknowledged {mode.name} but its heartbeat does not show it "
                        f"after {confirm_s:g} s")

    def land(self, *, wait_ack: bool = True, timeout_s: float = 1.0) -> None:
        """Command a landing (MAV_CMD_NAV_LAND; if refused, switch to the family's land mode).

        With ``wait_ack=False`` (used by the watchdog, when the link may be gone) the
        command and the mode switch are both sent once, without waiting.
        """
        land_mode = self.modes["land"]
        if not wait_ack:
            self.command(MAV_CMD_NAV_LAND, wait_ack=False)
            self.command(MAV_CMD_DO_SET_MODE, (MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, land_mode.main,
                                               land_mode.sub), wait_ack=False)
            return
        try:
            self.command(MAV_CMD_NAV_LAND, timeout_s=timeout_s)
        except LinkError:
            self.set_mode(land_mode, timeout_s=timeout_s)

    def send_actuator_target(self, target: ActuatorTarget) -> None:
        """SET_ACTUATOR_CONTROL_TARGET group 0: roll, pitch, yaw in [-1, 1], thrust in [0, 1].

        Values are clipped to their ranges; a non-finite value raises LinkError
        (never put NaN on the wire).
        """
        values = (target.roll, target.pitch, target.yaw, target.thrust)
        if not all(math.isfinite(v) for v in values):
            raise LinkError(f"refusing to send a non-finite actuator setpoint {values}")
        controls = [_clip(target.roll, -1, 1), _clip(target.pitch, -1, 1),
                    _clip(target.yaw, -1, 1), _clip(target.thrust, 0, 1), 0.0, 0.0, 0.0, 0.0]
        t_us = int((time.monotonic() - self._t0) * 1e6)
        self._send(lambda mav: mav.set_actuator_control_target_send(
            t_us, 0, self.target_system, self.target_component, controls),
            "SET_ACTUATOR_CONTROL_TARGET")

    def send_attitude_target(self, target: AttitudeTarget) -> None:
        """SET_ATTITUDE_TARGET: unit quaternion (w, x, y, z) and thrust in [0, 1]; the body
        rates (rad/s) with it where the target has them, else ignored."""
        q = target.q_wxyz
        norm = math.sqrt(sum(v * v for v in q))
        rates = target.body_rates
        if not (math.isfinite(norm) and norm > 0 and math.isfinite(target.thrust)
                and (rates is None or all(math.isfinite(v) for v in rates))):
            raise LinkError(f"refusing to send a non-finite attitude setpoint {q}, {target.thrust}"
                            f"{'' if rates is None else f', {rates}'}")
        qn = [v / norm for v in q]
        mask, (wr, wp, wy) = ((ATTITUDE_TARGET_IGNORE_RATES, (0.0, 0.0, 0.0)) if rates is None
                              else (0, rates))
        self._send(lambda mav: mav.set_attitude_target_send(
            self._boot_ms(), self.target_system, self.target_component,
            mask, qn, float(wr), float(wp), float(wy), _clip(target.thrust, 0, 1)),
            "SET_ATTITUDE_TARGET")

    def send_rate_target(self, target: RateTarget) -> None:
        """SET_ATTITUDE_TARGET with the attitude ignored: body rates (rad/s) and thrust in
        [0, 1] (ArduCopter GUIDED_NOGPS; raw thrust with GUID_OPTIONS 8)."""
        rates = (target.roll_rate_rad_s, target.pitch_rate_rad_s, target.yaw_rate_rad_s)
        if not all(math.isfinite(v) for v in (*rates, target.thrust)):
            raise LinkError(f"refusing to send a non-finite rate setpoint {rates}, "
                            f"{target.thrust}")
        self._send(lambda mav: mav.set_attitude_target_send(
            self._boot_ms(), self.target_system, self.target_component,
            ATTITUDE_TARGET_IGNORE_ATTITUDE, [1.0, 0.0, 0.0, 0.0], float(rates[0]),
            float(rates[1]), float(rates[2]), _clip(target.thrust, 0, 1)), "SET_ATTITUDE_TARGET")

    def send_setpoint(self, target: ActuatorTarget | AttitudeTarget | RateTarget) -> None:
        """Send any kind of setpoint."""
        if isinstance(target, ActuatorTarget):
            self.send_actuator_target(target)
        elif isinstance(target, RateTarget):
            self.send_rate_target(target)
        else:
            self.send_attitude_target(target)

    def request_autopilot_version(self, timeout_s: float = 1.0) -> AutopilotVersion | None:
        """AUTOPILOT_VERSION, asked with MAV_CMD_REQUEST_MESSAGE (148), else with the older
        MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES; None if neither brings it (a peer that does
        not serve it is no fault). Each way waits ``timeout_s / 2`` for the acknowledgement
        and as long again for the message."""
        with self.subscribe(AutopilotVersion) as sub:
            for cmd, params in ((MAV_CMD_REQUEST_MESSAGE, (MAVLINK_MSG_ID_AUTOPILOT_VERSION,)),
                                (MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, (1.0,))):
                try:
                    self.command(cmd, params, timeout_s=timeout_s / 2, retries=1)
                except LinkError:
                    continue  # refused or unanswered: try the other way
                version = sub.get(timeout_s / 2)
                if version is not None:
                    return version  # type: ignore[return-value]
        return None

    def send_timesync(self, ts1_ns: int) -> None:
        """TIMESYNC request (tc1 0): the peer answers with its clock and ``ts1_ns`` echoed."""
        self._send(lambda mav: mav.timesync_send(0, int(ts1_ns)), "TIMESYNC")

    def send_param_request_read(self, name: str = "", index: int = -1) -> None:
        """PARAM_REQUEST_READ by name (index -1) or by index."""
        self._send(lambda mav: mav.param_request_read_send(
            self.target_system, self.target_component, name.encode(), index), "PARAM_REQUEST_READ")

    def send_file_transfer(self, payload: bytes, network: int = 0) -> None:
        """FILE_TRANSFER_PROTOCOL (MAVLink FTP) to the vehicle; ``payload`` is 251 bytes."""
        self._send(lambda mav: mav.file_transfer_protocol_send(
            network, self.target_system, self.target_component, payload),
            "FILE_TRANSFER_PROTOCOL")

    def send_param_request_list(self) -> None:
        self._send(lambda mav: mav.param_request_list_send(
            self.target_system, self.target_component), "PARAM_REQUEST_LIST")

    def send_param_set(self, name: str, value: float, param_type: int) -> None:
        self._send(lambda mav: mav.param_set_send(
            self.target_system, self.target_component, name.encode(), float(value), param_type),
            "PARAM_SET")


def _clip(v: float, lo: float, hi: float) -> float:
    return lo if v < lo else hi if v > hi else float(v)



def _euler(q: Any) -> tuple[float, float, float]:
    """ZYX Euler angles (rad) of a quaternion ``(w, x, y, z)``."""
    w, x, y, z = (float(v) for v in q)
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw
