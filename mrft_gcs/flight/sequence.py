"""The tuning sequence as a state machine (paper section "Takeoff and Full System Identification").

Phases (:class:`Phase`): ``PREFLIGHT`` -> ``TAKEOFF`` (PI on altitude, eq. 21) ->
``INNER_MRFT`` (MRFT on altitude, roll and pitch at once; the bounding relay of
eq. 22 on x/y gives the attitude set points) -> ``SIDE_MRFT`` (once roll and pitch
are identified: MRFT on x and y through the GCS attitude PDs) -> ``HOVER`` (every
loop on its identified PD) -> ``DONE``; ``LANDING``/``ABORTED`` on a safety stop.

:class:`TuningSequence` owns no I/O and no identification: its :meth:`~TuningSequence.step`
turns the latest :class:`~mrft_gcs.flight.controllers.FlightState` into a setpoint
(called on each setpoint-stream tick at 250 Hz), :meth:`~TuningSequence.ready`
hands the steady cycles to whoever identifies them (the tuning API, on its own
thread) and :meth:`~TuningSequence.apply` switches a loop to its PD at once.

Axes: x and y are the forward and right axes of the heading at take-off (north and
east for a take-off facing north): positions and velocities are rotated into that
frame as they come in. x is driven by ``-pitch``, y by ``+roll``; the x and y relays
and PDs output that tilt command in rad, exactly the ``u`` that the side-motion
identification expects, and it is rotated onto roll and pitch by the *measured*
heading's departure from the take-off heading, so a yaw drift during the tests
(the attitude relays turn the heading by a few degrees) does not couple the two side
tests.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import threading
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from mrft_gcs.features import crosses_setpoint, rising_switches
from mrft_gcs.flight.config import SequenceConfig
from mrft_gcs.flight.controllers import FlightState, PDLoop, YawHold, catch_pd, wrap_pi
from mrft_gcs.flight.cycles import CycleRules, CycleWatcher
from mrft_gcs.flight.noise import ComplementaryFilter, NoiseEstimator
from mrft_gcs.flight.takeoff import TakeoffController
from mrft_gcs.identify import CycleDetector, CycleStatus, Identification, RelaySettings
from mrft_gcs.loops import INNER_LOOPS, SIDE_LOOPS, Loop
from mrft_gcs.profiles import Actuation
from mrft_gcs.relay import MRFT, BoundingRelay
from mrft_gcs.telemetry import ActuatorTarget, AttitudeTarget

__all__ = [
    "Phase",
    "LoopState",
    "LoopTest",
    "CycleSnapshot",
    "SequenceConfig",
    "TuningSequence",
    "quat_from_euler",
    "AUTOPILOT_ATTITUDE",
]

_NAN = float("nan")
#: why roll and pitch are left alone on the attitude path (the report's note)
AUTOPILOT_ATTITUDE = ("attitude path: the autopilot keeps its own attitude loop "
                      "(SET_ATTITUDE_TARGET), so roll and pitch are not tested or written")
_TILT_SAMPLES = 30_000  # 30 s of ATTITUDE at 1 kHz: as long as the cycle detector keeps
#: the attitude loop behind each side loop (x north: -pitch, y east: +roll)
SIDE_INNER = {Loop.X: Loop.PITCH, Loop.Y: Loop.ROLL}


class Phase(enum.Enum):
    """Where the tuning sequence stands."""

    PREFLIGHT = "preflight"
    TAKEOFF = "take-off"
    INNER_MRFT = "inner MRFT"
    SIDE_MRFT = "side MRFT"
    HOVER = "hover"
    LANDING = "landing"
    DONE = "done"
    ABORTED = "aborted"


class LoopState(enum.Enum):
    """One loop's progress."""

    WAITING = "waiting"
    RELAY = "oscillating"
    IDENTIFYING = "identifying"
    TUNED = "tuned"
    LEFT_ALONE = "left alone"


@dataclass(frozen=True)
class CycleSnapshot:
    """The steady relay cycles handed to identification (arrays of shape (m,))."""

    loop: Loop
    t_s: np.ndarray
    u: np.ndarray
    y: np.ndarray
    beta: float
    h: float
    bias: float
    status: CycleStatus
    #: the relay's set point in the units of ``y`` (altitude, x, y: the point the relay
    #: oscillates about); None for roll and pitch, whose set point moves with the bounding
    #: relay. Identification refuses cycles that do not cross it every half-cycle.
    setpoint: float | None = None
    #: x and y: the measured tilt along the axis (rad, the sign of ``u``: x ``-pitch``, y
    #: ``+roll`` in the take-off heading frame) from ATTITUDE, interpolated onto ``t_s``:
    #: with ``u`` it measures the closed attitude loop the side relay drove (attitude path)
    tilt: np.ndarray | None = None


@dataclass
class LoopTest:
    """Mutable per-loop state of the sequence (read by displays under the sequence lock)."""

    loop: Loop
    state: LoopState = LoopState.WAITING
    beta: float = _NAN
    h: float = _NAN
    bias: float = 0.0
    relay: MRFT | None = None
    #: the relay's cycles: when they are steady, which to identify (:mod:`.cycles`)
    watch: CycleWatcher = field(default_factory=lambda: CycleWatcher(CycleRules()))
    pd: PDLoop | None = None
    identification: Identification | None = None
    snapshot: CycleSnapshot | None = None
    t_relay_start_s: float = _NAN
    t_tuned_s: float = _NAN
    note: str = ""
    u: float = 0.0
    band: float = _NAN
    ext: float = 0.0  # extreme error since the relay's last switch
    unarmed: int = 0  # switches made before the threshold could arm (relay too small)
    raises: int = 0  # times the relay amplitude was raised
    switches: int = 0  # relay switches since the relay (re)started
    center: float = 0.0  # side relays: the position the relay oscillates about (m)
    settling: bool = False  # side relays: bringing the axis to rest before the relay starts
    presettle: bool = False  # side loops: held at rest while waiting for the altitude test
    #: side relays: (t_att_s, measured tilt along the axis) while the relay runs
    tilt: deque = field(default_factory=lambda: deque(maxlen=_TILT_SAMPLES))
    #: roll/pitch: the last steady-looking cycle's (period s, amplitude rad), and the
    #: damping PD (Kc, Kd) that holds the axis while a run-away is caught (None: relay)
    cycle: tuple[float, float] = (_NAN, _NAN)
    catch: tuple[float, float] | None = None
    #: roll/pitch: the amplitude the relay takes once its first period is measured and
    #: whether that is done; (t, u, y, rate) since the relay's first switch (its periods run
    #: from one turn of the axis to the next the same way); the turns seen in it; the
    #: measured swing per unit of h (rad); times resized; the catch hands back inside this
    #: share of the cycle's envelope (a resized relay restarts nearly at rest)
    h_goal: float = _NAN
    sized: bool = True
    probe: list = field(default_factory=list)
    turns: list = field(default_factory=list)
    turn_sign: float = 0.0
    probe_switches: int = 0
    pushed_away: int = 0  # roll/pitch: times the relay was turned round early (see _attitude)
    from_rest: bool = False  # roll/pitch: the relay restarted at rest after it was resized
    amp_per_h: float = _NAN
    resizes: int = 0
    catch_release: float = 1.0
    t_catch_s: float = _NAN
    bias_votes: list = field(default_factory=list)  # mean torque of the last periods
    #: roll/pitch before the first period: (t, relay state, de/dt)
    probe_rate: deque = field(default_factory=lambda: deque(maxlen=400))

    @property
    def status(self) -> CycleStatus:
        """What the cycle watcher has seen of the relay's cycles."""
        return self.watch.status

    @status.setter
    def status(self, value: CycleStatus) -> None:
        self.watch.status = value

    @property
    def detector(self) -> CycleDetector:
        """The cycle watcher's detector."""
        return self.watch.detector

    @detector.setter
    def detector(self, value: CycleDetector) -> None:
        self.watch.detector = value

    def restart_detection(self) -> None:
        """Forget the cycles seen so far: the relay starts over."""
        self.watch.restart()


def quat_from_euler(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """ZYX Euler angles (rad) to a unit quaternion ``(w, x, y, z)``."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy)


class TuningSequence:
    """State machine of one tune: call :meth:`start`, then :meth:`step` at every tick.

    Parameters
    ----------
    config : SequenceConfig
    attitude_relay, altitude_relay : RelaySettings
        MRFT beta and h for roll/pitch (normalised torque) and altitude (normalised thrust).
    """

    def __init__(self, config: SequenceConfig, attitude_relay: RelaySettings,
                 altitude_relay: RelaySettings) -> None:
        self.config = config
        self.attitude_relay = attitude_relay
        self.altitude_relay = altitude_relay
        self._lock = threading.RLock()
        self.reset()

    # ------------------------------------------------------------------ lifecycle
    def reset(self) -> None:
        cfg = self.config
        self.phase = Phase.PREFLIGHT
        self.loops: dict[Loop, LoopTest] = {
            lp: LoopTest(lp, watch=CycleWatcher(cfg.cycle_rules(lp))) for lp in Loop}
        self.yaw = YawHold()
        self.bounding = BoundingRelay(cfg.takeoff.eps1_m, cfg.takeoff.eps2_m,
                                      cfg.takeoff.h_o1_rad, cfg.takeoff.h_o2_rad, n=2)
        u_init = 0.0 if cfg.hover_thrust_guess is None else 0.9 * cfg.hover_thrust_guess
        self.takeoff = TakeoffController(cfg.z_ref_m, cfg.takeoff, beta=self.altitude_relay.beta,
                                         u_init=u_init, h_alt=self.altitude_relay.h,
                                         relay_bias=cfg.hover_thrust_guess)
        self.origin = (0.0, 0.0, 0.0)
        self.yaw_ref = 0.0
        self.t_start_s = _NAN
        self.t_last_tuned_s = _NAN
        self.state: FlightState | None = None
        self.tilt_cmd = (0.0, 0.0)  # (roll_ref, pitch_ref), rad
        self._t_att_prev = self._t_pos_prev = -math.inf
        self.att_noise = NoiseEstimator(4)  # roll, pitch (rad), their rates (rad/s)
        self.lifted = False  # the attitude relays run (lift-off seen)
        self._liftoff: tuple[float, ...] | None = None  # ground roll, pitch; thresholds
        self.pos_noise = NoiseEstimator(3)  # x, y (filtered), z up (m)
        self.xy_filter = (ComplementaryFilter(cfg.side_filter_k),
                          ComplementaryFilter(cfg.side_filter_k))
        self.z_filter = ComplementaryFilter(cfg.side_filter_k)
        self.xy_f = (0.0, 0.0)
        self.z_f = 0.0
        self.events: list[str] = []  # for the report's notes (relay amplitude raised...)
        #: largest tilt seen in each phase (deg, by :class:`Phase` value), for the report
        self.max_tilt_by_phase: dict[str, float] = {}
        alt = self.loops[Loop.ALTITUDE]
        alt.beta, alt.h = self.altitude_relay.beta, self.altitude_relay.h
        for lp in (Loop.ROLL, Loop.PITCH):
            t = self.loops[lp]
            t.beta = self.attitude_relay.beta
            t.h_goal = max(self.attitude_relay.h, cfg.h_att_min)
            t.h, t.sized = min(t.h_goal, cfg.h_att_start), False
            if cfg.actuation is Actuation.ATTITUDE:
                t.state = LoopState.LEFT_ALONE
                t.note = AUTOPILOT_ATTITUDE

    def _heading_frame(self, s: FlightState) -> FlightState:
        """``s`` with x, y and their velocities along the take-off heading's forward/right."""
        if self.yaw_ref == 0.0:
            return s
        c, n = math.cos(self.yaw_ref), math.sin(self.yaw_ref)
        return dataclasses.replace(s, x_m=c * s.x_m + n * s.y_m, y_m=c * s.y_m - n * s.x_m,
                                   vx_m_s=c * s.vx_m_s + n * s.vy_m_s,
                                   vy_m_s=c * s.vy_m_s - n * s.vx_m_s)

    def observe(self, s: FlightState) -> None:
        """A sample on the ground before the take-off command: measures the signals' noise."""
        with self._lock:
            if self.phase is Phase.PREFLIGHT:
                self.yaw_ref = s.yaw_rad  # the heading the side axes will follow
                s = self._heading_frame(s)
                self._filter_xy(s)
                self.att_noise.update(s.t_att_s, (s.roll_rad, s.pitch_rad, s.p_rad_s,
                                                  s.q_rad_s))
                self.pos_noise.update(s.t_pos_s, (*self.xy_f, self.z_f))

    def _filter_xy(self, s: FlightState) -> None:
        fx, fy = self.xy_filter
        self.xy_f = (fx.update(s.t_pos_s, s.x_m, s.vx_m_s), fy.update(s.t_pos_s, s.y_m, s.vy_m_s))
        self.z_f = self.z_filter.update(s.t_pos_s, s.z_up_m, s.vz_up_m_s)

    def noise_band(self, loop: Loop) -> float:
        """Relay noise band of ``loop`` (its units): ``noise_band_sigmas`` x measured noise."""
        cfg = self.config
        if loop in (Loop.ROLL, Loop.PITCH):
            sig, default = self.att_noise.sigma()[0 if loop is Loop.ROLL else 1], \
                cfg.relay_band_att_rad
        else:
            i = {Loop.X: 0, Loop.Y: 1, Loop.ALTITUDE: 2}[loop]
            sig, default = self.pos_noise.sigma()[i], cfg.relay_band_pos_m
        return float(cfg.noise_band_sigmas * sig) if np.isfinite(sig) else default

    def start(self, s: FlightState) -> None:
        """Take-off command: remember the take-off point and heading, enter TAKEOFF."""
        with self._lock:
            self.yaw_ref = s.yaw_rad
            s = self._heading_frame(s)
            self.origin = (s.x_m, s.y_m, s.z_up_m)
            self.t_start_s = max(s.t_att_s, s.t_pos_s)
            self.state = s
            self.phase = Phase.TAKEOFF
            alt = self.loops[Loop.ALTITUDE]
            alt.state, alt.t_relay_start_s = LoopState.RELAY, self.t_start_s
            alt.band = self.takeoff.band_m = self.noise_band(Loop.ALTITUDE)
            self._liftoff = self._liftoff_thresholds(s)

    def _liftoff_thresholds(self, s: FlightState) -> tuple[float, ...]:
        """(ground roll, ground pitch, angle threshold roll, pitch, rate threshold p, q)."""
        cfg = self.config
        sig = self.att_noise.sigma()
        if self.att_noise.samples >= 8:
            r0, p0 = np.mean(np.asarray(self.att_noise.v)[:, :2], axis=0)
        else:
            r0, p0 = s.roll_rad, s.pitch_rad
        rates = [max(cfg.liftoff_rate_floor_rad_s, cfg.liftoff_rate_sigmas * x)
                 if np.isfinite(x) else cfg.liftoff_rate_floor_rad_s for x in sig[2:]]
        return (float(r0), float(p0), self.noise_band(Loop.ROLL), self.noise_band(Loop.PITCH),
                *rates)

    def _lifted_off(self, s: FlightState, z: float) -> bool:
        """The vehicle has left the ground: altitude, or roll/pitch off their ground values."""
        if self.lifted or z > self.config.airborne_m or self.takeoff.switched:
            return True
        guess = self.config.hover_thrust_guess
        if self._liftoff is None or self.loops[Loop.ALTITUDE].u < (
                self.config.liftoff_thrust_share * guess if guess else 0.1):
            return False  # no thrust to leave the ground with: vibration, not lift-off
        r0, p0, br, bp, wp, wq = self._liftoff
        return (abs(s.roll_rad - r0) > br or abs(s.pitch_rad - p0) > bp
                or abs(s.p_rad_s) > wp or abs(s.q_rad_s) > wq)

    def leave_alone(self, loop: Loop, why: str) -> None:
        """Give up on a loop (it keeps what it had) and say why in the report."""
        with self._lock:
            t = self.loops[loop]
            t.state, t.note, t.relay = LoopState.LEFT_ALONE, why, None

    # ------------------------------------------------------------------ queries
    @property
    def inner_done(self) -> bool:
        return all(self.loops[lp].state in (LoopState.TUNED, LoopState.LEFT_ALONE)
                   for lp in (Loop.ROLL, Loop.PITCH))

    @property
    def all_done(self) -> bool:
        return all(t.state in (LoopState.TUNED, LoopState.LEFT_ALONE) for t in self.loops.values())

    def side_ready(self) -> list[Loop]:
        """Side loops not started, once both attitude loops are done.

        Altitude must be done too: its relay swings the thrust by +-h (about a quarter of
        hover), which modulates the horizontal force of a tilt and breaks the side cycles.
        Scaling the tilt commands by hover / thrust does not undo it (it lags by the
        attitude loop's response).
        """
        done = (LoopState.TUNED, LoopState.LEFT_ALONE)
        if self.loops[Loop.ALTITUDE].state not in done:
            return []
        if not self.inner_done:
            # both attitude loops first: a side relay tilts its axis, which can throw the
            # other attitude loop's relay, still running, into a slow drifting cycle
            return []
        return [lp for lp in SIDE_INNER if self.loops[lp].state is LoopState.WAITING]

    @property
    def side_waiting(self) -> bool:
        """A side loop can start (its attitude loop is done): its relay settings are due."""
        return bool(self.side_ready())

    @property
    def duration_s(self) -> float:
        """Vehicle seconds from the take-off command to the last gains applied (NaN before)."""
        return self.t_last_tuned_s - self.t_start_s

    def elapsed_s(self) -> float:
        s = self.state
        if s is None or not math.isfinite(self.t_start_s):
            return 0.0
        return max(s.t_att_s, s.t_pos_s) - self.t_start_s

    def relay_age_s(self, loop: Loop) -> float:
        """Seconds the loop's relay has run (NaN if not running)."""
        t = self.loops[loop]
        if t.state not in (LoopState.RELAY, LoopState.IDENTIFYING) or self.state is None:
            return _NAN
        return max(self.state.t_att_s, self.state.t_pos_s) - t.t_relay_start_s

    # ------------------------------------------------------------------ main-thread hooks
    def ready(self) -> list[CycleSnapshot]:
        """Loops whose oscillation became steady since the last call (now IDENTIFYING)."""
        out = []
        with self._lock:
            for t in self.loops.values():
                if t.state is LoopState.RELAY and t.status.steady:
                    sigma = t.band / self.config.noise_band_sigmas
                    if (sigma > self.config.max_noise_ratio * t.status.amplitude
                            and self._raise_h(t, sigma / (0.7 * self.config.max_noise_ratio
                                                          * t.status.amplitude))):
                        continue  # started over on the larger amplitude
                    if sigma > self.config.max_noise_ratio * t.status.amplitude:
                        # at its largest amplitude a noisy cycle is identified as it is:
                        # waiting would only end in the "no steady oscillation" error
                        self.events.append(
                            f"{t.loop.value}: noise {100 * sigma / t.status.amplitude:.1f} % of "
                            f"the cycle amplitude with the relay at its largest amplitude "
                            f"({t.h:.3g}); identified as it is")
                    cycles = t.watch.cycles()
                    if cycles is None:
                        continue
                    ts, u, y = cycles
                    t.state = LoopState.IDENTIFYING
                    sp = (t.center if t.loop in SIDE_LOOPS else self.takeoff.z_relay_m
                          if t.loop is Loop.ALTITUDE else None)
                    t.snapshot = CycleSnapshot(t.loop, ts, u, y, t.beta, t.h, t.bias, t.status,
                                               sp, self._tilt_on(t, ts))
                    out.append(t.snapshot)
        return out

    @staticmethod
    def _tilt_on(t: LoopTest, ts: np.ndarray) -> np.ndarray | None:
        """The side axis' measured tilt at the times ``ts`` (None if it does not cover them)."""
        if t.loop not in SIDE_LOOPS or len(t.tilt) < 2:
            return None
        tt, tv = np.array(t.tilt).T
        if tt[0] > ts[0] + 0.02 or tt[-1] < ts[-1] - 0.02:  # ATTITUDE and LOCAL_POSITION_NED
            return None  # samples need not coincide, but must cover the cycles
        return np.interp(ts, tt, tv)

    def _h_max(self, loop: Loop) -> float:
        if loop is Loop.ALTITUDE:
            # the thrust must stay clear of zero: u = bias -+ h
            bias = self.loops[Loop.ALTITUDE].bias
            cap = 0.8 * bias if 0 < bias < 1 else self.config.h_max[1]
            return min(self.config.h_max[1], cap)
        return self.config.h_max[0 if loop in (Loop.ROLL, Loop.PITCH) else 2]

    def _raise_h(self, t: LoopTest, factor: float) -> bool:
        """Raise a relay's amplitude (the oscillation is too small for the noise); start over.

        False if it is already as large as it may be (nothing changed).
        """
        relay = self.takeoff.relay if t.loop is Loop.ALTITUDE else t.relay
        h = min(self._h_max(t.loop), t.h * max(factor, self.config.h_raise))
        if math.isfinite(t.amp_per_h) and t.amp_per_h > 0:
            # roll/pitch: not past what swings the axis 1.5 x att_amp_max_rad (its measured
            # swing per unit h), as when it was sized
            h = min(h, 1.5 * self.config.att_amp_max_rad / t.amp_per_h)
        if relay is None or h <= t.h * 1.01:
            return False
        self.events.append(f"{t.loop.value}: relay amplitude raised from {t.h:.3g} to {h:.3g} "
                           f"(cycle too small for the measured noise)")
        t.h = h
        relay.h[:] = h
        if t.loop is Loop.ALTITUDE:
            self.takeoff.h = h
        t.raises += 1
        t.unarmed = t.switches = 0
        t.probe, t.turns, t.turn_sign = [], [], 0.0  # roll/pitch sizing: periods at this h
        t.restart_detection()
        return True

    def _watch(self, t: LoopTest, relay: MRFT, e: float, state_before: float,
               e_rate: float = 0.0) -> None:
        """After a relay step: two switches in a row before the threshold armed raise h.

        A runaway (the error beyond ``runaway_factor`` cycle amplitudes while the relay
        pushes it further out, e.g. after a noise-triggered switch-back, or, once cycles were
        measured, while it still grows: ``e`` and ``e_rate`` of one sign) hands roll and
        pitch to a damping PD until they are back inside their cycle, and restarts the
        others as a plain sign relay, which at once pushes back; the detector starts over.
        A roll/pitch swing still carrying out counts by where it will stop, not where it
        is (``SequenceConfig.catch_torque_factor``).
        """
        st = float(relay.state[0])
        amp = t.status.amplitude
        if not math.isfinite(amp) and t.loop in (Loop.ROLL, Loop.PITCH):
            # just restarted (detector reset): the cycle seen before the run-away still
            # sizes the limit; with the bare floor the relay's own start-up swing would be
            # caught as a run-away again and again
            amp = t.cycle[1]
        floor = self.config.runaway_floor[0 if t.loop in (Loop.ROLL, Loop.PITCH) else
                                          1 if t.loop is Loop.ALTITUDE else 2]
        if not math.isfinite(amp) and t.loop in (Loop.ROLL, Loop.PITCH):
            floor = max(floor, self.config.runaway_floor_startup_rad)
        limit = max(floor, self.config.runaway_factor * amp) if math.isfinite(amp) else floor
        if t.loop in (Loop.ROLL, Loop.PITCH):
            # a disturbed cycle inflates its own amplitude: never let the limit pass the
            # largest tilt the tests command (20 deg), well inside the 35 deg safety limit
            limit = min(limit, self.config.max_tilt_cmd_rad)
        # u pushes y away, or y still moves away (``e_rate``: de/dt, roll and pitch) although
        # u pushes back: GCS stalls can lock a relay into a slow, large mode that swings out
        # on its momentum while u pushes back all along, then drives the return at full h
        # into as large a swing the other way; the damping PD brings the return swing to
        # rest instead. Only once the detector has measured cycles since the relay
        # (re)started, as its own start-up swing also carries past 3 amplitudes while it
        # pushes back (or once a resized roll/pitch relay restarted at rest: its cycle is
        # known, and its start-up swing is no larger)
        outward = e * e_rate > 0 and (math.isfinite(t.status.amplitude) or t.from_rest)
        reach = abs(e)
        if outward and t.loop in (Loop.ROLL, Loop.PITCH):
            per, a = t.cycle if math.isfinite(t.cycle[0]) else (t.status.period_s,
                                                                   t.status.amplitude)
            if math.isfinite(per) and per > 0 and a > 0:  # where the swing will stop
                w0 = 2 * math.pi / per
                reach += e_rate ** 2 / (2 * math.pi * a * w0 ** 2 / 4)
        if reach > limit and (st * e < 0 or outward):
            relay.reset()
            t.from_rest = False
            if (t.loop in (Loop.ROLL, Loop.PITCH) and not math.isfinite(t.cycle[0])
                    and math.isfinite(t.status.period_s) and t.status.amplitude > 0):
                # no settled cycle yet: the last complete one still sizes a damping PD (a
                # sign relay restarted at the run-away's error swings further out)
                t.cycle = (t.status.period_s, t.status.amplitude)
            if t.loop in (Loop.ROLL, Loop.PITCH) and math.isfinite(t.cycle[0]):
                # A relay is no stabilising controller: restarted after a disturbance (a
                # GCS stall holding one relay level) it feeds each swing into a larger one.
                # A damping PD from the relay's own cycle brings the axis back first.
                t.catch = catch_pd(t.h, *t.cycle)
                self.events.append(f"{t.loop.value}: relay paused, a damping PD caught the "
                                   f"run-away (error {e:+.3g})")
            elif t.loop is Loop.ALTITUDE and self.takeoff.resettle():
                self.events.append(f"altitude: relay stopped (error {e:+.3g} ran away); it "
                                   f"starts again once the climb controller holds the set point")
            else:
                relay.step(e)
                self.events.append(f"{t.loop.value}: relay restarted (error {e:+.3g} ran away)")
            t.unarmed = t.switches = 0
            t.ext = 0.0
            t.restart_detection()
            return
        if state_before != 0 and st != state_before:
            t.switches += 1
            if t.switches > 2 and abs(t.ext) * (1 + t.beta) <= t.band:
                t.unarmed += 1
                if t.unarmed >= 2:
                    self._raise_h(t, self.config.h_raise)
            else:
                t.unarmed = 0
            t.ext = 0.0
        elif st > 0:
            t.ext = max(t.ext, e)
        else:
            t.ext = min(t.ext, e)

    def retry(self, loop: Loop, restart: bool = False) -> None:
        """Identification failed on this cycle: keep the relay going and wait for the next.

        ``restart``: the cycles were not a proper MRFT oscillation (a slow, lopsided mode
        the relay can lock into); the relay starts over, x and y after settling again.
        """
        with self._lock:
            t = self.loops[loop]
            if t.state is LoopState.IDENTIFYING:
                t.state = LoopState.RELAY
                t.restart_detection()
                relay = self.takeoff.relay if loop is Loop.ALTITUDE else t.relay
                if restart and relay is not None:
                    # altitude climbs back to its set point first, biased at the mean
                    # thrust of the refused cycles; the others restart where they are
                    mean_u = float(np.mean(t.snapshot.u)) if t.snapshot is not None else None
                    if not (loop is Loop.ALTITUDE and self.takeoff.resettle(hover=mean_u)):
                        relay.reset()
                    t.unarmed = t.switches = 0
                    t.ext = 0.0
                    if loop in SIDE_LOOPS:
                        t.settling = True
                        if self.state is not None:
                            t.t_relay_start_s = self.state.t_pos_s

    def apply(self, loop: Loop, ident: Identification) -> None:
        """Switch ``loop`` from its relay to the identified PD, from the next tick on."""
        with self._lock:
            t = self.loops[loop]
            snap = t.snapshot
            trim = float(np.mean(snap.u)) if snap is not None and snap.u.size else t.bias
            if loop in SIDE_LOOPS:
                trim = 0.0  # no constant tilt is needed to hold position
            lim = self.config.max_tilt_cmd_rad
            lo, hi = {Loop.ALTITUDE: (0.0, 1.0), Loop.X: (-lim, lim),
                      Loop.Y: (-lim, lim)}.get(loop, (-1.0, 1.0))
            k = self.config.gcs_attitude_pd_scale if loop in (Loop.ROLL, Loop.PITCH) else 1.0
            t.pd = PDLoop(k * ident.gains.Kc, k * ident.gains.Kd, trim, lo, hi)
            t.identification = ident
            t.relay = None
            t.state = LoopState.TUNED
            now = self.state
            t.t_tuned_s = max(now.t_att_s, now.t_pos_s) if now is not None else _NAN
            self.t_last_tuned_s = t.t_tuned_s
            self._advance()

    def start_side(self, settings: dict[Loop, RelaySettings]) -> None:
        """Start the x/y relays (beta from the side-motion domain of each attitude class).

        Each axis starts as soon as its own attitude loop is done (x: pitch, y: roll);
        settings for an axis that is not ready yet are ignored.
        """
        with self._lock:
            now = self.state
            ready = self.side_ready()
            for lp, rs in settings.items():
                t = self.loops[lp]
                if lp not in ready:
                    continue
                t.beta, t.h = rs.beta, max(rs.h, self.config.h_side_min)
                t.band = self.noise_band(lp)
                t.relay = MRFT(t.beta, t.h, band=t.band)
                t.state = LoopState.RELAY
                t.settling = True
                t.center = self.xy_f[0 if lp is Loop.X else 1]
                t.t_relay_start_s = max(now.t_att_s, now.t_pos_s) if now else _NAN
            self._advance()

    def finish(self, phase: Phase = Phase.DONE) -> None:
        with self._lock:
            self.phase = phase

    def _advance(self) -> None:
        if self.phase in (Phase.DONE, Phase.ABORTED, Phase.LANDING, Phase.PREFLIGHT):
            return
        if self.all_done:
            self.phase = Phase.HOVER
        elif any(self.loops[lp].state in (LoopState.RELAY, LoopState.IDENTIFYING)
                 for lp in SIDE_LOOPS):
            self.phase = Phase.SIDE_MRFT

    # ------------------------------------------------------------------ the tick
    def step(self, s: FlightState) -> ActuatorTarget | AttitudeTarget:
        """Setpoint for the latest state (torque path: ActuatorTarget; attitude: AttitudeTarget)."""
        with self._lock:
            s = self._heading_frame(s)
            self.state = s
            cfg = self.config
            tilt = math.degrees(s.tilt_rad)
            if tilt > self.max_tilt_by_phase.get(self.phase.value, -1.0):
                self.max_tilt_by_phase[self.phase.value] = tilt
            z = s.z_up_m - self.origin[2]
            new_att = s.t_att_s > self._t_att_prev
            new_pos = s.t_pos_s > self._t_pos_prev
            self._t_att_prev, self._t_pos_prev = s.t_att_s, s.t_pos_s
            if new_pos:
                self._filter_xy(s)
            thrust = self._altitude(s, z, new_pos)
            if self.phase is Phase.TAKEOFF and self.takeoff.switched:
                self.phase = Phase.INNER_MRFT
            ux, uy = self._side(s, new_pos)
            # onto the body axes by the measured heading (PX4's position controller does the
            # same): a yaw drift must not turn the x test's tilt into y motion
            d = wrap_pi(s.yaw_rad - self.yaw_ref)
            c, n = math.cos(d), math.sin(d)
            if new_att:  # the measured tilt along each axis, back through the same rotation
                for lp, tilt in ((Loop.X, c * -s.pitch_rad - n * s.roll_rad),
                                 (Loop.Y, c * s.roll_rad - n * s.pitch_rad)):
                    t = self.loops[lp]
                    if t.relay is not None and not t.settling:
                        t.tilt.append((s.t_att_s, tilt))
            lim = cfg.max_tilt_cmd_rad
            roll_ref = min(lim, max(-lim, c * uy - n * ux))
            pitch_ref = min(lim, max(-lim, -(c * ux + n * uy)))
            self.tilt_cmd = (roll_ref, pitch_ref)
            if cfg.actuation is Actuation.ATTITUDE:
                q = quat_from_euler(roll_ref, pitch_ref, self.yaw_ref)
                return AttitudeTarget(s.t_att_s, q, thrust)
            self.lifted = airborne = self._lifted_off(s, z)
            roll = self._attitude(Loop.ROLL, roll_ref, s.roll_rad, s.p_rad_s, s.t_att_s,
                                  new_att, airborne)
            pitch = self._attitude(Loop.PITCH, pitch_ref, s.pitch_rad, s.q_rad_s, s.t_att_s,
                                   new_att, airborne)
            yaw = self.yaw.step(self.yaw_ref, s.yaw_rad, s.r_rad_s) if airborne else 0.0
            return ActuatorTarget(s.t_att_s, roll, pitch, yaw, thrust)

    @staticmethod
    def _feed(t: LoopTest, t_s: float, u: float, y: float, new: bool) -> None:
        # one watcher sample per telemetry sample (ticks between samples repeat the state)
        if new and t.state in (LoopState.RELAY, LoopState.IDENTIFYING):
            t.watch.update(t_s, u, y)

    def _altitude(self, s: FlightState, z: float, new: bool) -> float:
        t = self.loops[Loop.ALTITUDE]
        if self.phase is Phase.PREFLIGHT:
            return 0.0
        if t.pd is not None:
            # where its relay oscillated (the climb may have come to rest under z_ref_m): a
            # step would disturb the x/y tests that start now
            u = t.pd.step(self.takeoff.z_relay_m, z, s.vz_up_m_s)
        else:
            relay = self.takeoff.relay
            before = float(relay.state[0]) if relay is not None else 0.0
            zf = self.z_f - self.origin[2]  # smoothed with the climb rate, as x and y
            self.takeoff.no_brake = self.config.brake_after_attitude and not self.inner_done
            u = self.takeoff.step(s.t_pos_s, zf, s.vz_up_m_s)
            if self.takeoff.switched:
                t.bias = self.takeoff.u_z0
                if relay is not None:
                    self._watch(t, relay, self.takeoff.z_relay_m - zf, before)
                cycles = t.status.cycles
                self._feed(t, s.t_pos_s, u, zf, new)
                if t.status.cycles > cycles and self._lopsided(t):
                    self.takeoff.resettle(hover=float(np.mean(t.watch.last_cycles(2)[1])))
                    self.events.append(
                        "altitude: two relay cycles in a row did not cross the set point (a "
                        "lopsided cycle); the relay starts again once the climb controller "
                        "holds the set point")
                    t.restart_detection()
        t.u = u
        return u

    def _lopsided(self, t: LoopTest) -> bool:
        """The altitude relay's last two cycles both miss the set point in a half-cycle.

        Identification would refuse them (:func:`~mrft_gcs.features.cycle_features`); seen
        at once, the relay is started over from the set point instead of waiting for three
        steady cycles of a slow (0.9 s) lopsided mode first.
        """
        if t.state is not LoopState.RELAY or t.status.cycles < 2:
            return False
        _, u, y = t.watch.last_cycles(2)
        if u.size < 8:
            return False
        high = u > 0.5 * (u.max() + u.min())
        rises = np.concatenate([[0], rising_switches(u)])  # the window opens on a rise
        falls = np.flatnonzero(high[:-1] & ~high[1:]) + 1
        e = self.takeoff.z_relay_m - y
        if len(rises) != 3:
            return False
        for a, b in zip(rises[:-1], rises[1:], strict=True):
            f = falls[(falls > a) & (falls < b)]
            if f.size != 1 or crosses_setpoint(e, a, f[0], b):
                return False
        return True

    def _side(self, s: FlightState, new: bool) -> tuple[float, float]:
        ex = self.origin[0] - s.x_m
        ey = self.origin[1] - s.y_m
        tx, ty = self.loops[Loop.X], self.loops[Loop.Y]
        xf, yf = self.xy_f
        bb = (0.0, 0.0)
        held = (LoopState.WAITING, LoopState.LEFT_ALONE)  # no test of their own (yet)
        if tx.state in held or ty.state in held:
            # the bounding relay keeps an axis near the take-off point until its test starts
            b2 = self.bounding.step(np.array([ex, ey]))
            bb = (float(b2[0]), float(b2[1]))
        out = []
        for t, pos, vel, o, pf, b in ((tx, s.x_m, s.vx_m_s, self.origin[0], xf, bb[0]),
                                      (ty, s.y_m, s.vy_m_s, self.origin[1], yf, bb[1])):
            if t.state in held and self._attitude_ready(t.loop):
                # its attitude loop is tuned: bring the axis to rest already (the soft settle
                # PD about where it was then), so that its relay can start as soon as the
                # altitude test ends instead of settling only then; an axis left alone
                # (not requested) is held there for the rest of the tune
                if not t.presettle:
                    t.presettle, t.center = True, pf
                u = self._settle(t.center - pf, vel)
            elif t.state in held:
                u = b
            elif t.pd is not None:
                # hold where the relay oscillated: a step back to the take-off point would
                # disturb the other axis while its test still runs
                u = t.pd.step(t.center if t.identification is not None else o, pos, vel)
            elif t.relay is not None and t.settling:
                u = self._settle(t.center - pf, vel)
                if (abs(vel) < self.config.settle_speed_m_s or
                        s.t_pos_s - t.t_relay_start_s > self.config.settle_max_s):
                    t.settling, t.center = False, pf
            elif t.relay is not None:
                before = float(t.relay.state[0])
                u = float(t.relay.step(t.center - pf)[0])
                self._watch(t, t.relay, t.center - pf, before)
                self._feed(t, s.t_pos_s, u, pf, new)
            else:
                u = 0.0
            t.u = u
            out.append(u)
        return out[0], out[1]

    def _attitude_ready(self, loop: Loop) -> bool:
        """The attitude loop behind side ``loop`` can take a position PD's tilt commands.

        Torque path: once the GCS runs its identified PD. Attitude path: the autopilot's
        own loop is there from the start, but the bounding relay (eq. 22) keeps the axis
        until the altitude test is over, as on the torque path.
        """
        if self.config.actuation is Actuation.ATTITUDE:
            return self.loops[Loop.ALTITUDE].state in (LoopState.TUNED, LoopState.LEFT_ALONE)
        return self.loops[SIDE_INNER[loop]].pd is not None

    def _settle(self, e: float, vel: float) -> float:
        """The soft PD that brings a side axis to rest (tilt command, rad, clipped)."""
        kp, kd = self.config.settle_pd
        lim = self.config.settle_max_tilt_rad
        return min(lim, max(-lim, kp * e - kd * vel))

    def _attitude(self, loop: Loop, ref: float, y: float, rate: float, t_s: float, new: bool,
                  airborne: bool) -> float:
        t = self.loops[loop]
        if t.pd is not None:
            u = t.pd.step(ref, y, rate)
        elif not airborne:
            u = 0.0
        else:
            if t.state is LoopState.WAITING:
                t.band = self.noise_band(loop)
                t.relay = MRFT(t.beta, t.h, band=t.band)
                t.state, t.t_relay_start_s = LoopState.RELAY, t_s
            assert t.relay is not None
            if t.catch is not None:
                # back to the relay once inside its own cycle's envelope (angle and rate)
                period, amp = t.cycle
                if t_s - t.t_catch_s < 3 * period:  # a resized relay: at rest first
                    amp *= t.catch_release
                e = ref - y
                if abs(e) < amp and abs(rate) < 2 * math.pi * amp / period:
                    t.from_rest = t.catch_release < 1.0
                    t.catch, t.catch_release = None, 1.0
                else:
                    kc, kd = t.catch
                    lim = self.config.catch_torque_factor * t.h
                    # about the relay's bias: the torque that holds the axis (a CoM offset)
                    u = t.bias + min(lim, max(-lim, kc * e - kd * rate))
                    t.u = u
                    return u
            before = float(t.relay.state[0])
            u = float(t.relay.step(ref - y)[0])
            self._watch(t, t.relay, ref - y, before, -rate)
            if t.relay is not None and self._drives_away(t, ref - y, -rate):
                # the MRFT's lead braked a return swing short of its set point (too little
                # swing to arm the switch: a torque bias, an agile vehicle at its first h)
                # and now pushes the axis away from it, which tilts a light vehicle far
                # over. The relay is turned round at once, this point its new extreme
                e = ref - y
                r = t.relay
                r.state[:] = 1.0 if e >= 0 else -1.0
                r.ext[:] = r.entry[:] = e
                r.first[:] = False
                r.switches += 1
                u = float(r.bias[0] + r.h[0] * r.state[0])
                t.pushed_away += 1
            self._feed(t, t_s, u, y, new)
            if new and t.relay is not None:
                self._size_attitude_relay(t, t_s, u, y, ref - y, -rate)
            st = t.status
            if (st.cycles >= 2 and st.spread < 0.15 and math.isfinite(st.period_s)
                    and st.amplitude > 0):
                t.cycle = (st.period_s, st.amplitude)
        t.u = u
        return u

    def _size_attitude_relay(self, t: LoopTest, t_s: float, u: float, y: float, e: float,
                             e_rate: float) -> None:
        """Roll/pitch relay sizing, on each new attitude sample while the relay runs.

        The first period (``h_att_start``) sets h and the bias; later periods resize a relay
        whose swing passes 1.25 x ``att_amp_max_rad`` (a first period from rest can fall
        short of the steady cycle) or whose mean torque moved off its bias by
        ``att_bias_min`` of h. A period runs from one turn of the axis (rate through zero)
        to the next turn the same way: the rate is zero at both ends, so the mean relay
        output over it is the torque that holds the axis (the plant integrates); from
        switch to switch it is not while the cycle still grows. Before the first period, a
        relay that cannot turn the axis back (a torque bias over h: pushed back, yet
        speeding away beyond ``att_amp_max_rad``) is doubled at once.
        """
        cfg, relay = self.config, t.relay
        assert relay is not None
        st = float(relay.state[0])
        if not t.sized:
            t.probe_rate.append((t_s, st, e_rate))
            # pushed back for long enough to have acted, yet still speeding outward (a normal
            # swing slows down once the push-back acts)
            back = [r for r in t.probe_rate if r[0] >= t_s - cfg.att_bias_window_s]
            if (len(back) >= 3 and back[0][0] <= t_s - 0.9 * cfg.att_bias_window_s
                    and all(r[1] == st for r in back)
                    and abs(e) > cfg.att_amp_max_rad and st * e > 0 and e * e_rate > 0
                    and abs(e_rate) > abs(back[0][2]) and t.h < t.h_goal):
                h = min(t.h_goal, 2.0 * t.h)
                self.events.append(f"{t.loop.value}: relay amplitude raised from {t.h:.3g} to "
                                   f"{h:.3g} (it could not turn the axis back: a torque bias)")
                t.h = h
                relay.h[:] = h
                t.probe, t.turns, t.turn_sign = [], [], 0.0
                t.probe_rate.clear()
                return
        n = int(relay.switches[0])
        if n < t.probe_switches:  # the relay was restarted (a run-away): periods from here
            t.probe, t.turns, t.turn_sign = [], [], 0.0
        t.probe_switches = n
        if n == 0:
            return  # from the relay's first switch on
        rate = -e_rate
        t.probe.append((t_s, u, y, rate))
        thr = self._turn_rate(t.loop)
        if t.turn_sign == 0.0:
            t.turn_sign = math.copysign(1.0, rate) if abs(rate) > thr else 0.0
        elif rate * t.turn_sign < -thr:  # a turn, with hysteresis against gyro noise
            t.turn_sign = -t.turn_sign
            t.turns.append(len(t.probe) - 1)
            if len(t.turns) >= 3:
                self._period_done(t)
            elif not t.sized and len(t.turns) == 2:
                self._first_swing(t)

    def _turn_rate(self, loop: Loop) -> float:
        """Rate (rad/s) the axis must pass the other way for a turn: the lift-off threshold."""
        if self._liftoff is None:
            return self.config.liftoff_rate_floor_rad_s
        return self._liftoff[4 if loop is Loop.ROLL else 5]

    def _drives_away(self, t: LoopTest, e: float, e_rate: float) -> bool:
        """Roll/pitch in its first cycles (until sized and two detector cycles): the relay
        pushes the axis away from its set point while it moves away, beyond twice the noise
        band. In a proper MRFT cycle the relay pushes away only to brake a swing that still
        moves towards the set point."""
        if t.sized and t.status.cycles >= 2 or t.catch is not None or t.relay is None:
            return False
        st = float(t.relay.state[0])
        band = t.band if math.isfinite(t.band) else 0.0
        return (st * e < 0 and e * e_rate > 0 and abs(e) > 2 * band
                and abs(e_rate) > self._turn_rate(t.loop))

    def _first_swing(self, t: LoopTest) -> None:
        """Size at once on the first swing from turn to turn if it passed twice
        ``att_amp_max_rad``: a full first period of a light, agile vehicle at
        ``h_att_start`` would tilt it far over (its bias is measured on later periods)."""
        i, j = t.turns
        seg = np.array(t.probe[i:j + 1])
        amp = 0.5 * float(np.ptp(seg[:, 2]))
        if amp > 2.0 * self.config.att_amp_max_rad:
            t.sized = True
            t.probe_rate.clear()
            t0, t1 = float(seg[0, 0]), float(seg[-1, 0])
            self._resize_attitude_relay(t, np.array([t0, t0 + 2.0 * (t1 - t0)]), amp, t.bias,
                                        "its first swing")

    def _period_done(self, t: LoopTest) -> None:
        """A period from turn to turn is complete: size the relay on it if due."""
        cfg = self.config
        i, j = t.turns[-3], t.turns[-1]
        rec = np.array(t.probe[i:j + 1])
        # keep what the next period needs: from the turn before the last on
        k = t.turns[-2]
        t.probe = t.probe[k:]
        t.turns = [0, j - k]
        if rec.shape[0] < 4:
            return
        ts, us, ys = rec[:, 0], rec[:, 1], rec[:, 2]
        dt = np.diff(ts)
        mean_u = float(np.sum(us[:-1] * dt) / np.sum(dt))
        amp = 0.5 * float(np.ptp(ys))
        if not t.sized:
            t.sized = True
            t.probe_rate.clear()
            self._resize_attitude_relay(t, ts, amp, mean_u, "its first period")
            return
        if t.resizes >= cfg.att_max_resizes or not amp > 0:
            return
        if abs(ys[-1] - ys[0]) > 0.25 * amp:
            t.bias_votes.clear()
            return  # not yet periodic (growing or shrinking): its mean torque is no bias
        t.bias_votes.append(mean_u)
        # a new bias only on two periods in a row that agree (a ground-station stall holds
        # the torque the vehicle gets, not the one recorded: one period can be far off)
        tol = cfg.att_bias_min * t.h
        m = t.bias_votes[-2:]
        off = (len(m) == 2 and abs(m[0] - m[1]) < tol
               and all(abs(x - t.bias) > tol for x in m))
        if amp > 1.25 * cfg.att_amp_max_rad or off:
            self._resize_attitude_relay(t, ts, amp, float(np.mean(m)) if off else t.bias,
                                        "a period")

    def _resize_attitude_relay(self, t: LoopTest, ts: np.ndarray, amp: float, mean_u: float,
                               what: str) -> None:
        """Set roll/pitch's h and bias from one period (its times, swing ``amp`` in rad, mean
        torque): h no larger than swings the axis ``att_amp_max_rad`` (the swing is
        proportional to h), the bias at the mean torque; the relay restarts at rest."""
        cfg, relay = self.config, t.relay
        assert relay is not None
        h0 = t.h
        h = t.h_goal if what.startswith("its first") else h0
        if amp > 0:
            t.amp_per_h = amp / h0
            if t.amp_per_h * h > 1.25 * cfg.att_amp_max_rad:
                # (with a margin: the first period after lift-off is no steady cycle yet and
                # can swing twice as far as the steady one)
                h = cfg.att_amp_max_rad / t.amp_per_h
            # no smaller than the noise needs (the amplitude ``ready`` raises to), within reason
            sigma = t.band / cfg.noise_band_sigmas if math.isfinite(t.band) else 0.0
            h_noise = sigma / (0.7 * cfg.max_noise_ratio * t.amp_per_h)
            h = max(h, min(h_noise, t.h_goal, 1.5 * cfg.att_amp_max_rad / t.amp_per_h))
        h = max(h, cfg.h_att_floor)
        bias = mean_u if (cfg.att_bias_min * min(h, h0) < abs(mean_u - t.bias)
                          and abs(mean_u) <= cfg.att_bias_max) else t.bias
        notes = []
        if abs(h - h0) > 0.01 * h0:
            notes.append(f"amplitude {h0:.3g} -> {h:.3g}")
        if bias != t.bias:
            notes.append(f"bias {t.bias:+.3g} -> {bias:+.3g} (the mean torque)")
        if not notes:
            return
        self.events.append(f"{t.loop.value}: relay sized on {what} ({amp:.3g} rad at h "
                           f"{h0:.3g}): " + ", ".join(notes))
        t.resizes += 1
        t.h, t.bias = h, bias
        relay.h[:] = h
        relay.bias[:] = bias
        t.probe, t.turns, t.turn_sign = [], [], 0.0
        t.bias_votes.clear()
        t.unarmed = t.switches = 0
        t.ext = 0.0
        t.restart_detection()
        if amp > 0:  # the cycle to expect at the new h (sizes the run-away catch)
            t.cycle = (float(ts[-1] - ts[0]), t.amp_per_h * h)
        if amp > 0:
            relay.reset()
            # the relay restarts from rest at its set point: an MRFT (beta -0.7) switched to a
            # smaller h or a new bias mid-swing swung out further or locked into a lopsided
            # cycle that never crossed its set point, a sign relay restarted off its set point
            # swung out to twice the cycle, and a larger h taken mid-swing under stalls
            # tilted the vehicle twice as far as with the restart. A damping PD sized on that
            # cycle brings the axis there first
            t.catch = catch_pd(h, *t.cycle)
            t.catch_release = cfg.att_restart_envelope
            t.t_catch_s = float(ts[-1])

    # ------------------------------------------------------------------ display
    def snapshot(self) -> dict[str, object]:
        """A consistent copy for displays: phase, elapsed, each loop's state/period/amplitude."""
        with self._lock:
            return {
                "phase": self.phase,
                "elapsed_s": self.elapsed_s(),
                "loops": {lp: (t.state, t.status.cycles, t.status.period_s, t.status.amplitude,
                               t.status.steady) for lp, t in self.loops.items()},
            }


INNER = INNER_LOOPS  # re-exported names used by the API
SIDE = SIDE_LOOPS
