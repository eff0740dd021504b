"""MAVLink 2 over UDP for the simulated vehicle, PX4-style (the subset in docs/link-and-stream.md).

Like PX4 SITL's offboard port, the server *sends* to ``127.0.0.1:PORT`` (default 14540) from
an ephemeral local port and answers on the same socket; a ground station listens on the port
(pymavlink ``udp:127.0.0.1:14540``, MAVSDK ``udpin://127.0.0.1:14540``). System 1,
component 1 (autopilot), MAVLink 2.

Served: HEARTBEAT (1 Hz), COMMAND_LONG / COMMAND_INT -> COMMAND_ACK
(MAV_CMD_COMPONENT_ARM_DISARM, MAV_CMD_DO_SET_MODE, MAV_CMD_SET_MESSAGE_INTERVAL,
MAV_CMD_NAV_LAND, MAV_CMD_REQUEST_MESSAGE for AUTOPILOT_VERSION; anything else is answered
MAV_RESULT_UNSUPPORTED), SET_MODE, SET_ACTUATOR_CONTROL_TARGET (group 0),
SET_ATTITUDE_TARGET, PARAM_REQUEST_LIST / PARAM_REQUEST_READ / PARAM_SET -> PARAM_VALUE,
TIMESYNC (a request answered at once with the vehicle clock in ns), STATUSTEXT.
Streams (rates set with MAV_CMD_SET_MESSAGE_INTERVAL, up to 1000 Hz): ATTITUDE
(default 50 Hz), ATTITUDE_QUATERNION (50 Hz), LOCAL_POSITION_NED (30 Hz), HIGHRES_IMU (off),
ATTITUDE_TARGET (off; the set point the attitude loop last tracked),
SYS_STATUS and EXTENDED_SYS_STATE (1 Hz).

Timing: simulated time follows a monotonic clock times ``speedup``; physics runs in 1 ms
steps caught up on each wake, telemetry is sent when simulated time crosses its due time, and
the loop sleeps in ``select`` until the next message is due or a datagram arrives.

A vehicle's ``link_delay_s`` holds every frame that long in simulated time, each way;
its ``telemetry_max_hz`` caps every stream (asking faster gives that rate).

Malformed input (garbage, truncated frames, bad CRC, bad signature, NaN or out-of-range
setpoints) is dropped and counted; it never stops the server.
"""

from __future__ import annotations

import collections
import math
import select
import socket
import threading
import time
from dataclasses import dataclass, field
from typing import Any

from pymavlink.dialects.v20 import common as mavlink2

from mrft_gcs.link.latency import latency_hints
from mrft_gcs.sitl.onboard import CommandResult, FlightMode
from mrft_gcs.sitl.physics import quat_from_euler
from mrft_gcs.sitl.vehicle import SimVehicle

__all__ = ["SitlServer", "ServerStats", "DEFAULT_STREAM_HZ", "MAX_STREAM_HZ"]

M = mavlink2
MAX_STREAM_HZ = 1000.0
DEFAULT_STREAM_HZ: dict[int, float] = {
    M.MAVLINK_MSG_ID_ATTITUDE: 50.0,
    M.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: 50.0,
    M.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 30.0,
    M.MAVLINK_MSG_ID_HIGHRES_IMU: 0.0,
    M.MAVLINK_MSG_ID_SYS_STATUS: 1.0,
    M.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 1.0,
    M.MAVLINK_MSG_ID_ATTITUDE_TARGET: 0.0,
}
_FORCE_DISARM = 21196.0
_UNSIGNED_OK = {M.MAVLINK_MSG_ID_HEARTBEAT, M.MAVLINK_MSG_ID_RADIO_STATUS}


@dataclass
class ServerStats:
    """Counters for tests and the jitter benchmark."""

    received: int = 0
    rejected: int = 0          # malformed frames, bad signatures, invalid setpoints
    sent: int = 0
    overruns: int = 0          # times the loop fell > 0.25 s behind and dropped wall time
    commands: dict[int, int] = field(default_factory=dict)


class _UdpWriter:
    """File-like sink that pymavlink writes packed frames to.

    With a link delay, frames wait in :attr:`queue` (due simulated time, bytes) until
    :meth:`flush` finds them due.
    """

    def __init__(self, sock: socket.socket, addr: tuple[str, int], stats: ServerStats,
                 delay_s: float = 0.0, clock: Any = None) -> None:
        self.sock, self.addr, self.stats = sock, addr, stats
        self.delay_s, self.clock = delay_s, clock
        self.queue: collections.deque[tuple[float, bytes]] = collections.deque()

    def write(self, buf: bytes) -> None:
        if self.delay_s > 0:
            self.queue.append((self.clock() + self.delay_s, bytes(buf)))
            return
        self._send(buf)

    def flush(self, t: float) -> None:
        while self.queue and self.queue[0][0] <= t + 1e-9:
            self._send(self.queue.popleft()[1])

    def _send(self, buf: bytes) -> None:
        try:
            self.sock.sendto(buf, self.addr)
            self.stats.sent += 1
        except OSError:
            pass  # nobody listening yet (ICMP port unreachable): keep going


class SitlServer:
    """Serve one :class:`SimVehicle` over MAVLink/UDP until :meth:`stop` is called.

    Parameters
    ----------
    vehicle : SimVehicle
    port : int
        UDP port the ground station listens on (the server sends there).
    host : str
        Address of the ground station, default loopback.
    speedup : float
        Simulated seconds per wall-clock second (1 = real time).
    signing_key : bytes or None
        32-byte MAVLink 2 signing key: if given, outgoing frames are signed and incoming
        frames other than HEARTBEAT must carry a valid signature.
    """

    def __init__(self, vehicle: SimVehicle, port: int = 14540, host: str = "127.0.0.1",
                 speedup: float = 1.0, signing_key: bytes | None = None) -> None:
        if not speedup > 0:
            raise ValueError("speedup must be > 0")
        self.vehicle = vehicle
        self.addr = (host, int(port))
        self.speedup = float(speedup)
        self.stats = ServerStats()
        self._stop = threading.Event()
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((host, 0))
        try:  # room for bursts (a flood must not crowd out the next command)
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        except OSError:
            pass
        self.sock.setblocking(False)
        af = vehicle.airframe
        #: the vehicle's link: one-way delay (s) each direction, fastest stream (Hz)
        self.link_delay_s = float(af.link_delay_s)
        self.max_stream_hz = min(MAX_STREAM_HZ, float(af.telemetry_max_hz))
        self._writer = _UdpWriter(self.sock, self.addr, self.stats, self.link_delay_s,
                                  lambda: self.vehicle.time_s)
        self._inbox: collections.deque[tuple[float, Any]] = collections.deque()
        self.mav = M.MAVLink(self._writer, srcSystem=1, srcComponent=1)
        self.mav.robust_parsing = True
        if signing_key is not None:
            if len(signing_key) != 32:
                raise ValueError("signing key must be 32 bytes")
            sg = self.mav.signing
            sg.secret_key = bytes(signing_key)
            sg.sign_outgoing = True
            sg.link_id = 0
            sg.timestamp = int((time.time() - 1420070400) * 1e5)
            sg.allow_unsigned_callback = lambda _mav, msg_id: msg_id in _UNSIGNED_OK
        self._interval = {mid: (1.0 / min(hz, self.max_stream_hz) if hz > 0 else 0.0)
                          for mid, hz in DEFAULT_STREAM_HZ.items()}
        self._due = {mid: 0.0 for mid in self._interval}
        self._next_heartbeat = 0.0
        self._next_any = 0.0
        self.stream_log: list[tuple[float, float]] | None = None  # (wall, sim) of ATTITUDE

    # ------------------------------------------------------------- lifecycle
    def stop(self) -> None:
        """Ask :meth:`serve_forever` to return (thread- and signal-safe)."""
        self._stop.set()

    def close(self) -> None:
        self.sock.close()

    def serve_forever(self) -> None:
        """Run in (scaled) real time until :meth:`stop`."""
        latency_hints()  # a late wake-up here is delay in the ground station's relay loops
        v = self.vehicle
        dt = v.dt
        wall0 = time.monotonic() - v.time_s / self.speedup
        max_lag = max(1, int(0.25 / dt))
        while not self._stop.is_set():
            now = time.monotonic()
            target = int((now - wall0) * self.speedup / dt + 1e-9)
            lag = target - v.steps
            if lag > max_lag:  # overloaded: slow simulated time down rather than burst
                self.stats.overruns += 1
                wall0 += (lag - 1) * dt / self.speedup
                target = v.steps + 1
            while v.steps < target:
                v.step()
                if self._inbox or self._writer.queue:
                    self._link_due(v.time_s)
                if v.time_s >= self._next_any - 1e-9:
                    self._send_due(v.time_s)
            self._send_events()
            self._receive()
            nxt = self._next_any
            if self._inbox or self._writer.queue:
                self._link_due(v.time_s)
                nxt = min([nxt] + [q[0][0] for q in (self._inbox, self._writer.queue) if q])
            wake = wall0 + nxt / self.speedup
            timeout = min(max(0.0, wake - time.monotonic()), 0.004)
            try:
                select.select([self.sock], [], [], timeout)
            except (OSError, ValueError):
                break

    # -------------------------------------------------------------- sending
    def _send_due(self, t: float) -> None:
        if t >= self._next_heartbeat - 1e-9:
            self._heartbeat()
            self._next_heartbeat = t + 1.0
        for mid, interval in self._interval.items():
            if interval > 0 and t >= self._due[mid] - 1e-9:
                self._send_stream(mid, t)
                due = self._due[mid] + interval
                self._due[mid] = due if due > t else t + interval
        nxt = [self._due[m] for m, i in self._interval.items() if i > 0]
        self._next_any = min([self._next_heartbeat, *nxt])

    def _heartbeat(self) -> None:
        ap = self.vehicle.autopilot
        base = M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if ap.armed:
            base |= M.MAV_MODE_FLAG_SAFETY_ARMED
        if ap.mode in (FlightMode.OFFBOARD, FlightMode.AUTO_LAND):
            base |= M.MAV_MODE_FLAG_AUTO_ENABLED | M.MAV_MODE_FLAG_GUIDED_ENABLED
        if ap.mode is not FlightMode.ACRO:
            base |= M.MAV_MODE_FLAG_STABILIZE_ENABLED
        mav_type = (M.MAV_TYPE_HEXAROTOR if self.vehicle.airframe.n_motors == 6
                    else M.MAV_TYPE_QUADROTOR)
        state = M.MAV_STATE_ACTIVE if ap.armed else M.MAV_STATE_STANDBY
        self.mav.heartbeat_send(mav_type, M.MAV_AUTOPILOT_PX4, base, ap.mode.custom_mode, state)

    def _send_stream(self, mid: int, t: float) -> None:
        ph = self.vehicle.physics
        att, posv = ph.meas_att, ph.meas_posv
        ms = int(t * 1000.0 + 0.5)
        yaw = (att[2] + math.pi) % (2 * math.pi) - math.pi
        if mid == M.MAVLINK_MSG_ID_ATTITUDE:
            self.mav.attitude_send(ms, att[0], att[1], yaw, att[3], att[4], att[5])
            if self.stream_log is not None:
                self.stream_log.append((time.monotonic(), t))
        elif mid == M.MAVLINK_MSG_ID_ATTITUDE_QUATERNION:
            q = quat_from_euler(att[0], att[1], yaw)
            self.mav.attitude_quaternion_send(ms, *q, att[3], att[4], att[5])
        elif mid == M.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
            self.mav.local_position_ned_send(ms, *posv)
        elif mid == M.MAVLINK_MSG_ID_HIGHRES_IMU:
            self.mav.highres_imu_send(int(t * 1e6), att[6], att[7], att[8], att[3], att[4],
                                      att[5], 0.0, 0.0, 0.0, 1013.25, 0.0, -posv[2], 20.0,
                                      0b111111)
        elif mid == M.MAVLINK_MSG_ID_SYS_STATUS:
            sensors = (M.MAV_SYS_STATUS_SENSOR_3D_GYRO | M.MAV_SYS_STATUS_SENSOR_3D_ACCEL
                       | M.MAV_SYS_STATUS_SENSOR_3D_MAG | M.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE)
            self.mav.sys_status_send(sensors, sensors, sensors, 100, 16000, -1, 100,
                                     0, 0, 0, 0, 0, 0)
        elif mid == M.MAVLINK_MSG_ID_ATTITUDE_TARGET:
            ap = self.vehicle.autopilot
            self.mav.attitude_target_send(ms, 0b0000_0111, [float(v) for v in ap.attitude_sp],
                                          0.0, 0.0, 0.0, float(ap._sp_att[1]))
        elif mid == M.MAVLINK_MSG_ID_EXTENDED_SYS_STATE:
            landed = (M.MAV_LANDED_STATE_ON_GROUND if self.vehicle.autopilot.landed
                      else M.MAV_LANDED_STATE_IN_AIR)
            self.mav.extended_sys_state_send(M.MAV_VTOL_STATE_UNDEFINED, landed)

    def _link_due(self, t: float) -> None:
        """Deliver what the delayed link has carried by simulated time ``t``."""
        self._writer.flush(t)
        while self._inbox and self._inbox[0][0] <= t + 1e-9:
            msg = self._inbox.popleft()[1]
            try:
                self._dispatch(msg)
            except Exception:  # as in _parse: never stop the vehicle
                self.stats.rejected += 1

    def _send_events(self) -> None:
        for ev in self.vehicle.autopilot.drain_events():
            self.mav.statustext_send(ev.severity, ev.text.encode()[:50])

    def _param_value(self, name: str) -> None:
        prm = self.vehicle.autopilot.params
        self.mav.param_value_send(name.encode(), prm[name], M.MAV_PARAM_TYPE_REAL32,
                                  len(prm.names), prm.index(name))

    def _ack(self, command: int, result: CommandResult, msg: Any) -> None:
        self.mav.command_ack_send(command, int(result), 0, 0, msg.get_srcSystem(),
                                  msg.get_srcComponent())

    # ------------------------------------------------------------ receiving
    def _receive(self) -> None:
        for _ in range(256):  # bounded: never starve the physics
            try:
                data, _addr = self.sock.recvfrom(4096)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                continue  # e.g. ICMP port unreachable from an earlier send
            self._parse(data)

    def _parse(self, data: bytes) -> None:
        mav = self.mav
        try:
            msgs = mav.parse_buffer(data) or []
        except Exception:  # malformed frame, bad CRC, bad signature
            msgs = []
            self.stats.rejected += 1
        # one datagram carries whole frames: never let a truncated tail poison the next one
        mav.buf = bytearray()
        mav.buf_index = 0
        mav.expected_length = M.HEADER_LEN_V1 + 2
        for msg in msgs:
            if msg.get_type() == "BAD_DATA":
                self.stats.rejected += 1
                continue
            self.stats.received += 1
            if self.link_delay_s > 0:
                self._inbox.append((self.vehicle.time_s + self.link_delay_s, msg))
                continue
            try:
                self._dispatch(msg)
            except Exception:  # a message we cannot interpret must not stop the vehicle
                self.stats.rejected += 1

    def _for_us(self, msg: Any) -> bool:
        ts = getattr(msg, "target_system", 0)
        tc = getattr(msg, "target_component", 0)
        return ts in (0, 1) and tc in (0, 1)

    def _dispatch(self, msg: Any) -> None:
        kind = msg.get_type()
        ap = self.vehicle.autopilot
        if kind in ("COMMAND_LONG", "COMMAND_INT"):
            if self._for_us(msg):
                self._command(msg)
        elif kind == "SET_ACTUATOR_CONTROL_TARGET":
            c = msg.controls
            ok = (msg.group_mlx == 0 and self._for_us(msg)
                  and ap.set_actuator_controls(c[0], c[1], c[2], c[3]))
            if not ok:
                self.stats.rejected += 1
        elif kind == "SET_ATTITUDE_TARGET":
            ignore_att = msg.type_mask & M.ATTITUDE_TARGET_TYPEMASK_ATTITUDE_IGNORE
            ok = (self._for_us(msg) and not ignore_att
                  and ap.set_attitude_target(tuple(msg.q), msg.thrust))
            if not ok:
                self.stats.rejected += 1
        elif kind == "SET_MODE":
            if msg.target_system in (0, 1):
                cm = int(msg.custom_mode)
                mode = FlightMode.from_px4((cm >> 16) & 0xFF, (cm >> 24) & 0xFF)
                if mode is not None:
                    ap.set_mode(mode)
        elif kind == "TIMESYNC":
            if msg.tc1 == 0:  # a request: answered at once with the vehicle's clock, as PX4 does
                self.mav.timesync_send(int(self.vehicle.time_s * 1e9), msg.ts1)
        elif kind == "PARAM_REQUEST_LIST":
            if self._for_us(msg):
                for name in ap.params.names:
                    self._param_value(name)
        elif kind == "PARAM_REQUEST_READ":
            if self._for_us(msg):
                idx = int(msg.param_index)
                names = ap.params.names
                if idx >= 0:
                    if idx < len(names):
                        self._param_value(names[idx])
                else:
                    name = _param_name(msg.param_id)
                    if name in ap.params:
                        self._param_value(name)
        elif kind == "PARAM_SET":
            if self._for_us(msg):
                name = _param_name(msg.param_id)
                if name in ap.params:
                    value = float(msg.param_value)
                    if not ap.params.set(name, value):
                        ap._event(4, f"param {name}: rejected value {value}")
                    self._param_value(name)  # new value, or the unchanged one if rejected
                else:
                    ap._event(4, f"unknown parameter {name[:30]}")

    def _command(self, msg: Any) -> None:
        cmd = int(msg.command)
        p = [float(getattr(msg, f"param{i}")) for i in range(1, 5)]
        self.stats.commands[cmd] = self.stats.commands.get(cmd, 0) + 1
        ap = self.vehicle.autopilot
        if cmd == M.MAV_CMD_COMPONENT_ARM_DISARM:
            res = ap.arm(p[0] > 0.5, force=abs(p[1] - _FORCE_DISARM) < 0.5)
        elif cmd == M.MAV_CMD_DO_SET_MODE:
            res = CommandResult.UNSUPPORTED
            if int(p[0]) & M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
                mode = FlightMode.from_px4(int(p[1]), int(p[2]))
                if mode is not None:
                    res = ap.set_mode(mode)
        elif cmd == M.MAV_CMD_NAV_LAND:
            res = ap.land()
        elif cmd == M.MAV_CMD_SET_MESSAGE_INTERVAL:
            res = self._set_interval(int(p[0]), p[1])
        elif cmd in (M.MAV_CMD_REQUEST_MESSAGE, M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES):
            want = int(p[0]) if cmd == M.MAV_CMD_REQUEST_MESSAGE else 148
            res = CommandResult.ACCEPTED
            self._ack(cmd, res, msg)
            if want == M.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
                self._autopilot_version()
            elif want in self._interval:
                self._send_stream(want, self.vehicle.time_s)
            elif want == M.MAVLINK_MSG_ID_HEARTBEAT:
                self._heartbeat()
            return
        else:
            res = CommandResult.UNSUPPORTED
        self._ack(cmd, res, msg)

    def _set_interval(self, mid: int, interval_us: float) -> CommandResult:
        if mid not in self._interval or not math.isfinite(interval_us):
            return CommandResult.DENIED if math.isfinite(interval_us) else CommandResult.FAILED
        if interval_us < 0:
            self._interval[mid] = 0.0
        elif interval_us == 0:
            hz = min(DEFAULT_STREAM_HZ[mid], self.max_stream_hz)
            self._interval[mid] = 1.0 / hz if hz > 0 else 0.0
        else:
            self._interval[mid] = max(interval_us * 1e-6, 1.0 / self.max_stream_hz)
        t = self.vehicle.time_s
        self._due[mid] = t
        self._next_any = min(self._next_any, t)
        return CommandResult.ACCEPTED

    def _autopilot_version(self) -> None:
        caps = (M.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | M.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
                | M.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                | M.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
                | _CAPABILITY_SET_ACTUATOR_TARGET)
        self.mav.autopilot_version_send(caps, (1 << 24) | (13 << 16) | (0xFF), 0, 0, 0,
                                        [0] * 8, [0] * 8, [0] * 8, 0, 0, 1)


#: MAV_PROTOCOL_CAPABILITY_SET_ACTUATOR_TARGET (256): the torque path's message, as PX4 up to
#: 1.13 announced it; newer pymavlink dialects no longer name it
_CAPABILITY_SET_ACTUATOR_TARGET = getattr(M, "MAV_PROTOCOL_CAPABILITY_SET_ACTUATOR_TARGET", 256)


def _param_name(raw: object) -> str:
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", errors="replace")
    return str(raw).split("\x00", 1)[0].strip()
