"""Where the tuning sequence's samples come from and its set points go: one interface.

:class:`VehicleSource` is what :class:`~mrft_gcs.flight.driver.SequenceDriver` runs the
sequence over. Three implementations answer it:

- :class:`LiveVehicle` (here): the MAVLink link (:class:`~mrft_gcs.link.VehicleLink`) and
  its 250 Hz set-point stream. The stream runs from the moment the source opens (PX4 wants
  set points before OFFBOARD) and sends, on every tick, either what ``on_tick`` returns for
  the newest state (a live tune: the sequence steps on the stream's own thread) or the last
  set point given to :meth:`~LiveVehicle.send`. :meth:`~LiveVehicle.next_state` waits for the
  next tick's state (None when none came within ``timeout_s``); modes and arming wait for the
  vehicle's acknowledgement and raise :class:`~mrft_gcs.errors.LinkError` when refused. The
  clock is the ground station's monotonic clock since the source opened.
- :class:`~mrft_gcs.sitl.lockstep.LockstepVehicle`: the in-process simulated vehicle stepped
  in simulated time, one ground-station tick per :meth:`next_state`, with an optional model
  of the ground station's link (telemetry rate and delay, command delay) and of its stalls.
  Every command (set points, modes, arming) reaches the vehicle after the command delay;
  a refused set point is ignored by the vehicle, as an autopilot does. The clock is the
  simulated time.
- :class:`ReplayVehicle` (here): a recorded session (:mod:`mrft_gcs.logs`) played back tick
  by tick: the states the ground station saw, in the order it saw them. Commands are
  accepted and ignored (the log already holds what the vehicle did); :meth:`applied`
  reports the logged command that answered the current state. At the end of the log
  :meth:`next_state` raises :class:`~mrft_gcs.telemetry.EndOfStream`. The clock is the
  vehicle clock of the newest sample (never going back).

All three: states are finite; ``close()`` may be called any number of times, and after it
``next_state`` returns None (live, simulated) or raises ``EndOfStream`` (replay).
"""

from __future__ import annotations

import enum
import math
import threading
import time
from collections.abc import Callable
from typing import Protocol, runtime_checkable

import numpy as np

from mrft_gcs.flight.controllers import FlightState
from mrft_gcs.link import SetpointStreamer, VehicleLink
from mrft_gcs.logs import DecodedLog
from mrft_gcs.telemetry import (
    ActuatorTarget,
    Attitude,
    AttitudeTarget,
    EndOfStream,
    LocalPosition,
    RateTarget,
)

__all__ = [
    "VehicleMode",
    "Setpoint",
    "VehicleSource",
    "LinkTelemetry",
    "LiveVehicle",
    "ReplayVehicle",
    "idle_setpoint",
    "state_time_s",
]

#: what the ground station sends (a rate set point: the rate path's torques as rates)
Setpoint = ActuatorTarget | AttitudeTarget | RateTarget


class VehicleMode(enum.Enum):
    """The flight modes a tune asks for (the value names the profile's ``[modes]`` entry)."""

    OFFBOARD = "offboard"
    POSITION = "position"
    LAND = "land"


def idle_setpoint(attitude_path: bool) -> Setpoint:
    """Zero torque or a level attitude, both at zero thrust: what goes out on the ground."""
    if attitude_path:
        return AttitudeTarget(0.0, (1.0, 0.0, 0.0, 0.0), 0.0)
    return ActuatorTarget(0.0, 0.0, 0.0, 0.0, 0.0)


def state_time_s(s: FlightState) -> float:
    """The vehicle time of a state: its newer sample (s)."""
    return max(s.t_att_s, s.t_pos_s)


@runtime_checkable
class VehicleSource(Protocol):
    """Samples in, set points and modes out (see the module docstring for each source).

    ``time_s`` is monotonic; ``next_state`` returns the state of the next ground-station
    tick (None: no complete state yet), or raises
    :class:`~mrft_gcs.telemetry.EndOfStream` where the source is finite; ``applied``
    is the set point the vehicle last acted on (a replay: the logged one), None before
    any.
    """

    @property
    def time_s(self) -> float: ...

    def next_state(self, timeout_s: float = 1.0) -> FlightState | None: ...

    def send(self, setpoint: Setpoint) -> None: ...

    def set_mode(self, mode: VehicleMode) -> None: ...

    def arm(self) -> None: ...

    def applied(self) -> Setpoint | None: ...

    def close(self) -> None: ...


class LinkTelemetry:
    """Latest ATTITUDE and LOCAL_POSITION_NED, drained from the link on the stream's ticks."""

    def __init__(self, link: VehicleLink) -> None:
        self.link = link
        self.att: Attitude | None = None
        self.pos: LocalPosition | None = None

    def poll(self) -> FlightState | None:
        """Drain the link's queue (on the stream's ticks only) and return the latest state."""
        while (smp := self.link.next_sample(0.0)) is not None:
            if isinstance(smp, Attitude):
                self.att = smp
            elif isinstance(smp, LocalPosition):
                self.pos = smp
        return self.latest()

    def latest(self) -> FlightState | None:
        """The latest state without draining (safe from any thread)."""
        a, p = self.att, self.pos
        if a is None or p is None:
            return None
        return FlightState(a.t_s, a.roll_rad, a.pitch_rad, a.yaw_rad, a.rollspeed_rad_s,
                           a.pitchspeed_rad_s, a.yawspeed_rad_s, p.t_s, p.x_m, p.y_m, -p.z_m,
                           p.vx_m_s, p.vy_m_s, -p.vz_m_s)


class LiveVehicle:
    """The live link as a :class:`VehicleSource` (module docstring: its semantics).

    Parameters
    ----------
    link : VehicleLink
        Connected; its ``modes`` name the custom modes of :class:`VehicleMode`.
    rate_hz : float
        Set-point stream rate (Hz).
    on_tick : callable, optional
        ``f(state or None) -> set point or None``, called on every stream tick with the
        newest state (the per-tick part of a tune); without it each tick sends the last
        set point given to :meth:`send` (nothing before the first).
    """

    def __init__(self, link: VehicleLink, rate_hz: float = 250.0,
                 on_tick: Callable[[FlightState | None], Setpoint | None] | None = None) -> None:
        self.link = link
        self.telemetry = LinkTelemetry(link)
        self._on_tick = on_tick
        self._sp: Setpoint | None = None
        self._applied: Setpoint | None = None
        self._ticks = 0
        self._tick_seen = threading.Condition()
        self._closed = False
        self._t0 = time.monotonic()
        #: held from reading telemetry to sending the answer (the link's, so that the
        #: session log shows the samples each command answered before it, and no other)
        self._order: threading.Lock = getattr(link, "order_lock", None) or threading.Lock()
        link.drain()
        self.streamer = SetpointStreamer(_InOrder(link, self._order), self._make,
                                         rate_hz=rate_hz)
        self.streamer.start()

    def _make(self, _t: float) -> Setpoint | None:
        self._order.acquire()  # released once the answer is sent (_InOrder), or here
        try:
            s = self.telemetry.poll()
            out = self._on_tick(s) if self._on_tick is not None else self._sp
        except BaseException:
            self._order.release()
            raise
        if out is None:
            self._order.release()
        self._applied = out if out is not None else self._applied
        with self._tick_seen:
            self._ticks += 1
            self._tick_seen.notify_all()
        return out

    @property
    def time_s(self) -> float:
        return time.monotonic() - self._t0

    def next_state(self, timeout_s: float = 1.0) -> FlightState | None:
        """The newest state after the next stream tick (None: no tick or no state in time,
        or the source is closed)."""
        with self._tick_seen:
            n = self._ticks
            if not self._tick_seen.wait_for(lambda: self._ticks > n or self._closed,
                                            timeout=timeout_s) or self._closed:
                return None
        return self.telemetry.latest()

    def send(self, setpoint: Setpoint) -> None:
        """The set point every tick sends from now on (ignored where ``on_tick`` is given)."""
        self._sp = setpoint

    def set_mode(self, mode: VehicleMode) -> None:
        if mode is VehicleMode.LAND:
            self.link.land()
        else:
            self.link.set_mode(self.link.modes[mode.value])

    def arm(self) -> None:
        self.link.arm()

    def applied(self) -> Setpoint | None:
        return self._applied

    def close(self) -> None:
        """Stop the stream (the link stays open: its owner closes it)."""
        self.streamer.stop()
        with self._tick_seen:
            self._closed = True
            self._tick_seen.notify_all()


class _InOrder:
    """The link as the stream's sink: sending a set point releases the order lock that
    :meth:`LiveVehicle._make` took before reading the telemetry it answers."""

    def __init__(self, link: VehicleLink, lock: threading.Lock) -> None:
        self.link, self.lock = link, lock

    def send_setpoint(self, target: Setpoint) -> None:
        try:
            self.link.send_setpoint(target)
        finally:
            self.lock.release()

    def telemetry_age_s(self) -> float:
        return self.link.telemetry_age_s()

    def land(self, *, wait_ack: bool = True, timeout_s: float = 1.0) -> None:
        self.link.land(wait_ack=wait_ack, timeout_s=timeout_s)


def _last_before(order: np.ndarray, at: np.ndarray) -> np.ndarray:
    """For each position ``at``, the index of the last ``order`` entry before it (-1: none);
    ``order`` sorted ascending."""
    return np.searchsorted(order, at, side="left") - 1


class ReplayVehicle:
    """A recorded session as a :class:`VehicleSource` (module docstring: its semantics).

    Ticks: where the log keeps the order of both directions (a .tlog), one per logged
    command, with the newest ATTITUDE and LOCAL_POSITION_NED logged before it: the state
    the ground station answered (exactly so for logs of :class:`LiveVehicle`, which logs
    nothing received between reading telemetry and sending the answer; in older logs a
    sample received meanwhile makes a state one sample newer now and then). Else one per
    ATTITUDE sample, with the newest position and command up to its time.

    Parameters
    ----------
    decoded : DecodedLog
        A log decoded by :func:`mrft_gcs.logs.decode_log`.
    """

    def __init__(self, decoded: DecodedLog) -> None:
        d = decoded.cleaned()
        self.source = d.source
        att, pos = d.attitude, d.position
        cmds, kind = ((d.actuator, "actuator") if len(d.actuator) >= len(d.attitude_target)
                      else (d.attitude_target, "attitude_target"))
        self._cmds, self._cmd_kind = cmds, kind
        fo = d.file_order
        if len(cmds) and all(k in fo for k in ("attitude", "position", kind)):
            # each table sorted by where it was logged, then each command's newest samples
            ia, ip, ic = (np.argsort(fo[k], kind="stable") for k in ("attitude", "position",
                                                                     kind))
            at = fo[kind][ic]
            ra = _last_before(fo["attitude"][ia], at)
            rp = _last_before(fo["position"][ip], at)
            ok = (ra >= 0) & (rp >= 0)
            self._att_rows = ia[ra[ok]]
            self._pos_rows = ip[rp[ok]]
            self._cmd_rows = ic[ok]
        else:
            self._att_rows = np.arange(len(att))
            self._pos_rows = np.searchsorted(pos[:, 0], att[:, 0], side="right") - 1
            self._cmd_rows = (np.searchsorted(cmds[:, 0], att[:, 0], side="right") - 1
                              if len(cmds) else np.full(len(att), -1))
            keep = self._pos_rows >= 0
            self._att_rows, self._pos_rows = self._att_rows[keep], self._pos_rows[keep]
            self._cmd_rows = self._cmd_rows[keep]
        self._att, self._pos = att, pos
        self._i = -1
        self._t = -math.inf
        self._closed = False

    def __len__(self) -> int:
        return len(self._att_rows)

    def _state(self, i: int) -> FlightState:
        a, p = self._att[self._att_rows[i]], self._pos[self._pos_rows[i]]
        return FlightState(float(a[0]), float(a[1]), float(a[2]), float(a[3]), float(a[4]),
                           float(a[5]), float(a[6]), float(p[0]), float(p[1]), float(p[2]),
                           -float(p[3]), float(p[4]), float(p[5]), -float(p[6]))

    def _command(self, i: int) -> Setpoint | None:
        r = int(self._cmd_rows[i])
        if r < 0:
            return None
        row = self._cmds[r]
        if self._cmd_kind == "actuator":
            return ActuatorTarget(*(float(v) for v in row))
        return AttitudeTarget(float(row[0]), tuple(float(v) for v in row[1:5]),  # type: ignore[arg-type]
                              float(row[5]))

    def takeoff_tick(self) -> int | None:
        """Index of the first tick whose logged command has thrust: the session's first
        take-off command (a live tune started the sequence on the tick before); None
        where the log has none."""
        for i in range(len(self)):
            c = self._command(i)
            if c is not None and c.thrust > 0:
                return i
        return None

    @property
    def time_s(self) -> float:
        return self._t

    def next_state(self, timeout_s: float = 1.0) -> FlightState:
        """The next tick's state; :class:`EndOfStream` after the last (``timeout_s`` unused:
        a log never waits)."""
        if self._closed or self._i + 1 >= len(self):
            raise EndOfStream(self.source)
        self._i += 1
        s = self._state(self._i)
        self._t = max(self._t, state_time_s(s))
        return s

    def send(self, setpoint: Setpoint) -> None:
        """Accepted and ignored: the log holds what the vehicle was sent."""

    def set_mode(self, mode: VehicleMode) -> None:
        """Accepted and ignored."""

    def arm(self) -> None:
        """Accepted and ignored."""

    def applied(self) -> Setpoint | None:
        """The logged command that answered the current state (None before the first)."""
        return self._command(self._i) if self._i >= 0 else None

    def close(self) -> None:
        self._closed = True
