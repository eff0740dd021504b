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
(measured: 5 deg on racer250 under the attitude relays) does not couple the two
side tests.
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
from mrft_gcs.flight.controllers import FlightState, PDLoop, YawHold, catch_pd, wrap_pi
from mrft_gcs.flight.noise import ComplementaryFilter, NoiseEstimator
from mrft_gcs.flight.takeoff import TABLE_V, TakeoffController, TakeoffSettings
from mrft_gcs.identify import CycleDetector, CycleStatus, Identification, RelaySettings
from mrft_gcs.loops import INNER_LOOPS, SIDE_LOOPS, Loop, LoopKind
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
    detector: CycleDetector = field(default_factory=CycleDetector)
    status: CycleStatus = field(default_factory=lambda: CycleStatus(0, False, _NAN, _NAN, math.inf))
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
    dt_s: float = _NAN  # mean telemetry interval seen by the detector
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

    def restart_detection(self) -> None:
        """Forget the cycles seen so far: the relay starts over."""
        self.detector.reset()
        self.status = CycleStatus(0, False, _NAN, _NAN, math.inf)


@dataclass(frozen=True)
class SequenceConfig:
    """How the sequence flies; units in the names.

    ``hover_thrust_guess`` (the autopilot's estimate, normalised thrust) turns the
    take-off into a climb on a PD about it, with the altitude relay started at rest and
    biased at it (:mod:`mrft_gcs.flight.takeoff`); without it, eq. 21 with Table V.
    """

    actuation: Actuation = Actuation.TORQUE
    z_ref_m: float = 1.0
    takeoff: TakeoffSettings = TABLE_V
    hover_thrust_guess: float | None = None
    #: the climb's brake (``TakeoffSettings.brake_m``) only once roll and pitch are tuned:
    #: a braked climb starts the altitude relay about 1 s sooner, and its thrust swing then
    #: overlaps more attitude relays. In-process at 6 x this box's stalls (racer250, 90
    #: seeds) a brake at any time gave roll/pitch over 10 % J 28 -> 39 of 180, x/y over
    #: 100 % J or unstable 2 -> 9, tilt over 35 deg 2 -> 5; with this rule 29, 1 and 3
    #: (a variant changing only the altitude held after the relay: 29, 2 and 4)
    brake_after_attitude: bool = True
    max_tilt_cmd_rad: float = 0.35
    airborne_m: float = 0.03
    #: lift-off as the attitude sees it: after the take-off command, a roll/pitch rate beyond
    #: ``liftoff_rate_sigmas`` x its ground noise (at least ``liftoff_rate_floor_rad_s``) or
    #: an angle off its ground value by more than the relay's noise band starts the attitude
    #: relays. A centre-of-mass offset is a torque the ground carries until lift-off; waiting
    #: for ``airborne_m`` on the (delayed) altitude left it 0.15-0.25 s to tilt the vehicle
    liftoff_rate_sigmas: float = 5.0
    liftoff_rate_floor_rad_s: float = 0.05
    #: ... once the thrust command is this share of the hover guess (0.1 without one)
    liftoff_thrust_share: float = 0.7
    #: cycles handed to identification (the classifier input averages up to four)
    identify_cycles: int = 4
    #: ... except altitude and x/y, which the tune waits for (x and y start once altitude is
    #: done): they hand over this many (altitude, side) once steady, one cycle sooner
    #: (measured on the in-process SITL, 3 airframes x 8 seeds: take-off to all loops tuned
    #: 11.8 s mean with 4 cycles, 10.5 s with 3; see README "Tuning a vehicle" for J).
    #: Roll and pitch are done seconds before altitude and keep four. Two side cycles:
    #: racer250 x/y J up to 63 %, one unstable (tune_stalls --gcs-delay, 12 seeds)
    identify_cycles_alt_side: tuple[int, int] = (3, 3)
    #: periods (and amplitudes) that must agree before a loop's cycles are identified:
    #: attitude, altitude, side. x and y run at once and disturb each other: on racer250
    #: (thrust-to-weight 4.5) each side relay switch saturates the motors, so one axis'
    #: torque depends on the other's and the two cycles beat (periods 0.62-0.78 s, where
    #: either axis alone is steady within 1.3 %). Waiting for three steady side periods
    #: then took up to 12 s. The cycles handed over are still checked for steadiness (the
    #: harmonic fit's spread, :data:`mrft_gcs.identify.runtime.FIT_MAX_SD`). Measured
    #: (tune_stalls, 12 seeds per airframe with stalls): racer250 take-off to all tuned
    #: mean 12.7 s, max 17.9 s with 3; 10.0 / 13.7 s with 2 (24 seeds: max 13.7 s); x/y |J|
    #: within 7.2 % both ways
    steady_periods: tuple[int, int, int] = (3, 2, 2)
    #: from this many cycles on (attitude, altitude, side; None: never) a loop's detector
    #: accepts periods and amplitudes within ``relaxed_tol`` instead of ``period_tol`` and
    #: 8 %. Ground-station stalls hold a relay switch for a tick now and then; on 0.2-0.3 s
    #: roll/pitch cycles that kicks nearly every cycle (racer250 in-process at this box's
    #: stall rate: periods 176-216 ms, amplitudes 40-64 mrad, 31 cycles before three agreed
    #: within 8 %). Measured (tune_stalls --gcs-delay, 3 airframes x 24 seeds): qdrone's
    #: roll/pitch tuned by 3.3 s at the latest instead of 7.3 s; J of the written gains
    #: unchanged (README "Tuning a vehicle", step 6). Live racer250, 12 seeds each way:
    #: take-off to all tuned mean 11.04 -> 8.66 s, roll/pitch |J| mean 3.2 -> 2.9 %
    relax_after_cycles: tuple[int | None, int | None, int | None] = (8, None, None)
    relaxed_tol: tuple[float, float] = (0.08, 0.16)
    #: periods agree within this fraction, or 2.5 telemetry intervals if that is more.
    #: Live over UDP the periods of an otherwise steady cycle wobble by 2-4 % (f550 roll
    #: 0.496-0.52 s; x/y 1.55-1.66 s while both side relays run): with 3 % the tune waited
    #: for attitude or x/y up to 13 s longer (f550, 5 seeds: take-off to all tuned
    #: 12.1-22.0 s with 3 %, 12.5-13.8 s with 5 %, J within +-3 % both ways)
    period_tol: float = 0.05
    #: a relay whose error passes ``runaway_factor`` x its cycle amplitude (and the floor:
    #: rad for attitude, m for altitude and side) while still pushing it out is restarted
    runaway_factor: float = 3.0
    runaway_floor: tuple[float, float, float] = (0.1, 0.15, 0.3)
    #: roll/pitch before any cycle is known (rad): a relay's start-up swings are larger
    #: than its steady cycle (racer250: 0.10-0.20 rad against 0.05), and a restart as a
    #: sign relay at such an error swings further out: with GCS stalls in-process, racer250
    #: was restarted 140-270 times with errors growing to 0.48 rad (tilt 42-56 deg) in 2 of
    #: 12 seeds with the 0.1 rad floor
    runaway_floor_startup_rad: float = 0.25
    #: roll/pitch run-away catch: a swing still carrying out is caught where it will *stop*
    #: (error plus rate^2 / 2 a, with a = pi A w0^2 / 4 the plant's acceleration per h from
    #: the relay's cycle) rather than where it is, and the damping PD may use this many
    #: times the relay amplitude. A GCS stall of 60 ms during racer250's first relay cycle
    #: sent roll and pitch to -3.5 rad/s; a catch limited to h (what the relay itself
    #: pushes back with) stopped them only at 25.5 deg. tune_stalls --gcs-delay, racer250
    #: x 24 seeds: largest tilt 25.5 -> 18.7 deg; x 30 seeds at 6 x the stalls: 33.0 ->
    #: 24.2 deg, written inner |J| max 24.7 -> 12.8 %; qdrone and f550 unchanged (no catch)
    catch_torque_factor: float = 3.0
    #: factor on the identified attitude PDs while they run on the GCS (during the side
    #: tests and the hover); the written gains are never scaled.
    gcs_attitude_pd_scale: float = 1.0
    #: relay noise band = this many standard deviations of the signal's noise, measured
    #: on the ground before the take-off (the classifiers were trained with 4 sigma)
    noise_band_sigmas: float = 4.0
    #: bands used when too few ground samples were seen to measure the noise
    relay_band_att_rad: float = 0.003
    relay_band_pos_m: float = 0.003
    #: the relay amplitude is raised (x ``h_raise``, up to ``h_max``: attitude torque,
    #: altitude thrust, side tilt in rad) when the oscillation is too small for the noise:
    #: switches before the MRFT threshold clears the band, or noise over ``max_noise_ratio``
    #: of the amplitude (the classifiers were trained with up to 3 %)
    h_raise: float = 1.6
    h_max: tuple[float, float, float] = (0.3, 0.25, 0.2)
    max_noise_ratio: float = 0.025
    #: smallest starting amplitude of the roll/pitch relays (normalised torque): the
    #: classifiers' default (Table V: 0.05) gives cycles of 0.01-0.016 rad at beta -0.7 on
    #: the bundled airframes, too small to clear a 4-sigma band of 0.8 mrad noise
    h_att_min: float = 0.12
    #: the roll/pitch relays start at this amplitude (a little over Table V's h_att, 0.05),
    #: and their first period measures how far the axis swings per unit of h and the torque
    #: that holds it on average (a centre-of-mass offset: the mean relay output over one
    #: period, as the plant integrates). The relay then takes ``h_att_min`` (or a raised
    #: amplitude), but no more than swings the axis ``att_amp_max_rad``, and that mean
    #: torque as its bias when it exceeds ``att_bias_min`` of h. At a fixed 0.12 the cycles
    #: of light, agile vehicles in the population reached 15-34 deg per axis (harmonic
    #: balance, GCS delay included). A 3 % centre-of-mass offset is up to 0.045 of torque:
    #: 0.05 turned a 2.5 kg vehicle against 0.037 so slowly that it drifted 5 m away
    #: (population benchmark, lockstep, 40 seeds: in-domain tuned 13 of 14 with 0.05, 14 with
    #: 0.06 or 0.07; bundled airframes under stalls, 54 tunes: alike)
    h_att_start: float = 0.06
    #: ... and never below this (a torque a motor dead band or the noise would swamp)
    h_att_floor: float = 0.02
    #: a relay pushing back for this long while the axis still speeds away is beaten by a
    #: torque bias (longer than the push-back takes to act: delays and motor lag, up to 0.15 s here)
    att_bias_window_s: float = 0.25
    #: per axis; both at once tilt about 10 deg. The noise needs up to 57 sigma (the raise
    #: rule's target): 0.02-0.11 rad at the population's 0.4-2 mrad of attitude noise
    att_amp_max_rad: float = 0.12
    att_bias_min: float = 0.2
    #: a larger mean torque is no centre-of-mass offset (3 % of the arm is 0.01-0.05) but a
    #: disturbed period, and is not taken as the bias
    att_bias_max: float = 0.1
    #: later periods may resize a relay this many times (each restarts its detection)
    att_max_resizes: int = 3
    #: a resized relay restarts once its axis is within this share of the expected cycle's
    #: amplitude and peak rate (for three periods at most; then the run-away catch's full
    #: envelope): a sign relay restarted 1.6 deg off its set point swung out to 16 deg,
    #: twice its cycle, and locked into a lopsided cycle
    att_restart_envelope: float = 0.1
    #: the same for the x/y relays (tilt, rad): the side classifiers' own 0.08. On x and
    #: y smoothed by the complementary filter (0.16 x the raw noise) it gives cycles of
    #: 1-10 cm, the noise 0.3-1.5 % of them; a noisier estimate raises it (``h_raise``).
    #: Each side relay switch steps the attitude set point by 2 h, which the freshly tuned
    #: attitude PD (15-25 deg of phase margin) overshoots, and a GCS stall holds the torque
    #: of that step: with 0.16 racer250 reached 42 deg (tune_stalls --gcs-delay, 36 tunes:
    #: largest tilt 42.0 -> 25.5 deg, racer250 mean 23.3 -> 11.4 deg with 0.08, take-off to
    #: all tuned mean 11.03 -> 10.62 s, x/y |J| within 4.5 and 3.5 %)
    h_side_min: float = 0.08
    #: gain of the complementary filter (position + velocity) on x, y and altitude for the
    #: relays and their identification (1 = raw position)
    side_filter_k: float = 0.05
    #: before a side relay starts, the axis is brought to rest by a soft PD (tilt per m and
    #: per m/s) until its speed is below ``settle_speed_m_s`` (at most ``settle_max_s``); the
    #: relay then oscillates about that point: an MRFT on the side cascade started off its
    #: centre or moving can lock into a slow, drifting cycle the classifier never saw
    settle_pd: tuple[float, float] = (0.3, 0.4)
    settle_speed_m_s: float = 0.03
    settle_max_s: float = 2.0
    #: largest tilt command of that soft PD (rad): an axis is handed to it from the bounding
    #: relay as soon as its attitude loop is tuned, possibly moving at 1 m/s, which unclipped
    #: is a 0.4 rad step on the freshly tuned attitude PD while the other axis still runs
    #: its relay (the bounding relay itself commands at most 0.1 rad)
    settle_max_tilt_rad: float = 0.1


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
    def _detector(self, loop: Loop) -> CycleDetector:
        cfg = self.config
        i = (LoopKind.ATTITUDE, LoopKind.ALTITUDE, LoopKind.SIDE).index(loop.kind)
        return CycleDetector(n_periods=cfg.steady_periods[i],
                             relax_after=cfg.relax_after_cycles[i], relaxed_tol=cfg.relaxed_tol)

    def reset(self) -> None:
        cfg = self.config
        self.phase = Phase.PREFLIGHT
        self.loops: dict[Loop, LoopTest] = {
            lp: LoopTest(lp, detector=self._detector(lp)) for lp in Loop}
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
        self._applied: dict[Loop, float] = {}  # see step()
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
        attitude loop's response): tried, README "Tuning a vehicle" step 7.
        """
        done = (LoopState.TUNED, LoopState.LEFT_ALONE)
        if self.loops[Loop.ALTITUDE].state not in done:
            return []
        if not self.inner_done:
            # both attitude loops first: a side relay tilts its axis +-0.2 rad, which broke
            # the other attitude loop's relay when it was still running (live qdrone: pitch's
            # 0.29 s cycle fell into a 0.57 s one under y's test and drifted to 35 deg)
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
                    ts, u, y = t.detector.last_cycles(self._cycles(t.loop))
                    if ts.size < 8:
                        continue
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

    def _cycles(self, loop: Loop) -> int:
        """Cycles handed to identification for ``loop``."""
        n = self.config.identify_cycles
        if loop is Loop.ALTITUDE:
            return min(n, self.config.identify_cycles_alt_side[0])
        if loop in SIDE_LOOPS:
            return min(n, self.config.identify_cycles_alt_side[1])
        return n

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
            # sizes the limit; the bare floor made a relay's own start-up swing on racer250
            # pitch (0.10-0.20 rad) a run-away again, 70 catches in a row
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
        # into as large a swing the other way (racer250 in-process, stalls x 6: pitch to
        # -48 deg in 0.6 s cycles where the steady one is 0.25 s). The damping PD brings
        # the return swing to rest instead (tune_stalls --stalls 6, 30 seeds: largest tilt
        # 48.4 -> 30.5 deg). Only once the detector has measured cycles since the relay
        # (re)started: its own start-up swing also carries past 3 amplitudes while it
        # pushes back (live racer250 roll: caught 10 times in a row at -0.18 rad)
        # (or once a resized roll/pitch relay restarted at rest: its cycle is measured, and
        # its start-up swing is no larger; a 70 ms stall then swung racer250 to 29 deg)
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
                # sign relay restarted at the run-away's error swings further out: racer250
                # with stalls in-process, 235 restarts from 0.22 to 0.33 rad, tilt 90 deg)
                t.cycle = (t.status.period_s, t.status.amplitude)
            if t.loop in (Loop.ROLL, Loop.PITCH) and math.isfinite(t.cycle[0]):
                # A relay is no stabilising controller: restarted after a disturbance (a
                # GCS stall holding one relay level for 50-100 ms) it had fed each swing
                # into a larger one (racer250, in-process with stalls: 8 restarts, 36 deg).
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
    def step(self, s: FlightState, applied: dict[Loop, float] | None = None
             ) -> ActuatorTarget | AttitudeTarget:
        """Setpoint for the latest state (torque path: ActuatorTarget; attitude: AttitudeTarget).

        ``applied``: per loop, the relay output the vehicle actually got (a log replay: the
        logged command); the cycle detectors then take it instead of this tick's own output.
        """
        with self._lock:
            s = self._heading_frame(s)
            self.state = s
            self._applied = applied or {}
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

    def _feed(self, t: LoopTest, t_s: float, u: float, y: float, new: bool) -> None:
        # one detector sample per telemetry sample (ticks between samples repeat the state)
        if new and t.state in (LoopState.RELAY, LoopState.IDENTIFYING):
            u = self._applied.get(t.loop, u)
            det = t.detector
            if det.t and math.isfinite(t.status.period_s) and t.status.period_s > 0:
                # switches are seen on telemetry samples: a period is known to about one
                # sample interval either way, so short cycles need a wider tolerance
                dt = t_s - det.t[-1]
                t.dt_s = dt if not math.isfinite(t.dt_s) else 0.99 * t.dt_s + 0.01 * dt
                det.period_tol = max(self.config.period_tol, 2.5 * t.dt_s / t.status.period_s)
            t.status = det.update(t_s, u, y)

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
                    self.takeoff.resettle(hover=float(np.mean(t.detector.last_cycles(2)[1])))
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
        _, u, y = t.detector.last_cycles(2)
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
                # and now pushes the axis away from it: random vehicle 3 went from 4 to 40
                # deg so. The relay is turned round at once, this point its new extreme
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
        ``att_amp_max_rad``: the first full period of an agile vehicle at ``h_att_start``
        tilted it 40 deg (random vehicle 3, 82 g; its bias is measured on later periods)."""
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
                # swung twice as far as the steady one on racer250's pitch)
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
            # swung out to twice the cycle, and a larger h taken mid-swing (racer250 under
            # stalls) tilted it 26 deg where 11 with the restart. A damping PD sized on that
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
