"""``tune(connection, profile=...) -> TuneResult``: one live tune, from the ground to hovering.

The steps (README, docs/method.md): connect (the session's .tlog is written as traffic
passes); measure the link and refuse one that cannot carry a relay test; read
every parameter the tune will write (a missing one fails before take-off) and
the hover thrust; get the relay settings of the bundled classifiers; stream
setpoints at 250 Hz *before* switching to OFFBOARD; arm; run
:class:`~mrft_gcs.flight.sequence.TuningSequence` (take-off, MRFT on altitude,
roll and pitch at once, then x and y), identifying each loop as soon as its
oscillation is steady and switching it to its PD at once (the bundled identification
runs in a process of its own, :mod:`mrft_gcs.identify.worker`, so that it never holds
up the stream); hover; write the gains
as autopilot parameters (clamped into the profile's ``[param_ranges]``, a note per
clamp; backup first, every value read back); switch to the autopilot's position
mode so it flies on them; check a short hover; where asked (``hold_compare_s``, the
profile's ``[hold_compare]``), hold there on the written values and on the ones they replaced
and keep the written set only where it holds at least as well
(:mod:`mrft_gcs.flight.holdcompare`).

Safety: every setpoint tick checks the limits (:mod:`mrft_gcs.flight.safety`);
telemetry silent for 0.5 s stops the stream and lands (the streamer's watchdog);
Ctrl-C lands. All raise :class:`~mrft_gcs.errors.SafetyAbort` (exit code 5).
A failed tune's exception carries what was done so far as ``err.partial_result``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as _dt
import gc
import math
import os
import time
from collections.abc import Callable, Collection
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mrft_gcs.errors import (
    GainsReverted,
    IdentificationError,
    LinkError,
    MrftError,
    ParameterError,
    PilotTookOver,
    SafetyAbort,
    UsageError,
)
from mrft_gcs.flight.controllers import FlightState
from mrft_gcs.flight.driver import NUMERIC_RETRIES, SequenceDriver  # noqa: F401 - re-exported
from mrft_gcs.flight.holdcompare import (
    HoldComparison,
    HoldFigures,
    HoldVerdict,
    compare_holds,
    judge_holds,
)
from mrft_gcs.flight.hover import HoverCheck, check_hover_states
from mrft_gcs.flight.inair import (
    CHECK_ROUNDS,
    PASS_PM_DEG,
    PM_HIGH_DEG,
    SIDE_PM_MIN_DEG,
    STRUCT_TIGHTEN_GAIN,
    STRUCT_TIGHTEN_LIVE,
    CheckPlan,
    InAirCheck,
    OnboardCascade,
    SquareWaveProbe,
    Verification,
    check_margin,
    plan_check,
    probe_amplitude,
    probe_centre,
    redesigned_gains,
    side_behind_checked,
    structured_redesign,
    tighten_above,
    without_gain_deficit,
)
from mrft_gcs.flight.onboard import (
    GcsDelay,
    PositionLoopRate,
    Retarget,
    SideLoop,
    cascade_delay_out_s,
    measure_gcs_delay,
    onboard_extra_delay_s,
    onboard_gains,
    pooled_attitude,
    pooled_note,
    robust_onboard_gains,
    shared_side_gains,
    vehicle_position_rate,
)
from mrft_gcs.flight.phases.yaw import IDENTIFY_AS as YAW_IDENTIFY_AS
from mrft_gcs.flight.phases.yaw import YawOutcome
from mrft_gcs.flight.ratepath import CHECK_AMPLITUDE_RAD as RATE_CHECK_AMPLITUDE_RAD
from mrft_gcs.flight.ratepath import CHECK_LEAD_S as RATE_CHECK_LEAD_S
from mrft_gcs.flight.ratepath import CHECK_SETTLE_S as RATE_CHECK_SETTLE_S
from mrft_gcs.flight.ratepath import CHECK_SPAN_S as RATE_CHECK_SPAN_S
from mrft_gcs.flight.ratepath import CHECK_SWING as RATE_CHECK_SWING
from mrft_gcs.flight.ratepath import GCS_PD_SCALE as RATE_GCS_PD_SCALE
from mrft_gcs.flight.ratepath import INAIR_CHECK as RATE_INAIR_CHECK
from mrft_gcs.flight.ratepath import STREAM_HZ as RATE_STREAM_HZ
from mrft_gcs.flight.ratepath import RatePath, rate_path_refusal
from mrft_gcs.flight.ratepath import check_cascade as rate_check_cascade
from mrft_gcs.flight.ratepath import check_points as rate_check_points
from mrft_gcs.flight.safety import SafetyMonitor
from mrft_gcs.flight.sequence import (
    CycleSnapshot,
    LoopState,
    Phase,
    SequenceConfig,
    TuningSequence,
    quat_from_euler,
)
from mrft_gcs.flight.source import LinkTelemetry, LiveVehicle, Setpoint, VehicleMode
from mrft_gcs.flight.structure import (
    OnboardStructure,
    rate_d_values,
    structured_retarget,
    vehicle_structure,
)
from mrft_gcs.flight.timeliness import HostTooSlow, TimelinessMonitor, host_advice
from mrft_gcs.identify import (
    Identification,
    RelaySettings,
    attach_residual,
    relay_settings,
)
from mrft_gcs.identify.live import (
    Identifier,
    bundled_identifier,
    measured_attitude_loop,
    warm_up_identification,
)
from mrft_gcs.identify.worker import AVAILABLE as worker_available
from mrft_gcs.identify.worker import IdentificationWorker, WorkerError
from mrft_gcs.link import (
    SetpointStreamer,
    StreamStats,
    VehicleLink,
    measure_link,
    require_relay_capable,
)
from mrft_gcs.link.clock import ClockFit, ClockModel
from mrft_gcs.link.firmware import Firmware, detect_firmware, torque_path_refusal
from mrft_gcs.link.latency import CpuWakeLatency
from mrft_gcs.link.modes import CustomMode, mode_matches
from mrft_gcs.link.quality import LinkQuality
from mrft_gcs.loops import SIDE_INNER, Loop, LoopKind
from mrft_gcs.params import ParamChange, ParamClient
from mrft_gcs.plant import PD, InnerModel, SideModel
from mrft_gcs.profiles import (
    Actuation,
    AutopilotProfile,
    PDGains,
    SafetyLimits,
    fit_profile,
    load_profile,
    params_in_range,
)
from mrft_gcs.telemetry import (
    ActuatorTarget,
    Attitude,
    AttitudeSetpoint,
    AttitudeTarget,
    LocalPosition,
)

__all__ = ["tune", "TuneResult", "LoopResult", "Identifier", "YAW_NOTE", "SCHEMA",
           "requested_loops", "parse_actuation", "NOT_REQUESTED"]

SCHEMA = "mrft-gcs/tune-report/1"
YAW_NOTE = ("yaw is not tuned: it is held by a conservative GCS-side PD during the tests "
            "(Kc 0.2 /rad, Kd 0.08 s/rad on normalised yaw torque) and keeps the autopilot's "
            "own yaw gains afterwards")
NOT_REQUESTED = "not requested"
#: telemetry (Hz) PX4's attitude path needs: its relays switch on position, whose cycles last
#: a second or more, and stock PX4 streams position no faster than its EKF2 runs (~100-125 Hz)
PX4_ATTITUDE_PATH_MIN_TELEMETRY_HZ = 90.0
_ATTITUDE_LOOPS = (Loop.ROLL, Loop.PITCH)
#: seconds the identification worker may take to load (else the tune identifies in its own
#: process), and to answer one identification (60-120 ms measured; else likewise)
WORKER_WARM_UP_S = 60.0
WORKER_CALL_S = 20.0
#: seconds the stream runs on the ground before arming: the pre-arm check of the loop's
#: timeliness (telemetry at the asked rate, set points going out) watches it
PREARM_S = 2.0


def requested_loops(loops: Collection[str | Loop] | None, actuation: Actuation) -> frozenset[Loop]:
    """The loops a tune writes: ``loops`` checked against the actuation path.

    ``None`` is every loop the path can tune (torque and rate: all five; attitude:
    altitude, x and y, the autopilot keeping its own roll and pitch loops).

    >>> sorted(lp.value for lp in requested_loops(["x", "altitude"], Actuation.TORQUE))
    ['altitude', 'x']
    >>> sorted(lp.value for lp in requested_loops(None, Actuation.ATTITUDE))
    ['altitude', 'x', 'y']
    """
    names = ", ".join(lp.value for lp in Loop)
    if loops is None:
        out = frozenset(Loop)
        return out - frozenset(_ATTITUDE_LOOPS) if actuation is Actuation.ATTITUDE else out
    if isinstance(loops, Loop):
        loops = [loops]
    elif isinstance(loops, str):
        loops = [n for n in loops.split(",") if n.strip()]
    chosen = set()
    for item in loops:
        try:
            chosen.add(item if isinstance(item, Loop) else Loop(str(item).strip().lower()))
        except ValueError:
            raise UsageError(f"unknown loop {item!r}: choose from {names}") from None
    if not chosen:
        raise UsageError(f"no loop requested: name at least one of {names}")
    att = sorted(lp.value for lp in chosen & set(_ATTITUDE_LOOPS))
    if att and actuation is Actuation.ATTITUDE:
        raise UsageError(f"{' and '.join(att)} cannot be tuned on the attitude path (the "
                         f"autopilot keeps its own attitude loop): drop them from the loops or "
                         f"use the torque or rate path (--actuation torque or rate)")
    return frozenset(chosen)

def tilt_note(by_phase: dict[str, float]) -> str:
    """The report's line on the largest tilt of each phase.

    >>> tilt_note({"take-off": 1.23, "inner MRFT": 9.6, "side MRFT": 8.04})
    'largest tilt by phase: take-off 1.2 deg, inner MRFT 9.6 deg, side MRFT 8.0 deg'
    """
    return "largest tilt by phase: " + ", ".join(f"{ph} {d:.1f} deg"
                                                  for ph, d in by_phase.items())


@dataclass(frozen=True)
class LoopResult:
    """One loop of a tune. ``state`` is a :class:`LoopState` value; times on the vehicle clock."""

    loop: Loop
    state: str
    beta: float
    h: float
    bias: float
    period_s: float
    amplitude: float
    identification: Identification | None
    gains: PD | None
    t_tuned_s: float
    note: str
    cycles: tuple[np.ndarray, np.ndarray, np.ndarray] | None  # t_s, u, y of the identified cycles
    band: float = math.nan  # the relay's noise band (loop output units)
    #: the GCS delay re-targeted out of the written gains (s; NaN: written as identified)
    gcs_delay_s: float = math.nan
    #: how the written loop was checked in the air (None: no check ran; ``note`` says why)
    verification: Verification | None = None
    #: how the re-target was decided: the GCS delay measured, its plausible range, the cap
    #: (None: not re-targeted by measurement)
    retarget: Retarget | None = None


@dataclass(frozen=True)
class TuneResult:
    """Everything a tune did (the report is rendered from it, :mod:`mrft_gcs.flight.report`)."""

    connection: str
    autopilot: str
    profile: str
    actuation: str
    started: str
    duration_s: float
    loops: dict[Loop, LoopResult]
    parameters: tuple[ParamChange, ...]
    backup: str | None
    status: str
    error: str | None = None
    link: LinkQuality | None = None
    stream: StreamStats | None = None
    tlog: str | None = None
    max_tilt_deg: float = float("nan")
    #: the largest tilt in each phase of the tests (deg, by phase name: "take-off",
    #: "inner MRFT", "side MRFT", "hover"), from the samples the stream acted on
    max_tilt_by_phase: dict[str, float] = field(default_factory=dict)
    limits: SafetyLimits | None = None
    hover_error_m: float = float("nan")
    notes: tuple[str, ...] = field(default_factory=tuple)
    #: the autopilot firmware as it reported itself (None: not asked yet)
    firmware: Firmware | None = None
    #: the hover on the written gains after the hand-over (None: not reached)
    hover_check: HoverCheck | None = None
    #: yaw's relay test on the rate path (None: yaw was not relay-tested)
    yaw: YawOutcome | None = None
    #: the holds on the written and the old values after the hover check (None: not flown)
    hold_compare: HoldComparison | None = None
    #: the position loop's rate the altitude and x/y gains were designed for (None: not read)
    position_loop: PositionLoopRate | None = None


#: the latest state from the link (kept under its old name for the code below)
_Telemetry = LinkTelemetry


class _AgeLog:
    """Per stream tick: the vehicle times of the ATTITUDE and LOCAL_POSITION_NED samples a
    command answered, and when it left (monotonic); written on the stream's ticks only.
    The GCS delay re-targeted out of the written gains is measured on it
    (:func:`mrft_gcs.flight.onboard.measure_gcs_delay`)."""

    def __init__(self, capacity: int = 1 << 16) -> None:  # over four minutes at 250 Hz
        self.rows = np.full((capacity, 3), np.nan)  # t_att, t_pos, sent
        self.n = 0

    def record(self, att: Attitude | None, pos: LocalPosition | None) -> None:
        if self.n >= len(self.rows) or att is None or pos is None:
            return
        self.rows[self.n] = (att.t_s, pos.t_s, time.monotonic())
        self.n += 1

    def ages_s(self, position: bool, t0_s: float, t1_s: float, clock: ClockFit
               ) -> tuple[np.ndarray, np.ndarray]:
        """The samples (position or attitude) with vehicle time in [t0, t1], and how old
        each was when a command answering it left: send time minus the earliest the link
        delivers a sample of that vehicle time (``clock``, kept up to date over the session,
        :mod:`mrft_gcs.link.clock`)."""
        r = self.rows[: self.n]
        t = r[:, 1] if position else r[:, 0]
        m = (t >= t0_s) & (t <= t1_s)
        return t[m], r[m, 2] - t[m] - clock.offset_at(t[m])


class _ReceiveClock:
    """The vehicle's clock against this one (:class:`~mrft_gcs.link.clock.ClockModel`), fed
    the receive time of every ATTITUDE and LOCAL_POSITION_NED by the link's reader thread.

    The receive time is the link's own stamp of the sample (the one its running
    ``rx_offset_s`` takes): stamped again here, a reader thread that lost the GIL between
    would add its wait to the offset."""

    def __init__(self, link: VehicleLink, timeliness: TimelinessMonitor | None = None) -> None:
        self.model = ClockModel()
        self._link = link
        self._timeliness = timeliness
        subscribe = getattr(link, "subscribe", None)
        if subscribe is None:  # a link without subscribers: no measurement, half a period
            return
        self._sub = subscribe(Attitude, LocalPosition)
        sub = self._sub.__enter__()  # for the link's life: it closes with the session
        sub._offer = self._offer  # type: ignore[method-assign]  # counted here, never queued

    def _offer(self, event: object) -> None:
        if isinstance(event, Attitude | LocalPosition):
            rx = getattr(self._link, "_last_telemetry", None)
            rx = time.monotonic() if rx is None else rx
            self.model.update(rx, event.t_s)
            if self._timeliness is not None:
                self._timeliness.sample(rx, event.t_s)


_CHECK_METHOD = ("square wave on the attitude set point at the predicted crossover of the "
                 "written loop; closed loop measured at its 1st, 3rd and 5th harmonics")


def _verified(plan: CheckPlan, check: InAirCheck, action: str = "none") -> Verification:
    return Verification(_CHECK_METHOD, True, check.predicted_pm_deg, check.measured_pm_deg,
                        action, _check_note(plan, check))


def _story(tried: list[tuple[CheckPlan, InAirCheck]], kept: CheckPlan | None = None) -> str:
    """What the checks of one loop did, e.g. ``PM 38 -> 16 deg measured, the second kept``."""
    if len(tried) == 1:
        return "none"
    pms = " -> ".join(_pm_text(c).removeprefix("PM ").removesuffix(" deg") for _, c in tried)
    which = ("", "first", "second", "third", "fourth")
    out = f"{len(tried)} checks, re-designed on the measured loop: PM {pms} deg"
    if kept is not None:
        i = next(i for i, (p, _) in enumerate(tried) if p is kept)
        out += f"; the {which[i + 1] if i + 1 < len(which) else str(i + 1)} gains kept"
    return out


def _pm_text(check: InAirCheck) -> str:
    if not check.steady:
        return "no steady response"
    return f"PM {check.measured_pm_deg:.0f} deg"


#: MAVLink ATTITUDE_TARGET's message id
ATTITUDE_TARGET_ID = 83


def _round_trip_s(q: LinkQuality | None) -> float:
    """The link's median round trip where TIMESYNC timed it (s), else 0 (a parameter read's
    round trip holds the autopilot's own handling): the in-air check's set points go up and
    the angles come down over it; half of it is the one-way latency of a GCS delay."""
    if q is None or getattr(q, "rtt_method", None) != "TIMESYNC" or not q.rtt_p50_ms > 0:
        return 0.0
    return 1e-3 * q.rtt_p50_ms


def _optional_reader(link: VehicleLink) -> Callable[[str], float | None]:
    """A parameter's value, or None where the vehicle does not answer for it (briefly: a
    missing name costs one unanswered read before take-off)."""
    probe = ParamClient(link, timeout_s=0.3, retries=1)

    def read(name: str) -> float | None:
        try:
            return probe.read(name).value
        except ParameterError:
            return None
    return read


def _check_note(plan: CheckPlan, check: InAirCheck) -> str:
    return (f"crossover predicted at {plan.wc_rad_s:.3g} rad/s; measured onboard plant "
            f"{check.k:.2f} x the model's gain, {check.extra_delay_s * 1e3:+.1f} ms of delay"
            + (f"; input: {check.source}" if check.source else "")
            + (f"; loop: {plan.cascade.describe()}" if plan.cascade is not None else ""))


def tune(connection: str, profile: str | AutopilotProfile = "px4", *,
         actuation: Actuation | str | None = None, limits: SafetyLimits | None = None,
         z_ref_m: float = 1.0, dry_link: bool = False, baud: int | None = None,
         signing_key: str | os.PathLike[str] | bytes | None = None,
         tlog_path: str | os.PathLike[str] | None = None,
         backup_dir: str | os.PathLike[str] = ".", rate_hz: float = 250.0,
         heartbeat_timeout_s: float = 5.0, max_relay_s: float = 30.0, hover_check_s: float = 2.0,
         on_progress: Callable[[dict], None] | None = None,
         identifier: Identifier | None = None,
         relay: dict[LoopKind, RelaySettings] | None = None,
         gcs_delay_s: float | None = None,
         config: SequenceConfig | None = None, residuals: bool = True,
         loops: Collection[str | Loop] | None = None,
         hold_compare_s: float | None = None,
         hold_judge: Callable[[HoldFigures, HoldFigures], HoldVerdict] | None = None
         ) -> TuneResult:
    """Tune the vehicle at ``connection`` from take-off; returns what was done.

    Parameters
    ----------
    connection : str
        pymavlink connection string (``udp:127.0.0.1:14540``, ``tcp:...``, ``/dev/ttyUSB0``).
    profile : str or AutopilotProfile
        ``px4``, ``ardupilot``, ``sitl`` or a TOML path.
    actuation : Actuation or str, optional
        ``torque`` or ``attitude``; default from the profile.
    limits : SafetyLimits, optional
        Default from the profile (command-line overrides already applied).
    z_ref_m : float
        Climb set point above the take-off point (m); the tests run there, or up to 0.3 m
        lower where a slow climb is braked (``TakeoffSettings.brake_m``).
    dry_link : bool
        Connect and check the link and parameters, but do not arm (status ``dry-link``).
    tlog_path : path, optional
        Session log; default ``mrft-YYYYmmdd-HHMMSS.tlog`` in ``backup_dir``.
    backup_dir : path
        Where the parameter backup (and default .tlog) go.
    on_progress : callable, optional
        Called about ten times a second with :meth:`TuningSequence.snapshot` (plus
        ``"stream"``: sent setpoints so far).
    identifier : callable, optional
        Replaces the bundled classifiers (``f(loop, snapshot, inner) -> Identification``):
        for tests and custom pipelines.
    relay : dict, optional
        Relay settings per loop kind instead of the classifiers' (side settings
        are still asked with the attitude identification when missing here).
    gcs_delay_s : float, optional
        Delay the GCS-side relay adds to the identified inner loops (s); the written
        gains are re-targeted to the onboard loop without it
        (:func:`mrft_gcs.flight.onboard.onboard_gains`). Default: measured per loop over
        its identified cycles, how old telemetry was when the command answering it left,
        on the vehicle clock tracked over the session (:mod:`mrft_gcs.link.clock`),
        checked for plausibility (:func:`mrft_gcs.flight.onboard.measure_gcs_delay`: half
        a setpoint period where it cannot be measured or is implausible) and held back
        where the written gains would keep less than 15 deg of phase margin at the least
        plausible delay (:func:`mrft_gcs.flight.onboard.robust_onboard_gains`).
    config : SequenceConfig, optional
        Sequence settings (relay noise bands, amplitudes...); actuation, altitude,
        hover guess and tilt command limit are always taken from the tune's arguments.
    residuals : bool
        After the flight, compare each identified inner model with its measured cycles
        (:func:`mrft_gcs.identify.attach_residual`, about a second per loop): the report's
        ``residual`` fields.
    loops : collection of str, optional
        The loops to tune (:class:`~mrft_gcs.loops.Loop` values: ``altitude``, ``roll``,
        ``pitch``, ``x``, ``y``); default every loop the actuation path can tune. Loops not
        requested are never written. x and y not requested are not relay-tested (held
        where they are, left alone with the note "not requested"). Roll, pitch and
        altitude are flown and identified anyway where the ground station flies the
        vehicle with them (torque path: all three; attitude path: altitude), but only
        the requested ones are written. Roll or pitch on the attitude path, or an
        unknown name, is a :class:`~mrft_gcs.errors.UsageError`.
    hold_compare_s : float, optional
        After the hand-over and its hover check, hold this long (s) in the position mode on
        the written gains, then on the values they replaced, and keep the set that holds at
        least as well (:func:`mrft_gcs.flight.holdcompare.compare_holds`); 0: off. Default:
        the profile's ``[hold_compare] seconds`` (ArduPilot 8 s, others off).
    hold_judge : callable, optional
        ``judge(before, after) -> HoldVerdict`` in place of
        :func:`~mrft_gcs.flight.holdcompare.judge_holds` (for tests).

    Raises
    ------
    LinkError, ParameterError, IdentificationError, SafetyAbort, UsageError
        With ``partial_result`` (a :class:`TuneResult`) when the flight had started.
    GainsReverted
        The written gains held worse than the values they replaced, which were written back
        (a :class:`~mrft_gcs.errors.ParameterError`, exit code 4; ``partial_result``
        carries both holds).
    """
    prof = load_profile(profile) if isinstance(profile, str | os.PathLike) else profile
    act = parse_actuation(actuation) if actuation is not None else prof.actuation
    wanted = requested_loops(loops, act)
    if loops is not None and Loop.ALTITUDE in wanted and prof.altitude.not_written:
        raise UsageError(f"altitude cannot be written with profile {prof.name}: "
                         f"{prof.altitude.not_written}; drop altitude from the loops")
    CpuWakeLatency()  # a bad MRFT_CPU_LATENCY_US fails here, before the vehicle is touched
    lim = limits or prof.safety
    ident_fn = identifier or bundled_identifier
    started = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
    backup_dir = Path(backup_dir)
    if tlog_path is None:
        tlog_path = backup_dir / f"mrft-{_dt.datetime.now():%Y%m%d-%H%M%S}.tlog"
        n = 1
        while Path(tlog_path).exists():
            tlog_path = backup_dir / f"mrft-{_dt.datetime.now():%Y%m%d-%H%M%S}-{n}.tlog"
            n += 1
    link = VehicleLink.connect(connection, baud=baud, timeout_s=heartbeat_timeout_s,
                               tlog_path=tlog_path, signing_key=signing_key)
    run = _Run(link, prof, act, lim, z_ref_m, connection, started, backup_dir, rate_hz,
               max_relay_s, hover_check_s, on_progress, ident_fn, relay or {})
    run.gcs_delay_s = gcs_delay_s
    run.config = config or SequenceConfig()
    run.residuals = residuals
    run.requested = wanted
    run.hold_compare_s = hold_compare_s
    run.hold_judge = hold_judge
    try:
        return run.execute(dry_link, own_worker=identifier is None)
    except MrftError as err:
        err.partial_result = run.result(_status(err), str(err))
        raise
    finally:
        run.close_worker()
        link.close()


def parse_actuation(value: Actuation | str) -> Actuation:
    """``torque``, ``attitude`` or ``rate`` as an :class:`Actuation`; anything else is a
    UsageError."""
    try:
        return Actuation(value)
    except ValueError:
        raise UsageError(f"unknown actuation {value!r}: use torque, attitude or rate") from None


def _status(err: MrftError) -> str:
    return f"error:{err.exit_code}:{type(err).__name__}"


class _Run:
    """One tune's working state (kept out of :func:`tune` so it reads in one sitting)."""

    def __init__(self, link, prof, act, lim, z_ref_m, connection, started, backup_dir, rate_hz,
                 max_relay_s, hover_check_s, on_progress, ident_fn, relay) -> None:
        self.link: VehicleLink = link
        link.modes = dict(prof.modes)
        self.prof: AutopilotProfile = prof
        self.act: Actuation = act
        self.lim: SafetyLimits = lim
        self.z_ref_m = z_ref_m
        self.connection = connection
        self.started = started
        self.backup_dir = backup_dir
        self.rate_hz = rate_hz
        self.max_relay_s = max_relay_s
        self.hover_check_s = hover_check_s
        self.on_progress = on_progress
        self.ident_fn = ident_fn
        #: the bundled identification's own process (None: identified in this one)
        self.worker: IdentificationWorker | None = None
        self.relay: dict[LoopKind, RelaySettings] = relay
        self.seq: TuningSequence | None = None
        #: runs the sequence: per tick on the stream's thread, identification on this one
        self.driver: SequenceDriver | None = None
        #: the link and its set-point stream as the driver's vehicle source
        self.vehicle: LiveVehicle | None = None
        self.streamer: SetpointStreamer | None = None
        self.quality: LinkQuality | None = None
        self.changes: tuple[ParamChange, ...] = ()
        self.backup: str | None = None
        #: what stopped the stream from its own thread (a limit, the relay guard, a stall)
        self.limit_hit: MrftError | None = None
        self.hover_error_m = math.nan
        self.notes: list[str] = []
        self.gcs_delay_s: float | None = None  # None: measured per loop (self.ages)
        self.ages = _AgeLog()
        #: stalls of the ground station's loop (telemetry gaps, late set points)
        self.timeliness = TimelinessMonitor()
        self.clock = _ReceiveClock(link, self.timeliness)  # ages are counted on it
        self.delays: dict[Loop, float] = {}  # re-targeted out of the written gains (s)
        self.retargets: dict[Loop, Retarget] = {}
        #: the identifications the written gains were designed on (roll and pitch with
        #: their fast lags pooled: :func:`mrft_gcs.flight.onboard.pooled_attitude`)
        self.design: dict[Loop, Identification] = {}
        #: the autopilot's attitude-loop structure, read before take-off (flight/structure)
        self.structure: dict[Loop, OnboardStructure] = {}
        #: rate D written as this share of rate P (s), per roll/pitch loop whose design chose it
        self.d_over_p: dict[Loop, float] = {}
        #: the rate of the loop the written altitude and x/y gains go into, read before
        #: take-off (flight/onboard): its hold is designed for
        self.position_loop = PositionLoopRate()
        self.config = SequenceConfig()
        self.written: dict[Loop, PD] = {}
        self.residuals = True
        #: the in-air check's set points while it runs (read on the stream's ticks)
        self.probe: SquareWaveProbe | None = None
        #: roll and pitch set points (rad) flown while no check's square wave is (rate path:
        #: before and after it, the input shaping switched with the vehicle at rest there)
        self.probe_hold: tuple[float, float] | None = None
        #: the mode the vehicle must stay in while the tool flies it (None: not watched)
        self.mode_watch: CustomMode | None = None
        self.seen_armed = False
        self.taken_over = False
        self.probe_yaw = 0.0
        self.verification: dict[Loop, Verification] = {}
        self.requested: frozenset[Loop] = frozenset(Loop)
        self.firmware: Firmware | None = None
        self.hover_check: HoverCheck | None = None
        #: the body-rate path's state (None: another path), :mod:`mrft_gcs.flight.ratepath`
        self.rate: RatePath | None = None
        #: seconds of each hold of the comparison (None: the profile's), and its outcome
        self.hold_compare_s: float | None = None
        self.hold_judge: Callable[[HoldFigures, HoldFigures], HoldVerdict] | None = None
        self.hold_compare: HoldComparison | None = None

    @property
    def monitor(self) -> SafetyMonitor | None:
        """The safety limits' monitor, from the take-off command on (the driver's)."""
        return self.driver.monitor if self.driver is not None else None

    # ------------------------------------------------------------------ result
    def result(self, status: str, error: str | None = None) -> TuneResult:
        loops: dict[Loop, LoopResult] = {}
        seq = self.seq
        for lp in Loop:
            t = seq.loops[lp] if seq is not None else None
            if t is None:
                loops[lp] = LoopResult(lp, LoopState.WAITING.value, math.nan, math.nan, 0.0,
                                       math.nan, math.nan, None, None, math.nan, "", None)
                continue
            snap = t.snapshot
            ident = t.identification
            loops[lp] = LoopResult(
                lp, t.state.value, t.beta, t.h, t.bias,
                snap.status.period_s if snap else t.status.period_s,
                snap.status.amplitude if snap else t.status.amplitude,
                ident, self.written.get(lp, ident.gains if ident else None),
                t.t_tuned_s - (seq.t_start_s if seq is not None else math.nan), t.note,
                (snap.t_s, snap.u, snap.y) if snap else None, t.band,
                self.delays.get(lp, math.nan), self._verification(lp, status),
                self.retargets.get(lp))
        stream = self.streamer.stats() if self.streamer is not None else None
        return TuneResult(
            connection=self.connection, autopilot=self.link.family.value, profile=self.prof.name,
            actuation=self.act.value, started=self.started,
            duration_s=seq.duration_s if seq is not None else math.nan, loops=loops,
            parameters=self.changes, backup=self.backup, status=status, error=error,
            link=self.quality, stream=stream,
            tlog=str(self.link.tlog_path) if self.link.tlog_path else None,
            max_tilt_deg=self.monitor.max_tilt_seen_deg if self.monitor else math.nan,
            max_tilt_by_phase=dict(seq.max_tilt_by_phase) if seq is not None else {},
            limits=self.lim, hover_error_m=self.hover_error_m,
            notes=tuple([(self.rate.yaw_note if self.rate else None) or YAW_NOTE] + self.notes
                        + (self.rate.notes if self.rate else [])
                        + self._log_notes()
                        + [n for n in (self.timeliness.summary(),) if n]
                        + (list(seq.events) if seq else [])
                        + ([tilt_note(seq.max_tilt_by_phase)]
                           if seq and seq.max_tilt_by_phase else [])),
            firmware=self.firmware, hover_check=self.hover_check,
            yaw=self.rate.yaw_outcome(seq.t_start_s if seq else math.nan) if self.rate else None,
            hold_compare=self.hold_compare, position_loop=self.position_loop)

    def _verification(self, lp: Loop, status: str) -> Verification | None:
        """The in-air check of ``lp``; a written loop it does not measure is checked by the
        hover on the written gains (:meth:`_hand_over`), which passed where status is ok."""
        ver = self.verification.get(lp)
        if ver is not None or lp not in self.written or not self.changes:
            return ver
        if status != "ok":
            return None
        mode = self.prof.modes["position"].name
        why = ("the in-air check does not run on this path" if lp in _ATTITUDE_LOOPS
               else "the in-air check measures roll and pitch only")
        return Verification(
            f"hover in {mode} on the written gains for {self.hover_check_s:g} s", True,
            note=f"held within {self.hover_error_m:.2f} m; this loop's phase margin is not "
                 f"measured in the air ({why})")

    def _log_notes(self) -> list[str]:
        error = self.link.tlog_error
        if error is None:
            return []
        return [f"session log {self.link.tlog_path} is incomplete: writing it failed ({error}); "
                f"the rest of the session was not logged"]

    # ------------------------------------------------------------------ steps
    def execute(self, dry_link: bool, own_worker: bool = False) -> TuneResult:
        """The tune: link check, parameters, flight, write-back.

        ``own_worker``: identify in a process of its own (the bundled identification only),
        started here so that it loads while the link is measured.
        """
        link = self.link
        self._know_firmware()
        if Loop.ALTITUDE in self.requested and (why := self.prof.altitude.not_written):
            # flown and identified all the same (the ground station holds altitude in the tests)
            self.requested = self.requested - {Loop.ALTITUDE}
            self.notes.append(f"altitude gains not written ({self.prof.name}): {why}")
        if own_worker and not dry_link:
            self._start_worker()
        self.quality = measure_link(link, rate_hz=self.rate_hz)
        # PX4's attitude path relay-tests only altitude and x/y (cycles of a second or more),
        # and PX4 streams position no faster than EKF2 runs (100-125 Hz)
        px4_attitude = self.act is Actuation.ATTITUDE and self.prof.family.value == "px4"
        min_hz = PX4_ATTITUDE_PATH_MIN_TELEMETRY_HZ if px4_attitude else 200.0
        require_relay_capable(self.quality, setpoint_hz=self.rate_hz, actuation=self.act.value,
                              signed=link.signed, min_telemetry_hz=min_hz)
        client = ParamClient(link)
        current = client.read_many(self.prof.parameter_names())
        self.hover = current[self.prof.altitude.hover_thrust].value
        self.structure = vehicle_structure(_optional_reader(link), self.prof.family.value)
        self.position_loop = vehicle_position_rate(_optional_reader(link),
                                                   self.prof.family.value)
        self.notes.append(f"position loop: {self.position_loop.source}; the altitude and x/y "
                          f"gains allow for its hold ({self.position_loop.hold_s * 1e3:.2g} ms)")
        if dry_link:
            try:
                relay_settings(LoopKind.ATTITUDE)
            except IdentificationError as err:
                self.notes.append(f"a tune would stop here: {err}")
            return self.result("dry-link")
        att = self.relay.get(LoopKind.ATTITUDE) or relay_settings(LoopKind.ATTITUDE)
        alt = self.relay.get(LoopKind.ALTITUDE) or relay_settings(LoopKind.ALTITUDE)
        # also for an identifier passed in: one that wraps the bundled identification
        # would otherwise load it in flight, next to the stream, and stall it
        warm_up_identification(relay_settings(LoopKind.ATTITUDE),
                               relay_settings(LoopKind.ALTITUDE))
        self._worker_ready()
        # Everything loaded so far lives as long as the process: out of the cyclic garbage
        # collector's sight, a full collection in flight takes ~0 ms instead of 95-165 ms
        # (measured after the warm-up), time in which no setpoint would go out.
        gc.freeze()
        cfg = dataclasses.replace(
            # the rate path flies the torque sequence, its torques sent as rates
            self.config, actuation=Actuation.TORQUE if self.act is Actuation.RATE else self.act,
            z_ref_m=self.z_ref_m,
            hover_thrust_guess=self.hover if 0 < self.hover < 1 else None,
            max_tilt_cmd_rad=0.6 * math.radians(self.lim.max_tilt_deg))
        if self.act is Actuation.RATE and cfg.gcs_attitude_pd_scale == 1.0:
            cfg = dataclasses.replace(cfg, gcs_attitude_pd_scale=RATE_GCS_PD_SCALE)
        self.seq = TuningSequence(cfg, att, alt)
        self.driver = SequenceDriver(
            self.seq, lambda lp, snap, inner: self._offload("identify", self.ident_fn, lp, snap,
                                                            inner),
            attitude_loop=lambda snap: self._offload("attitude_loop", measured_attitude_loop,
                                                     snap),
            relay=self.relay, limits=self.lim, max_relay_s=self.max_relay_s, notes=self.notes,
            timeliness=self.timeliness)
        if (rtt := _round_trip_s(self.quality)) > 0:  # the relay guard looks a round trip ahead
            self.driver.guard_lead_s = rtt + 1.0 / self.rate_hz
        for lp in SIDE_INNER:
            if lp not in self.requested:
                self.seq.leave_alone(lp, f"{NOT_REQUESTED}: not relay-tested; held where it "
                                         f"was and its parameters left as they were")
        test_backup = self._set_test_params(client)
        try:
            self._fly(client)
        except KeyboardInterrupt:
            self._emergency_land()
            raise SafetyAbort("interrupted (Ctrl-C): test stopped, landing commanded") from None
        except BaseException:
            self._emergency_land()
            raise
        finally:
            if self.rate is not None:
                self.rate.restore_rest(client)
                self.rate.close()
            self._restore_test_params(client, test_backup)
        self._compare_holds()
        if self.residuals:
            self._residuals()
        return self.result("ok")

    def _compare_holds(self) -> None:
        """The written set against the one it replaced, each held in the position mode
        (:mod:`mrft_gcs.flight.holdcompare`); the old set stays where the written one held
        worse (:class:`GainsReverted`)."""
        seconds = self.prof.hold_compare_s if self.hold_compare_s is None else self.hold_compare_s
        if not seconds > 0:
            return
        if not self.changes:
            self.notes.append("hold comparison not flown: the tune wrote nothing")
            return
        assert self.monitor is not None
        mode = self.prof.modes["position"].name
        try:
            cmp = compare_holds(self.link, self.changes, seconds, self.monitor, mode,
                                self.backup_dir, judge=self.hold_judge or judge_holds)
        except KeyboardInterrupt:
            self.link.land(wait_ack=False)
            raise SafetyAbort(f"interrupted (Ctrl-C) in the hold comparison: landing "
                              f"commanded (the values from before the tune: {self.backup})"
                              ) from None
        except SafetyAbort as err:
            raise SafetyAbort(f"{err} (the values from before the tune: {self.backup})") from err
        self.hold_compare = cmp
        self.notes.append(cmp.line())
        if cmp.outcome == "reverted":
            raise GainsReverted(
                f"the written gains held worse in {mode} than the values they replaced: "
                f"{cmp.verdict.reason}; those values are back on the vehicle (read back) and "
                f"it hovers on them in {mode}; the report has both holds and the identified "
                f"models")

    def _set_test_params(self, client: ParamClient) -> Path | None:
        """The profile's ``test_params`` (e.g. ArduCopter's throttle filter, so that the
        altitude relay flies the filter the onboard altitude loop has), backed up first."""
        if not self.prof.test_params:
            return None
        result = client.write(dict(self.prof.test_params), self.backup_dir, label="test")
        changed = [f"{c.name} {c.old:g} -> {c.new:g}" for c in result.changes if c.old != c.new]
        if changed:
            self.notes.append(f"for the tests only ({self.prof.name} test_params): "
                              f"{', '.join(changed)}; restored after the flight")
        return result.backup_path

    def _restore_test_params(self, client: ParamClient, backup: Path | None) -> None:
        if backup is None:
            return
        try:
            client.restore(backup, self.backup_dir)
        except MrftError as err:
            self.notes.append(f"the test parameters were not restored ({err}): restore "
                              f"{backup} by hand")

    def _know_firmware(self) -> None:
        """Ask the firmware what it is, take the profile whose parameter names it has, and
        refuse a path it cannot carry: all before anything is armed or written."""
        fw = self.firmware = detect_firmware(self.link)
        if fw.version is None:
            self.notes.append(f"firmware: {fw.name}: the vehicle did not answer AUTOPILOT_VERSION "
                              f"(the heartbeat gives the autopilot, the parameters the names)")
        probe = ParamClient(self.link, timeout_s=0.4, retries=1)

        def has_param(name: str) -> bool:
            try:
                probe.read(name)
            except ParameterError:
                return False
            return True

        prof, note = fit_profile(self.prof, fw, has_param)
        if note:
            self.notes.append(note)
        if prof is not self.prof:
            self.prof = prof
            self.link.modes = dict(prof.modes)
        if self.act is Actuation.RATE and (why := rate_path_refusal(self.prof, fw)):
            raise UsageError(f"--actuation rate cannot fly this vehicle: {why}; use "
                             f"--actuation attitude (tunes altitude, x and y)")
        if self.act is Actuation.TORQUE and (why := torque_path_refusal(fw)) is not None:
            raise UsageError(f"--actuation torque cannot fly this vehicle: {why}; use "
                             f"--actuation attitude (tunes altitude, x and y) or, on "
                             f"ArduCopter, --actuation rate (all five loops)")

    # ------------------------------------------------------------------ identification
    def _start_worker(self) -> None:
        if not worker_available:
            return
        try:
            self.worker = IdentificationWorker()
            self.worker.request("warm", relay_settings(LoopKind.ATTITUDE),
                                relay_settings(LoopKind.ALTITUDE))
        except (WorkerError, OSError) as err:
            self._drop_worker(f"it did not start ({err})")

    def _worker_ready(self) -> None:
        """Wait for the worker's warm-up (before the stream starts)."""
        if self.worker is None:
            return
        try:
            self.worker.reply(timeout_s=WORKER_WARM_UP_S)
        except Exception as err:  # noqa: BLE001 - whatever it was, identify here instead
            self._drop_worker(str(err) if isinstance(err, WorkerError) else
                              f"its warm-up raised {type(err).__name__}: {err}")

    def _drop_worker(self, why: str) -> None:
        self.notes.append(f"identification ran in the ground station's own process, next to "
                          f"the setpoint stream: its worker process failed ({why})")
        self.close_worker()

    def close_worker(self) -> None:
        if self.worker is not None:
            self.worker.close()
            self.worker = None

    def _offload(self, op: str, here: Callable[..., Identification], *args: object
                 ) -> Identification:
        """``op`` in the worker where there is one, else ``here(*args)`` in this process."""
        if self.worker is not None:
            try:
                return self.worker.call(op, *args, timeout_s=WORKER_CALL_S)
            except WorkerError as err:
                self._drop_worker(str(err))
        return here(*args)

    def _residuals(self) -> None:
        """Residual analysis of each identified loop (after the flight: it takes seconds)."""
        seq = self.seq
        assert seq is not None
        for lp, t in seq.loops.items():
            snap, ident = t.snapshot, t.identification
            if ident is None or snap is None or ident.residual is not None:
                continue
            u, bias = snap.u, snap.bias
            if lp is Loop.ALTITUDE:  # the model's input is the thrust's deviation from hover
                u, bias = u - snap.bias, 0.0
            band = t.band if math.isfinite(t.band) else 0.0
            t.identification = attach_residual(ident, snap.t_s, u, snap.y, bias=bias,
                                               band=band, hover=self.hover)

    def _emergency_land(self) -> None:
        if self.rate is not None:  # the vehicle's own gains back before any landing
            self.rate.abort(ParamClient(self.link))
        if self.streamer is not None:
            self.streamer.stop()
        if self.seq is not None and self.seq.phase not in (Phase.DONE, Phase.PREFLIGHT):
            self.seq.finish(Phase.ABORTED)
        if self.taken_over:
            return  # the pilot (or the firmware's failsafe) flies it: a land command would fight
        try:
            self.link.land(wait_ack=False)
        except MrftError:
            pass

    def _setpoint(self) -> Callable[[FlightState | None], Setpoint | None]:
        """The per-tick part, run on the stream's thread (:meth:`SequenceDriver.tick`), with
        the in-air check's set points and the ages of the samples each command answers."""
        seq, drv, ages = self.seq, self.driver, self.ages
        assert seq is not None and drv is not None

        def make(s: FlightState | None) -> Setpoint:
            on_ground = s is None or seq.phase is Phase.PREFLIGHT
            self.timeliness.tick(time.monotonic())
            try:
                out = drv.tick(s)
            except MrftError as err:  # a limit, the relay guard, a stalled loop
                self.limit_hit = err
                raise
            if on_ground:
                return out
            assert s is not None and self.vehicle is not None
            probe, hold = self.probe, self.probe_hold
            if not isinstance(out, (ActuatorTarget, AttitudeTarget)):
                pass
            elif probe is not None and not probe.done:
                # the written attitude loop flies the check's set points (on the rate path
                # after its hand-over the sequence's own attitude set point is replaced);
                # altitude stays on the ground station's PD
                r, p = probe.step(time.monotonic(), s.t_att_s, s.roll_rad, s.pitch_rad)
                out = AttitudeTarget(out.t_s, quat_from_euler(r, p, self.probe_yaw),
                                     out.thrust)
            elif hold is not None:
                out = AttitudeTarget(out.t_s, quat_from_euler(*hold, self.probe_yaw), out.thrust)
            tel = self.vehicle.telemetry
            ages.record(tel.att, tel.pos)  # the command leaves right after
            return out

        return make

    def _fly(self, client: ParamClient) -> None:
        seq, drv = self.seq, self.driver
        assert seq is not None and drv is not None
        tick = self._setpoint()
        if self.act is Actuation.RATE:
            assert self.prof.rate_path is not None
            self.rate = RatePath(self.link, self.prof.rate_path, self.backup_dir)
            tick = self.rate.wrap(tick)
            rate = self.rate
            drv.side_gate = lambda: rate.handed_over
        # the stream starts at once: PX4 needs it before OFFBOARD
        self.timeliness.reset()
        vehicle = self.vehicle = LiveVehicle(self.link, self.rate_hz, on_tick=tick)
        self.streamer = vehicle.streamer
        qos = self.streamer.cpu_latency
        if qos is not None and qos.denied:
            self.notes.append(f"setpoint stream: {qos.outcome}")
        self._preflight_timeliness()
        vehicle.set_mode(VehicleMode.OFFBOARD)
        self.mode_watch = self.prof.modes["offboard"]
        vehicle.arm()
        if self.rate is not None:
            self.rate.engage(client)  # armed with the stock gains: no arming check is off
            # yaw relay-tested next to roll and pitch, its cycles identified like theirs
            if (hold := self.rate.yaw_hold(seq.attitude_relay.beta, lambda snap: self._offload(
                    "identify", self.ident_fn, YAW_IDENTIFY_AS, snap, None))) is not None:
                seq.yaw = hold
            self.rate.require_aligned()
        deadline = time.monotonic() + 1.0
        while (s := vehicle.telemetry.latest()) is None and time.monotonic() < deadline:
            time.sleep(0.01)
        if s is None:
            raise LinkError("no ATTITUDE and LOCAL_POSITION_NED after arming: check the "
                            "vehicle's position estimate")
        drv.start(s)  # the take-off command (safety origin too): duration_s counts from here
        self._run_tests()
        self._hold(0.5)
        self._write_back(client)
        self._verify_written(client)
        self._hand_over()

    def _preflight_timeliness(self) -> None:
        """Stream on the ground for :data:`PREARM_S` and refuse to arm where the loop
        already stalls by the relay tests' rules (:mod:`mrft_gcs.flight.timeliness`)."""
        end = time.monotonic() + PREARM_S
        why = None
        while time.monotonic() < end and why is None:
            time.sleep(0.02)
            assert self.streamer is not None
            if self.limit_hit is None and self.streamer.abort_reason is not None:
                why = self.streamer.abort_reason  # the watchdog, on the ground: no flight
                break
            self._check_stream()
        why = why or self.timeliness.trouble(time.monotonic())
        if why is not None:
            raise HostTooSlow(f"before arming, the ground station could not keep a relay "
                              f"test's loop on time: {why}; nothing was armed or written; "
                              f"{host_advice()}")

    def _check_stream(self) -> None:
        assert self.streamer is not None
        if self.limit_hit is not None:
            raise self.limit_hit
        if self.streamer.abort_reason is not None:
            raise SafetyAbort(self.streamer.abort_reason)
        self._watch_mode()
        if self.rate is not None:
            self.rate.check()

    def _watch_mode(self) -> None:
        """Stop at once when the vehicle leaves the offboard mode or disarms in flight: the
        pilot took over by RC (or a failsafe did). Nothing is written after that."""
        hb, mode = self.link.heartbeat, self.mode_watch
        if mode is None or hb is None:
            return
        self.seen_armed = self.seen_armed or hb.armed
        if mode_matches(self.link.family, mode, hb.custom_mode) and (hb.armed
                                                                     or not self.seen_armed):
            return
        self.taken_over = True
        what = (f"the vehicle left {mode.name} (custom mode {hb.custom_mode})" if hb.armed
                else "the vehicle disarmed")
        written = ("; the parameters written before it stay (restore the backup "
                   f"{self.backup})" if self.changes else "; nothing was written")
        raise PilotTookOver(f"{what}: an RC take-over or a failsafe; the tool stopped streaming "
                            f"and commands nothing more{written}")

    def _progress(self) -> None:
        if self.on_progress is not None and self.seq is not None:
            snap = self.seq.snapshot()
            snap["stream_sent"] = self.streamer.stats().sent if self.streamer else 0
            self.on_progress(snap)

    def _run_tests(self) -> None:
        """Supervise the tests from this thread (:meth:`SequenceDriver.supervise`) while the
        stream steps the sequence, until every loop hovers on its PD."""
        seq, drv = self.seq, self.driver
        assert seq is not None and drv is not None
        next_progress = 0.0
        while seq.phase is not Phase.HOVER:
            time.sleep(0.01)
            self._check_stream()
            drv.supervise()
            if self.rate is not None:
                rp_tuned = all(seq.loops[lp].state is LoopState.TUNED for lp in _ATTITUDE_LOOPS)
                if self.rate.roll_pitch_due(rp_tuned):
                    self._rate_roll_pitch_hand_over()
                if self.rate.inner_due(rp_tuned):
                    self._rate_inner_hand_over()
            if time.monotonic() >= next_progress:
                next_progress = time.monotonic() + 0.1
                self._progress()
        self._progress()

    def _rate_roll_pitch_values(self) -> None:
        """Rate path: roll and pitch's written gains designed on ArduCopter's cascade and
        staged for the hand-over (:meth:`RatePath.split`)."""
        seq, rate = self.seq, self.rate
        assert seq is not None and rate is not None
        gains: dict[Loop, PDGains] = {}
        for lp in _ATTITUDE_LOOPS:
            t = seq.loops[lp]
            if lp not in self.requested or t.identification is None:
                continue  # its own gains go back (the hand-over restores them)
            # designed on ArduCopter's cascade as it flies them (rate-target and gyro
            # filters, loop rate), on the model less the least plausible ground-station delay
            # (the most onboard delay, as the torque path's re-target checks its margin at)
            m = t.identification.model
            g = t.identification.gains
            if isinstance(m, InnerModel):
                out = (0.0 if self.gcs_delay_s is not None else
                       cascade_delay_out_s(m, self._gcs_delay(lp, t.snapshot)))
                cg = rate.roll_pitch_gains(m, g, _ATTITUDE_LOOPS.index(lp), out)
                if out > 0:  # the in-air check predicts on the same onboard model
                    self.delays[lp] = out
                g = cg.gains
                self.notes.append(f"rate path: {lp.value} written {cg.note()}")
            self.written[lp] = g
            gains[lp] = PDGains(g.Kc, g.Kd)
        ranged = params_in_range(self.prof, gains, self.hover) if gains else None
        if ranged is not None:
            self.notes.extend(ranged.notes)
        rate.split(ranged.values if ranged is not None else {})

    def _rate_roll_pitch_hand_over(self) -> None:
        """Rate path, yaw's relay still running: roll and pitch onto the onboard cascade now
        (:meth:`RatePath.hand_over_roll_pitch`), then the sequence flies attitude set points
        for the side tests, as on the attitude path, yaw's relay going on beside them."""
        seq, rate = self.seq, self.rate
        assert seq is not None and rate is not None and self.driver is not None
        self._rate_roll_pitch_values()
        rate.hand_over_roll_pitch(ParamClient(self.link), self._hold, lambda: seq.tilt_cmd)
        seq.config = dataclasses.replace(seq.config, actuation=Actuation.ATTITUDE)
        self.driver.autopilot_attitude_note = ("tuned on the rate path and written at its "
                                               "hand-over; the side test flew on the written "
                                               "gains")

    def _rate_inner_hand_over(self) -> None:
        """Rate path: the identified roll and pitch gains into the onboard cascade now (the
        rest of the test parameters restored with them; roll and pitch already there where
        they went ahead of yaw), then the sequence flies attitude set points for the side
        tests, as on the attitude path."""
        seq, rate = self.seq, self.rate
        assert seq is not None and rate is not None
        if not rate.rp_onboard:
            self._rate_roll_pitch_values()
        rate.hand_over(ParamClient(self.link), self._hold)
        seq.config = dataclasses.replace(seq.config, actuation=Actuation.ATTITUDE)
        assert self.driver is not None
        self.driver.autopilot_attitude_note = ("tuned on the rate path and written at its "
                                               "hand-over; the side test flew on the written "
                                               "gains")
        self.notes.append(
            "rate path: roll and pitch gains written as soon as both were identified, as "
            "identified where they keep their margin on ArduCopter's cascade (its gyro filter "
            "in, the least plausible GCS delay out), or re-designed there with rate D where "
            "that lowers the ISE; "
            "the side tests flew attitude set points on them")

    def _hold(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            time.sleep(0.02)
            self._check_stream()

    def _write_back(self, client: ParamClient) -> None:
        seq = self.seq
        assert seq is not None
        identified, delay = {}, {}
        retargets: dict[Loop, Retarget] = {}
        design = {lp: t.identification for lp, t in seq.loops.items()
                  if t.state is LoopState.TUNED and t.identification is not None}
        # (the rate path writes roll and pitch on its own cascade design, from the identified)
        handed = self.rate is not None and self.rate.handed_over
        if Loop.ROLL in design and Loop.PITCH in design and not handed:
            r0, p0 = design[Loop.ROLL], design[Loop.PITCH]
            design[Loop.ROLL], design[Loop.PITCH] = pooled_attitude(r0, p0)
            if design[Loop.ROLL] is not r0:
                self.notes.append(pooled_note(r0, p0, design[Loop.ROLL]))
        self.design = design
        for lp, t in seq.loops.items():
            if t.state is not LoopState.TUNED or t.identification is None:
                continue
            if self.rate is not None and self.rate.handed_over and lp in _ATTITUDE_LOOPS:
                continue  # written at the rate path's hand-over (self.written holds them)
            if lp not in self.requested:
                t.note = (f"{NOT_REQUESTED}: identified (the ground station flew the tests on "
                          f"it) but not written; the report's gains are the identified ones")
                continue
            identified[lp] = t.identification.gains
            rt = self._retarget(lp, design[lp], t.snapshot)
            delay[lp], retargets[lp] = rt.delay_s, rt
            self.written[lp] = rt.gains
            self.retargets[lp] = rt
            if rt.d_over_p_s > 0:
                self.d_over_p[lp] = rt.d_over_p_s
        side_notes = []
        side_loops: dict[Loop, SideLoop] = {}
        for lp, inner_lp in SIDE_INNER.items():
            # flown behind the written attitude gains, not the GCS's PD it was identified behind
            inner, ident = seq.loops[inner_lp].identification, seq.loops[lp].identification
            if (lp in self.written and inner_lp in retargets and inner is not None
                    and ident is not None and self.gcs_delay_s is None):
                st = self.structure.get(inner_lp)
                side_loops[lp] = SideLoop(ident, design.get(inner_lp, inner), retargets[inner_lp],
                                          st.target_hz if st else None, st.d_hz if st else 0.0)
        if side_loops:
            # x and y share the autopilot's position and velocity P: one PD designed for both
            shared = shared_side_gains(
                list(side_loops.values()),
                onboard_extra_s=onboard_extra_delay_s(Loop.X, self.position_loop.hz))
            for i, lp in enumerate(side_loops):
                self.written[lp] = shared[i].gains
                side_notes.append(f"{lp.value} {shared[i].note()}")
            if len(side_loops) > 1:
                side_notes.append("one PD for both (they share the autopilot's parameters): "
                                  "the smaller gains, raised only as far as the faster loop "
                                  "needs")
        moved = [lp for lp, g in identified.items() if self.written[lp] != g
                 and lp not in SIDE_INNER]
        self.delays.update({lp: delay[lp] for lp in moved})  # the rate path's kept
        if moved:
            if self.gcs_delay_s is not None:
                how = (f"{', '.join(f'{lp.value} {delay[lp] * 1e3:.1f} ms' for lp in moved)} "
                       f"less delay, as asked")
            else:
                how = ("less delay by how old telemetry was when the command answering it "
                       "left; " + "; ".join(f"{lp.value} {retargets[lp].note()}"
                                            for lp in moved))
            self.notes.append(
                f"written {', '.join(lp.value for lp in moved)} gains are re-targeted from the "
                f"GCS-side loop to the onboard loop ({how}); the report's gains are the "
                f"written ones")
        if side_notes:
            self.notes.append("written side gains: " + "; ".join(side_notes))
        for lp, inner_lp in SIDE_INNER.items():
            if (lp in self.written and inner_lp not in self.requested
                    and seq.loops[inner_lp].state is LoopState.TUNED):
                self.notes.append(
                    f"{lp.value} was identified behind the GCS's {inner_lp.value} PD, which is "
                    f"not written ({NOT_REQUESTED}): on the autopilot's own {inner_lp.value} "
                    f"gains the written {lp.value} gains hold only as far as the two agree")
        gains = {lp: PDGains(g.Kc, g.Kd) for lp, g in self.written.items()}
        models = {}
        alt_ident = seq.loops[Loop.ALTITUDE].identification
        if Loop.ALTITUDE in gains and alt_ident is not None and isinstance(alt_ident.model,
                                                                             InnerModel):
            # the cascade is matched on the onboard loop: the GCS delay taken out, as above
            m = alt_ident.model
            models[Loop.ALTITUDE] = dataclasses.replace(
                m, tau=max(m.tau - self.delays.get(Loop.ALTITUDE, 0.0), 1e-4))
        try:
            ranged = params_in_range(self.prof, gains, self.hover, models)  # as dry-run does
        except UsageError as err:
            if not models:
                raise
            # the other loops' gains still go in; the vehicle keeps its own altitude gains
            self.notes.append(f"altitude gains not written: {err}")
            gains.pop(Loop.ALTITUDE)
            self.written.pop(Loop.ALTITUDE, None)
            ranged = params_in_range(self.prof, gains, self.hover)
        self.notes.extend(ranged.notes)
        values = {**ranged.values, **rate_d_values(self.prof, ranged.gains, self.d_over_p)}
        if self.rate is not None:  # the attitude gains go in with the rate path's hand-over
            values = self.rate.split(values)
        if not values:
            return
        result = client.write(values, self.backup_dir, label="backup")
        self.changes, self.backup = result.changes, str(result.backup_path)
        self._check_stream()

    def _verify_written(self, client: ParamClient) -> None:
        """The in-air check of the written roll and pitch gains (:mod:`mrft_gcs.flight.inair`).

        Each loop is measured on the autopilot's own loop. Within the band
        [:data:`PASS_PM_DEG`, :data:`PM_HIGH_DEG`] (a loop designed at the margin: up to its
        prediction plus :data:`AGREE_DEG`, :func:`tighten_above`) it is done. Outside it, its
        gains are re-designed on the measured loop (an unsteady loop gets the ground-station
        loop's gains back), written and checked again, up to :data:`CHECK_ROUNDS` checks in all.
        Then the gains whose check came nearest the design's 20 deg among those that passed
        stay written; where none passed, the vehicle lands."""
        on_rate = self.rate is not None and self.rate.handed_over and RATE_INAIR_CHECK
        if self.act is not Actuation.TORQUE and not on_rate:
            return  # the autopilot keeps its own attitude gains: nothing written to check
        plans: dict[Loop, CheckPlan] = {}
        cascades: dict[Loop, OnboardCascade] = {}
        for i, lp in enumerate(_ATTITUDE_LOOPS):
            if on_rate:  # ArduPilot's cascade with the written gains, as restored
                assert self.rate is not None
                cascades[lp] = rate_check_cascade(self.rate.cascade(client, i))
            elif lp in self.d_over_p and lp in self.structure:
                # rate D written: the check predicts and inverts through the structure it
                # closes (its rate-target and D filters), as the design did
                st = self.structure[lp]
                cascades[lp] = OnboardCascade(st.target_hz, target_rate_ff=False,
                                              d_over_p_s=self.d_over_p[lp], d_filter_hz=st.d_hz)

        def plan_for(lp: Loop, model: InnerModel, gains: PD) -> CheckPlan:
            # a rate-target filter read is ArduPilot's cascade: its square-root angle P wants
            # the smaller wave (the rate path zeroes its acceleration limits instead)
            st = self.structure.get(lp)
            amp = (RATE_CHECK_AMPLITUDE_RAD if on_rate
                   else probe_amplitude(st.target_hz if st is not None else 0.0))
            plan = plan_check(model, gains, amp, cascade=cascades.get(lp))
            if not on_rate:
                return plan
            return dataclasses.replace(plan, cycles=max(plan.cycles, math.ceil(
                RATE_CHECK_SPAN_S / plan.period_s)))
        for lp in _ATTITUDE_LOOPS:
            ident = self.seq.loops[lp].identification if self.seq else None
            ident = self.design.get(lp, ident)  # the model the written gains were designed on
            gains = self.written.get(lp)
            if ident is None or gains is None or not isinstance(ident.model, InnerModel):
                continue
            m = ident.model
            model = dataclasses.replace(m, tau=max(m.tau - self.delays.get(lp, 0.0), 1e-4))
            try:
                plans[lp] = plan_for(lp, model, gains)
            except ValueError as err:
                self.verification[lp] = Verification(
                    _CHECK_METHOD, False, note=f"{err} (Kc {gains.Kc:.3g}, Kd {gains.Kd:.3g}; "
                    f"{cascades[lp].describe() if lp in cascades else 'plain PD'})")
                if on_rate:  # the check's linear angle P would let it diverge: land now
                    raise SafetyAbort(f"{lp.value}: the written gains are unstable on "
                                      f"ArduPilot's cascade as predicted ({err}); landing "
                                      f"commanded, the vehicle's own gains back") from err
        history: dict[Loop, list[tuple[CheckPlan, InAirCheck]]] = {lp: [] for lp in plans}
        on_structure: set[Loop] = set()  # loops tightened on their rate-target filter
        started = time.monotonic()
        for n in range(CHECK_ROUNDS):
            if not plans:
                break
            nxt: dict[Loop, CheckPlan] = {}
            for lp, (plan, check) in self._probe(plans).items():
                history[lp].append((plan, check))
                # a loop through a rate-target low-pass (read from the vehicle) whose design on
                # that filter would do better on the loop measured is tightened within the band
                hz = (self.structure[lp].target_hz if STRUCT_TIGHTEN_LIVE and not on_rate
                      and lp in self.structure else 0.0)
                tighter = (hz > 0 and check.passed and check.measured_pm_deg <= PM_HIGH_DEG
                           and structured_redesign(plan, check, hz)[1] >= STRUCT_TIGHTEN_GAIN)
                if tighter:
                    on_structure.add(lp)
                # a loop with rate D sits under its gain cap, not at the margin: not tightened
                # (nor on the rate path: its gains are the identified ones, capped on the
                # cascade, not designed at the margin); one at the margin is where it measures
                # more than predicted (the onboard delay pinned shorter than designed for)
                high = tighten_above(plan.predicted_pm_deg,
                                     rate_d=lp in self.d_over_p or on_rate)
                # a margin over the band that only a gain under the model's gives is not
                # tightened on (a torque command riding its limits reads as one)
                basis = (without_gain_deficit(plan, check)
                         if check.passed and check.measured_pm_deg > high else check)
                if (check.passed and basis.measured_pm_deg <= high and not tighter) or (
                        n + 1 == CHECK_ROUNDS):
                    continue
                if check.steady:
                    model = basis.corrected_model(plan)
                    new = redesigned_gains(plan, basis, target_hz=hz)
                else:
                    # no steady response, no model to correct: the gains of the ground-station
                    # loop, which carried more delay than the onboard one
                    ident = self.seq.loops[lp].identification if self.seq else None
                    assert ident is not None and isinstance(ident.model, InnerModel)
                    model, new = ident.model, ident.gains
                try:
                    nxt[lp] = plan_for(lp, model, new)
                except ValueError:
                    continue  # no loop to predict on the model measured: nothing to re-check
                self.written[lp] = new
            if nxt:
                self._rewrite(client, {lp: self.written[lp] for lp in nxt})
            plans = nxt
        rounds = max((len(t) for t in history.values()), default=0)
        self.notes.append(f"in-air check of the written roll and pitch gains: {rounds} "
                          f"check{'s' if rounds > 1 else ''}, {time.monotonic() - started:.1f} s "
                          f"after the write (not in the time to tune)")
        back: dict[Loop, PD] = {}
        kept: dict[Loop, tuple[CheckPlan, InAirCheck]] = {}
        for lp, tried in history.items():
            passed = [(p, c) for p, c in tried if c.passed]
            if not passed:
                plan, check = tried[-1]
                self.verification[lp] = Verification(
                    _CHECK_METHOD, False, check.predicted_pm_deg, check.measured_pm_deg,
                    f"{_story(tried)}; landed", _check_note(plan, check))
                raise SafetyAbort(
                    f"{lp.value}: none of the gains tried kept {PASS_PM_DEG:.0f} deg of phase "
                    f"margin measured in the air ({_story(tried)}); landing commanded (restore "
                    f"the backup {self.backup})")
            # tightened on the structure: the last gains that passed (their plain margin reads
            # near 20 deg either way; the ISE is what was gained); else nearest the design's 20
            plan, check = (passed[-1] if lp in on_structure else
                           min(passed, key=lambda pc: abs(pc[1].measured_pm_deg - 20.0)))
            kept[lp] = (plan, check)
            if plan.gains != self.written[lp]:
                back[lp] = self.written[lp] = plan.gains
            self.verification[lp] = _verified(plan, check, _story(tried, plan))
        # x and y are flown behind pitch and roll: where the check changed those, the side
        # gains must keep their margin behind the gains kept, on the attitude plant measured
        sides = []
        for lp, inner_lp in SIDE_INNER.items():
            side_id = self.seq.loops[lp].identification if self.seq else None
            first = self.retargets.get(inner_lp)
            if (inner_lp in kept and lp in self.written and first is not None
                    and side_id is not None and isinstance(side_id.model, SideModel)):
                g = side_behind_checked(self.written[lp], side_id.model, first.gains,
                                        *kept[inner_lp])
                if g != self.written[lp]:
                    self.written[lp] = g
                    sides.append(lp)
        if sides:
            self.notes.append(
                f"written side gains: {', '.join(lp.value for lp in sides)} re-designed behind "
                f"the attitude gains the in-air check kept (short of "
                f"{SIDE_PM_MIN_DEG:.0f} deg behind them on the attitude plant it measured)")
            # x and y share the autopilot's parameters (the more cautious of the two)
            back.update({lp: self.written[lp] for lp in SIDE_INNER if lp in self.written})
        if back:
            self._rewrite(client, back)

    def _probe(self, plans: dict) -> dict:
        """Fly the square waves of ``plans`` and return ``{loop: (plan, InAirCheck)}``."""
        assert self.streamer is not None
        on_rate = self.rate is not None
        probe = SquareWaveProbe(plans, self._probe_centre(),
                                swing_limit=RATE_CHECK_SWING if on_rate else None,
                                settle_s=RATE_CHECK_SETTLE_S if on_rate else 0.0)
        # the heading held through the check: the one flown now (a fresh reader has none)
        s = self.vehicle.telemetry.latest() if self.vehicle is not None else None
        self.probe_yaw = s.yaw_rad if s is not None else (self.seq.yaw_ref if self.seq else 0.0)
        small = (self.rate.small_signal(ParamClient(self.link)) if self.rate is not None
                 else contextlib.nullcontext())
        if on_rate:
            # the input shaping is switched off and back with the vehicle at rest on the
            # centre, brought there with it on: a set point step while it is off gives the
            # onboard target 100/s x the step of rate, which the acceleration limit, once
            # back, carries on for tens of degrees (a 3.5 deg step went on to 30 deg)
            self.probe_hold = probe.centre
            time.sleep(RATE_CHECK_LEAD_S)
        try:
            with small, self.link.subscribe(AttitudeSetpoint) as tracked:
                asked = self._ask_setpoints(self.rate_hz)
                self.probe = probe
                try:
                    end = time.monotonic() + probe.duration_s + 2.0
                    while not probe.done:
                        if time.monotonic() > end:
                            raise LinkError("the in-air check of the written gains got no "
                                            "telemetry: check the link")
                        time.sleep(0.02)
                        while (sp := tracked.get(0.0)) is not None:
                            if isinstance(sp, AttitudeSetpoint):
                                probe.track(sp.t_s, sp.roll_rad, sp.pitch_rad)
                        self._check_stream()
                        if probe.swing_over is not None:
                            # the abort restores the vehicle's own gains before the landing
                            lp, swing = probe.swing_over
                            raise SafetyAbort(
                                f"in-air check: {lp.value} swung {math.degrees(swing):.1f} deg "
                                f"off its centre on a "
                                f"{math.degrees(probe.plans[lp].amplitude):.1f} deg square wave "
                                f"(limit {RATE_CHECK_SWING:g}x): the written gains ring; the "
                                f"vehicle's own gains back, landing commanded")
                finally:
                    self.probe = None
                    if asked:  # the rate path keeps the stream it aligns its rates with
                        self._ask_setpoints(RATE_STREAM_HZ if self.rate is not None else 0.0)
        finally:
            self.probe_hold = None
        if self.rate is not None:  # each edge timed on the vehicle's record of its target
            points, how = rate_check_points(probe)
            probe.used_tracked = {lp: lp in points for lp in how}
            points = {lp: points.get(lp, (np.ones(1), np.ones(1, complex), np.full(1, np.inf)))
                      for lp in how}
            source = how
        else:
            points = probe.points(link_delay_s=_round_trip_s(self.quality))
            source = {lp: ("the set point the vehicle reported tracking (ATTITUDE_TARGET)"
                           if used else "the set point as sent")
                      for lp, used in probe.used_tracked.items()}
        out = {lp: (plans[lp], dataclasses.replace(check_margin(plans[lp], *points[lp]),
                                                   source=source[lp])) for lp in points}
        for lp, used in probe.used_tracked.items():
            if self.rate is not None and not used:
                # ArduPilot shapes the set point sent before it tracks it: only its own
                # record is the loop's input; without one the loop is not measured
                plan, chk = out[lp]
                out[lp] = (plan, dataclasses.replace(
                    chk, se=np.full_like(chk.se, np.inf),
                    source=chk.source if chk.source.startswith("none") else
                    "none: ATTITUDE_TARGET did not cover the cycles (the set point sent is "
                    "shaped onboard before the loop)"))
        return out

    def _probe_centre(self) -> tuple[float, float]:
        """Roll and pitch set points (rad) about which the check flies: where the written
        loops hold the vehicle level. The x/y hold is off through the check; about a plain
        level the written loops (no rate integrator) lean by their torque bias over Kc, some
        1 deg, and the vehicle drifts; the hold's command then grows and the hover after the
        check starts on that step, caught by the hand-over to position mode the later, the
        more it has tilted (docs/writing-gains.md). Not the hold's own command: averaged, it
        lags a hover still swinging, and a check centred on it flew the vehicle away."""
        seq = self.seq
        if seq is None or self.act is not Actuation.TORQUE:
            return 0.0, 0.0  # the autopilot's own loop flew the hover: no trim to carry
        out = []
        lim = seq.config.max_tilt_cmd_rad  # as the hold's own command
        for lp in _ATTITUDE_LOOPS:
            pd, g = seq.loops[lp].pd, self.written.get(lp)
            c = probe_centre(0.0, pd.trim, g.Kc) if pd is not None and g is not None else 0.0
            out.append(min(lim, max(-lim, c)))
        return out[0], out[1]

    def _ask_setpoints(self, rate_hz: float) -> bool:
        """Ask for ATTITUDE_TARGET (the set point the vehicle tracks) at ``rate_hz``, or back
        to its default with 0; False where the vehicle refuses (the check then times the
        set points as sent)."""
        return self.link.ask_message_interval(ATTITUDE_TARGET_ID, rate_hz)

    def _rewrite(self, client: ParamClient, gains: dict[Loop, PD]) -> None:
        ranged = params_in_range(self.prof, {lp: PDGains(g.Kc, g.Kd) for lp, g in gains.items()},
                                 self.hover)
        values = {**ranged.values, **rate_d_values(self.prof, ranged.gains, self.d_over_p)}
        if self.rate is not None and self.rate.handed_over:
            values = self.rate.keep_integrator_zero(values)
        result = client.write(values, self.backup_dir, label="backup-recheck")
        first = {c.name: c for c in self.changes}
        merged = {c.name: c for c in self.changes}
        # after the rate path's hand-over its gains are its changes (added at the end)
        done = self.rate.rewritten(result.changes) if self.rate is not None else result.changes
        for c in done:  # the old value stays the one from before the tune
            merged[c.name] = ParamChange(c.name, first[c.name].old if c.name in first else c.old,
                                         c.new)
        self.changes = tuple(merged.values())
        self._check_stream()

    def _retarget(self, lp: Loop, ident: Identification, snap: CycleSnapshot | None
                  ) -> Retarget:
        """``lp``'s written gains and the delay re-targeted out of them: as asked, else
        measured over its identified cycles on the session's clock model, checked for
        plausibility, and held back where the gains would lose their margin over what is
        plausible (:func:`mrft_gcs.flight.onboard.robust_onboard_gains`)."""
        period = 1.0 / self.rate_hz
        if self.gcs_delay_s is not None:
            d = self.gcs_delay_s
            gcs = measure_gcs_delay([], period)
            return Retarget(onboard_gains(ident, d), d if d > 0 else 0.0, math.nan, gcs)
        gcs = self._gcs_delay(lp, snap)
        rt = robust_onboard_gains(ident, gcs, onboard_extra_s=onboard_extra_delay_s(
            lp, self.position_loop.hz))
        return structured_retarget(ident, rt, self.structure.get(lp, OnboardStructure()))

    def _gcs_delay(self, lp: Loop, snap: CycleSnapshot | None) -> GcsDelay:
        """``lp``'s GCS delay measured over its identified cycles on the session's clock
        model, checked for plausibility (:func:`mrft_gcs.flight.onboard.measure_gcs_delay`)."""
        period = 1.0 / self.rate_hz
        clock = self.clock.model.fit()
        t, ages = np.empty(0), np.empty(0)
        if snap is not None and len(snap.t_s):
            t, ages = self.ages.ages_s(lp is Loop.ALTITUDE, float(snap.t_s[0]),
                                       float(snap.t_s[-1]), clock)
        rtt, q = _round_trip_s(self.quality), self.quality
        spread = 1e-3 * (q.rtt_p90_ms - q.rtt_p50_ms) if rtt > 0 and q is not None else 0.0
        return measure_gcs_delay(ages, period, sample_t_s=t, clock=clock, latency_s=0.5 * rtt,
                                 round_trip_s=rtt, round_trip_spread_s=spread)

    def _hand_over(self) -> None:
        """Switch to the autopilot's position mode, stop streaming, check it hovers."""
        seq, link = self.seq, self.link
        assert seq is not None and self.streamer is not None and self.monitor is not None
        if self.rate is not None:
            staged = self.rate.hand_over(ParamClient(link), self._hold)
            if staged:
                self.changes = self.changes + staged
                self.backup = self.rate.merged_backup(self.backup)
        self.mode_watch = None  # the tool leaves offboard itself from here
        assert self.vehicle is not None
        self.vehicle.set_mode(VehicleMode.POSITION)
        self.vehicle.close()  # the stream stops: the autopilot flies on the written gains
        seq.finish(Phase.DONE)
        telemetry = _Telemetry(link)
        end = time.monotonic() + self.hover_check_s
        worst = 0.0
        held: tuple[float, float, float] | None = None  # where position mode was entered
        states: list[FlightState] = []
        while time.monotonic() < end:
            s = telemetry.poll()
            if link.telemetry_age_s() > 0.5:
                link.land(wait_ack=False)
                raise SafetyAbort("telemetry lost after the hand-over to position mode; "
                                  "landing commanded")
            if s is not None:
                reason = self.monitor.violation(s, duration=False)
                if reason is not None:
                    link.land(wait_ack=False)
                    mode = self.prof.modes["position"].name
                    raise SafetyAbort(f"on the written gains in {mode}: {reason}; landing "
                                      f"commanded (restore the backup {self.backup})")
                # position mode holds where it was entered (PX4 and ArduPilot alike), not
                # the take-off point the relays oscillated about: the check is how still the
                # vehicle stays on the written gains, not where the tests left it
                here = (s.x_m, s.y_m, s.z_up_m)
                held = here if held is None else held
                worst = max(worst, math.dist(here, held))
                states.append(s)
            time.sleep(0.02)
        self.hover_error_m = worst
        # ``ok`` needs the vehicle airborne and steady over the whole window: a vehicle that
        # hit the ground in the hand-over also keeps still (2.9 m off, 28.5 deg seen)
        self.hover_check = check_hover_states(states, self.monitor.origin[2])
        if not self.hover_check.passed:
            link.land(wait_ack=False)
            mode = self.prof.modes["position"].name
            raise SafetyAbort(f"hover check on the written gains in {mode} failed: "
                              f"{self.hover_check.reason}; landing commanded (restore the "
                              f"backup {self.backup})")

