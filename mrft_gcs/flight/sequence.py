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

Each phase has its own room in :mod:`mrft_gcs.flight.phases`: lift-off detection
(:mod:`~mrft_gcs.flight.phases.liftoff`), the altitude relay
(:mod:`~mrft_gcs.flight.phases.altitude`), the roll and pitch relays with their sizing
(:mod:`~mrft_gcs.flight.phases.attitude`) and the x/y relays
(:mod:`~mrft_gcs.flight.phases.side`); what they share (settings, per-loop tests, the
take-off controller, ground noise, relay supervision) is :mod:`~mrft_gcs.flight.phases.shared`.
This module composes them: the tick, the hand-over of cycles to identification and back,
and the phase transitions.
"""

from __future__ import annotations

import dataclasses
import math
import threading

import numpy as np

from mrft_gcs.flight.config import SequenceConfig
from mrft_gcs.flight.controllers import FlightState, PDLoop, YawHold, wrap_pi
from mrft_gcs.flight.phases.altitude import AltitudeRelay
from mrft_gcs.flight.phases.attitude import AttitudeRelays
from mrft_gcs.flight.phases.liftoff import LiftoffDetector
from mrft_gcs.flight.phases.shared import Shared
from mrft_gcs.flight.phases.side import SideRelays, tilt_on
from mrft_gcs.flight.phases.state import (
    AUTOPILOT_ATTITUDE,
    SIDE_INNER,
    CycleSnapshot,
    LoopState,
    LoopTest,
    Phase,
)
from mrft_gcs.flight.phases.yaw import YawRelay
from mrft_gcs.flight.takeoff import TakeoffController
from mrft_gcs.identify import Identification, RelaySettings
from mrft_gcs.loops import INNER_LOOPS, SIDE_LOOPS, Loop
from mrft_gcs.profiles import Actuation
from mrft_gcs.telemetry import ActuatorTarget, AttitudeTarget, quat_from_euler

__all__ = [
    "Phase",
    "LoopState",
    "LoopTest",
    "CycleSnapshot",
    "SequenceConfig",
    "TuningSequence",
    "quat_from_euler",
    "AUTOPILOT_ATTITUDE",
    "SIDE_INNER",
]

_NAN = float("nan")


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
        self._config = config
        self.attitude_relay = attitude_relay
        self.altitude_relay = altitude_relay
        self._lock = threading.RLock()
        self.reset()

    # ------------------------------------------------------------------ lifecycle
    def reset(self) -> None:
        cfg = self.config
        self.phase = Phase.PREFLIGHT
        u_init = 0.0 if cfg.hover_thrust_guess is None else 0.9 * cfg.hover_thrust_guess
        takeoff = TakeoffController(cfg.z_ref_m, cfg.takeoff, beta=self.altitude_relay.beta,
                                    u_init=u_init, h_alt=self.altitude_relay.h,
                                    relay_bias=cfg.hover_thrust_guess)
        self.shared = Shared(cfg, takeoff)
        self.liftoff = LiftoffDetector(self.shared)
        self.altitude = AltitudeRelay(self.shared, self.altitude_relay)
        self.attitude = AttitudeRelays(self.shared, self.attitude_relay, self.liftoff)
        self.side = SideRelays(self.shared)
        self.yaw: YawHold | YawRelay = YawHold()
        self.yaw_ref = 0.0
        self.t_start_s = _NAN
        self.t_last_tuned_s = _NAN
        self.state: FlightState | None = None
        self.tilt_cmd = (0.0, 0.0)  # (roll_ref, pitch_ref), rad
        self._t_att_prev = self._t_pos_prev = -math.inf
        #: largest tilt seen in each phase (deg, by :class:`Phase` value), for the report
        self.max_tilt_by_phase: dict[str, float] = {}

    # the phases' shared state, under the names the API, the driver and the tests use
    @property
    def config(self) -> SequenceConfig:
        """The sequence's settings (the tuning API may replace them mid-tune)."""
        return self._config

    @config.setter
    def config(self, value: SequenceConfig) -> None:
        self._config = self.shared.config = value

    @property
    def loops(self) -> dict[Loop, LoopTest]:
        return self.shared.loops

    @property
    def events(self) -> list[str]:
        """For the report's notes (relay amplitude raised...)."""
        return self.shared.events

    @property
    def takeoff(self) -> TakeoffController:
        """The climb controller; the altitude relay runs inside it."""
        return self.shared.takeoff

    @property
    def origin(self) -> tuple[float, float, float]:
        """The take-off point in the take-off heading frame (m; z up)."""
        return self.shared.origin

    @property
    def lifted(self) -> bool:
        """The attitude relays run (lift-off seen)."""
        return self.liftoff.lifted

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
                sh = self.shared
                sh.filter_position(s)
                sh.att_noise.update(s.t_att_s, (s.roll_rad, s.pitch_rad, s.p_rad_s,
                                                s.q_rad_s))
                sh.pos_noise.update(s.t_pos_s, (*sh.xy_f, sh.z_f))

    def noise_band(self, loop: Loop) -> float:
        """Relay noise band of ``loop`` (its units): ``noise_band_sigmas`` x measured noise."""
        return self.shared.noise_band(loop)

    def start(self, s: FlightState) -> None:
        """Take-off command: remember the take-off point and heading, enter TAKEOFF."""
        with self._lock:
            self.yaw_ref = s.yaw_rad
            s = self._heading_frame(s)
            self.shared.origin = (s.x_m, s.y_m, s.z_up_m)
            self.t_start_s = max(s.t_att_s, s.t_pos_s)
            self.state = s
            self.phase = Phase.TAKEOFF
            self.altitude.start(self.t_start_s)
            self.liftoff.arm(s)

    def leave_alone(self, loop: Loop, why: str) -> None:
        """Give up on a loop (it keeps what it had) and say why in the report."""
        with self._lock:
            t = self.loops[loop]
            t.state, t.note, t.relay = LoopState.LEFT_ALONE, why, None

    # ------------------------------------------------------------------ queries
    @property
    def inner_done(self) -> bool:
        return self.shared.inner_done

    @property
    def all_done(self) -> bool:
        return all(t.state in (LoopState.TUNED, LoopState.LEFT_ALONE) for t in self.loops.values())

    def side_ready(self) -> list[Loop]:
        """Side loops not started, once altitude, roll and pitch are done
        (:meth:`SideRelays.ready <mrft_gcs.flight.phases.side.SideRelays.ready>`)."""
        return self.side.ready()

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
            cfg = self.config
            for t in self.loops.values():
                if (t.state is LoopState.RELAY and t.status.steady
                        and t.status.cycles > t.retry_from):
                    sigma = t.band / cfg.noise_band_sigmas
                    if (sigma > cfg.max_noise_ratio * t.status.amplitude
                            and self.shared.raise_h(t, sigma / (0.7 * cfg.max_noise_ratio
                                                                * t.status.amplitude))):
                        continue  # started over on the larger amplitude
                    if sigma > cfg.max_noise_ratio * t.status.amplitude:
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
                                               sp, tilt_on(t, ts))
                    out.append(t.snapshot)
        return out

    def retry(self, loop: Loop, restart: bool = False, larger: bool = False) -> None:
        """Identification failed on this cycle: keep the relay going and wait for the next.

        ``restart``: the cycles were not a proper MRFT oscillation (a slow, lopsided mode
        the relay can lock into); the relay starts over, x and y after settling again.
        ``larger``: the cycles were too small for the noise; the relay runs on and the next
        cycle is tried with the last ones (starting the detection over costs its steady
        periods again, a second or more on a side axis, for cycles like these). Once a whole
        new set of cycles (``refused_sets_before_raise`` sets) was refused too, the amplitude
        is what fails: it is raised (``h_raise``, within ``h_max``) and the detection starts
        over. A raise at once was slower: its first cycles, still growing, were refused as
        well.
        """
        with self._lock:
            t = self.loops[loop]
            if t.state is LoopState.IDENTIFYING:
                t.state = LoopState.RELAY
                if larger:
                    n = self.config.cycle_rules(loop).identify_cycles
                    if t.retry_base < 0:
                        t.retry_base = t.status.cycles
                    sets = self.config.refused_sets_before_raise
                    if t.status.cycles - t.retry_base < sets * n or not self.shared.raise_h(
                            t, self.config.h_raise, "identification refused two whole new "
                            "sets of cycles as too small for the noise"):
                        t.retry_from = t.status.cycles
                        return
                t.restart_detection()
                relay = self.shared.relay_of(t)
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
            t.pd = PDLoop(k * k * ident.gains.Kc, k * ident.gains.Kd, trim, lo, hi)
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
            self.side.start(settings, self.state)
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
    def step(self, s: FlightState, applied: dict[Loop, float] | None = None
             ) -> ActuatorTarget | AttitudeTarget:
        """Setpoint for the latest state (torque path: ActuatorTarget; attitude: AttitudeTarget).

        ``applied``: per loop, the relay output the vehicle actually got (a log replay: the
        logged command); the cycle detectors then take it instead of this tick's own output.
        """
        with self._lock:
            s = self._heading_frame(s)
            self.state = s
            sh = self.shared
            sh.applied = applied or {}
            cfg = self.config
            tilt = math.degrees(s.tilt_rad)
            if tilt > self.max_tilt_by_phase.get(self.phase.value, -1.0):
                self.max_tilt_by_phase[self.phase.value] = tilt
            z = s.z_up_m - sh.origin[2]
            new_att = s.t_att_s > self._t_att_prev
            new_pos = s.t_pos_s > self._t_pos_prev
            self._t_att_prev, self._t_pos_prev = s.t_att_s, s.t_pos_s
            if new_pos:
                sh.filter_position(s)
            thrust = 0.0 if self.phase is Phase.PREFLIGHT else self.altitude.step(s, z, new_pos)
            if self.phase is Phase.TAKEOFF and self.takeoff.switched:
                self.phase = Phase.INNER_MRFT
            ux, uy = self.side.step(s, new_pos)
            # onto the body axes by the measured heading (PX4's position controller does the
            # same): a yaw drift must not turn the x test's tilt into y motion
            d = wrap_pi(s.yaw_rad - self.yaw_ref)
            c, n = math.cos(d), math.sin(d)
            if new_att:  # the measured tilt along each axis, back through the same rotation
                self.side.record_tilt(s, c, n)
            lim = cfg.max_tilt_cmd_rad
            roll_ref = min(lim, max(-lim, c * uy - n * ux))
            pitch_ref = min(lim, max(-lim, -(c * ux + n * uy)))
            self.tilt_cmd = (roll_ref, pitch_ref)
            if cfg.actuation is Actuation.ATTITUDE:
                q = quat_from_euler(roll_ref, pitch_ref, self.yaw_ref)
                return AttitudeTarget(s.t_att_s, q, thrust)
            airborne = self.liftoff.step(s, z)
            roll = self.attitude.step(Loop.ROLL, roll_ref, s.roll_rad, s.p_rad_s, s.t_att_s,
                                      new_att, airborne)
            pitch = self.attitude.step(Loop.PITCH, pitch_ref, s.pitch_rad, s.q_rad_s, s.t_att_s,
                                       new_att, airborne)
            yaw = (self.yaw.step(self.yaw_ref, s.yaw_rad, s.r_rad_s, s.t_att_s) if airborne
                   else 0.0)
            return ActuatorTarget(s.t_att_s, roll, pitch, yaw, thrust)

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
