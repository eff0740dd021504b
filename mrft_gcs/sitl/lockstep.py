"""The in-process simulated vehicle as a vehicle source, stepped in lockstep with the tune.

:class:`LockstepVehicle` answers :class:`~mrft_gcs.flight.source.VehicleSource` over a
:class:`~mrft_gcs.sitl.SimVehicle` in simulated time: each :meth:`~LockstepVehicle.next_state`
steps the vehicle to the ground station's next tick (1 ms physics steps) and returns the
state it has then. Deterministic given the vehicle's seed and the commands.

Optional models of what lies between the ground station and a real vehicle:

- :class:`GcsLink`: telemetry at the vehicle's rate, each frame held a link delay on its way
  down, commands held as long on their way up, and the ground station's tick at a phase of
  its own (what the population benchmark flies);
- a command delay alone (the sample is fresh; the answer lands some ms later);
- stalls: now and then the ground station misses ticks, and the vehicle keeps the last
  set point meanwhile, as an autopilot does (:class:`PeriodicStalls`, or any
  ``f(time_s) -> extra physics steps``).

:func:`truth_identifier` is a test double for the identification: it ignores the cycles
and returns the airframe's true linear model with its optimal PD, so the sequence and the
write-back can be tested apart from the classifiers.
"""

from __future__ import annotations

import collections
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mrft_gcs.flight.controllers import FlightState
from mrft_gcs.flight.scoring import true_response
from mrft_gcs.flight.source import Setpoint, VehicleMode
from mrft_gcs.identify import Identification, RelaySettings
from mrft_gcs.loops import Loop, LoopKind
from mrft_gcs.pd_design import optimal_pd
from mrft_gcs.plant import InnerModel, SideModel
from mrft_gcs.sitl.airframe import load_airframe
from mrft_gcs.sitl.onboard import FlightMode
from mrft_gcs.sitl.vehicle import SimVehicle
from mrft_gcs.telemetry import ActuatorTarget, AttitudeTarget

__all__ = ["GcsLink", "LockstepVehicle", "PeriodicStalls", "state_of", "true_tilt_deg",
           "truth_identifier", "TRUTH_RELAYS"]

_MODES = {VehicleMode.OFFBOARD: FlightMode.OFFBOARD, VehicleMode.POSITION: FlightMode.POSCTL}


def state_of(v: SimVehicle) -> FlightState:
    """The vehicle's measured state now (what its telemetry would carry)."""
    a, p = v.physics.meas_att, v.physics.meas_posv
    t = v.time_s
    return FlightState(t, a[0], a[1], a[2], a[3], a[4], a[5], t, p[0], p[1], -p[2], p[3], p[4],
                       -p[5])


def true_tilt_deg(v: SimVehicle) -> float:
    """The vehicle's true tilt (deg), not the measured one."""
    r, p, _ = v.physics.euler
    return math.degrees(math.acos(max(-1.0, min(1.0, math.cos(r) * math.cos(p)))))


@dataclass(frozen=True)
class GcsLink:
    """The ground station's link: telemetry every ``1 / telemetry_hz`` s, each frame and
    each command held ``delay_s`` on its way; the first tick at ``phase_s``."""

    delay_s: float
    telemetry_hz: float
    phase_s: float = 0.0


class PeriodicStalls:
    """Stalls of up to ``ms`` (uniform 50-100 % of it) about every ``every_s`` (50-150 % of
    it), drawn from ``rng``: ``f(time_s) -> extra physics steps`` before the next tick."""

    def __init__(self, ms: float, every_s: float, rng: np.random.Generator,
                 tick_steps: int = 4) -> None:
        self.ms, self.every_s, self.rng, self.tick_steps = ms, every_s, rng, tick_steps
        self.next_s = every_s

    def __call__(self, t_s: float) -> int:
        if t_s <= self.next_s:
            return 0
        n = self.tick_steps
        steps = n * max(1, int(self.ms / n * self.rng.uniform(0.5, 1.0)))
        self.next_s = t_s + self.every_s * self.rng.uniform(0.5, 1.5)
        return steps - n


class LockstepVehicle:
    """A :class:`SimVehicle` as a :class:`~mrft_gcs.flight.source.VehicleSource`.

    Parameters
    ----------
    vehicle : SimVehicle
        Stepped by this source only.
    rate_hz : float
        The ground station's tick rate (Hz).
    link : GcsLink, optional
        Delayed telemetry and commands (see the module docstring); without it each tick's
        state is the vehicle's measurement at the tick, and commands take
        ``command_delay_s``.
    command_delay_s : float
        Without ``link``: how long after the tick a command acts (s).
    stalls : callable, optional
        ``f(time_s) -> int``: extra physics steps before the next tick (0: on time).
    """

    def __init__(self, vehicle: SimVehicle, rate_hz: float = 250.0, *,
                 link: GcsLink | None = None, command_delay_s: float = 0.0,
                 stalls: Callable[[float], int] | None = None) -> None:
        self.v = vehicle
        self.link = link
        self.period_s = 1.0 / rate_hz
        self.command_delay_s = link.delay_s if link is not None else command_delay_s
        self.stalls = stalls
        self.next_tick = vehicle.time_s + (link.phase_s if link is not None else 0.0)
        self.tel_period = 1.0 / link.telemetry_hz if link is not None else math.nan
        self.next_tel = vehicle.time_s
        self.tel_q: collections.deque = collections.deque()  # (arrival, FlightState)
        self.cmd_q: collections.deque = collections.deque()  # (arrival, callable)
        self.latest: FlightState | None = None
        #: when the newest delivered sample was taken (the link model: arrival) (s)
        self.latest_arrival = math.nan
        #: largest true tilt seen (deg)
        self.max_tilt = 0.0
        self._applied: Setpoint | None = None
        self._closed = False

    @property
    def time_s(self) -> float:
        return self.v.time_s

    def _command(self, fn: Callable[[], object]) -> None:
        self.cmd_q.append((self.v.time_s + self.command_delay_s, fn))

    def next_state(self, timeout_s: float = 1.0) -> FlightState | None:
        """Step to the next tick; the newest state delivered by then (None: none yet, or
        the source is closed)."""
        if self._closed:
            return None
        v = self.v
        if self.stalls is not None:
            self.next_tick += self.stalls(v.time_s) * v.dt
        while v.time_s < self.next_tick - 1e-9:
            while self.cmd_q and self.cmd_q[0][0] <= v.time_s + 1e-9:
                self.cmd_q.popleft()[1]()
            if self.link is not None and v.time_s >= self.next_tel - 1e-9:
                ph = v.physics
                self.tel_q.append((v.time_s + self.link.delay_s, _state(v.time_s, ph.meas_att,
                                                                        ph.meas_posv)))
                self.next_tel += self.tel_period
            v.step()
            self.max_tilt = max(self.max_tilt, true_tilt_deg(v))
        if self.link is None:
            self.latest, self.latest_arrival = state_of(v), v.time_s
        while self.tel_q and self.tel_q[0][0] <= v.time_s + 1e-9:
            self.latest_arrival, self.latest = self.tel_q.popleft()
        self.next_tick += self.period_s
        return self.latest

    def send(self, setpoint: Setpoint) -> None:
        """The set point acts after the command delay (the vehicle ignores an invalid one)."""
        ap = self.v.autopilot

        def act(sp: Setpoint = setpoint) -> None:
            if isinstance(sp, AttitudeTarget):
                ok = ap.set_attitude_target(sp.q_wxyz, sp.thrust)
            elif isinstance(sp, ActuatorTarget):
                ok = ap.set_actuator_controls(sp.roll, sp.pitch, sp.yaw, sp.thrust)
            else:  # no rate set points here (the bundled SITL's PX4 1.13 takes torques)
                ok = False
            if ok:
                self._applied = sp

        self._command(act)

    def set_mode(self, mode: VehicleMode) -> None:
        ap = self.v.autopilot
        if mode is VehicleMode.LAND:
            self._command(ap.land)
        else:
            fm = _MODES[mode]
            self._command(lambda: ap.set_mode(fm))

    def arm(self) -> None:
        self._command(lambda: self.v.autopilot.arm(True))

    def applied(self) -> Setpoint | None:
        return self._applied

    def close(self) -> None:
        self._closed = True


def _state(t: float, att, posv) -> FlightState:
    return FlightState(t, att[0], att[1], att[2], att[3], att[4], att[5], t, posv[0], posv[1],
                       -posv[2], posv[3], posv[4], -posv[5])


#: Relay settings to fly with :func:`truth_identifier` (which ignores the cycles): the
#: bundled classifiers' beta, so such a flight has the cycles a real tune flies.
TRUTH_RELAYS = {LoopKind.ATTITUDE: RelaySettings(beta=-0.7, h=0.05),
                LoopKind.ALTITUDE: RelaySettings(beta=-0.7, h=0.10746),
                LoopKind.SIDE: RelaySettings(beta=-0.7, h=0.08)}


def truth_identifier(vehicle: str):
    """``f(loop, snapshot, inner) -> Identification`` from the airframe's true models.

    A test double, not a classifier: it ignores the cycles (their period and amplitude go
    into the result as measured) and returns the true linear model with its optimal PD.
    """
    models = load_airframe(vehicle).linear_models()

    def ident(loop: Loop, snap, inner: Identification | None = None) -> Identification:
        m = models[loop.value]
        if loop in (Loop.X, Loop.Y):
            G, w = true_response(models, loop, inner.gains if inner else None)
            model: InnerModel | SideModel = SideModel(m["K"], m["T2"], m["tau"])
            kind = LoopKind.SIDE
        else:
            G, w = true_response(models, loop)
            model = InnerModel(m["K"], m["T_prop"], m["T1"], m["tau"])
            kind = LoopKind.ATTITUDE if loop in (Loop.ROLL, Loop.PITCH) else LoopKind.ALTITUDE
        pd = optimal_pd(G, w).pd
        return Identification(kind, model, 0, 1.0, snap.beta, snap.h, snap.status.period_s,
                              snap.status.amplitude, pd)

    return ident

