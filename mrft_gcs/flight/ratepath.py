"""The body-rate path (``--actuation rate``): all five loops through a stock autopilot.

ArduCopter has no torque input over MAVLink, but its rate loop adds a feed-forward term to
P/I/D. With P = I = D = 0, angle P = 0, no acceleration limit, no target filter and
feed-forward ``k`` (the profile's ``[rate_path]``), a body-rate set point ``w`` of
SET_ATTITUDE_TARGET (attitude ignored) comes out as the normalised command ``k w``. The
sequence's torques ``u`` are therefore sent as rates ``u / k``.

Two things stand between the rate sent and the torque that comes out, and both are
measured in flight:

* ``k``: ArduPilot's PID_TUNING reports per axis the desired rate and the output's FF, P,
  I and D terms (``GCS_PID_MASK``). ``FF / desired`` is the ``k`` in effect; P, I and D
  must stay zero. A ``k`` off by more than :data:`K_CORRECT` is corrected (the rates are
  scaled), by more than :data:`K_REFUSE` refused (the tune stops and lands).
* Alignment: the onboard attitude target integrates the commanded rates open loop, and the
  feed-forward is rotated from that target into the body frame (scaled down above 30 deg
  of target-to-body thrust angle). The target is read from ATTITUDE_TARGET and every rate
  sent is pre-rotated by the inverse, so the body gets the torque asked for; beyond
  :data:`MAX_THRUST_ERROR_DEG` the tune stops and lands.

The test parameters are written only after arming (arming checks see the stock gains:
none is switched off), backed up first. The hand-over back to onboard control is staged
while the ground station flies: rate P first (its effect is inverted in the rates sent),
then the feed-forward, then the rates go to zero, the onboard attitude target is set onto
the body, and the written angle P and every other test parameter go in at once
(:meth:`RatePath.hand_over`). On any abort the test
parameters are restored *before* the landing command (a landing on zero gains would tumble).

Roll and pitch go onto the onboard cascade the moment both are identified
(:meth:`RatePath.hand_over_roll_pitch`, the same stages on their parameters alone), while
yaw's relay test goes on through the rate feed-forward: the set point from then on is the
sequence's roll/pitch attitude with yaw's rate as the body-rate feed-forward
(:data:`HAND_ROLL_PITCH_FIRST`). Yaw's hand-over then writes the rest.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mrft_gcs.domains import D_ATT
from mrft_gcs.errors import LinkError, MrftError, SafetyAbort, UsageError
from mrft_gcs.flight.controllers import FlightState, YawHold
from mrft_gcs.flight.inair import OnboardCascade, SquareWaveProbe, harmonic_points
from mrft_gcs.flight.onboard import CascadeGains, cascade_gains, rate_loop_gains
from mrft_gcs.flight.phases.state import CycleSnapshot
from mrft_gcs.flight.phases.yaw import YawOutcome, YawRelay, YawState
from mrft_gcs.flight.source import Setpoint
from mrft_gcs.flight.structure import (
    DEFAULT_D_HZ,
    RATE_D_OVER_P_S,
    WRITE_RATE_D,
    OnboardStructure,
    cascade_design,
)
from mrft_gcs.identify import Identification
from mrft_gcs.link.failsafe import rate_path_guard
from mrft_gcs.link.firmware import Firmware
from mrft_gcs.link.vehicle import VehicleLink
from mrft_gcs.loops import Loop
from mrft_gcs.params import (
    Param,
    ParamChange,
    ParamClient,
    read_params_file,
    write_params_file,
)
from mrft_gcs.pd_design import PD
from mrft_gcs.plant import InnerModel
from mrft_gcs.profiles import AutopilotProfile, RatePathParams
from mrft_gcs.telemetry import (
    ActuatorTarget,
    AttitudeSetpoint,
    AttitudeTarget,
    AutopilotFamily,
    PidTuning,
    RateTarget,
    quat_from_euler,
)

__all__ = ["RatePath", "RateChannel", "FeedForwardCheck", "Alignment", "alignment",
           "check_feed_forward", "rate_path_refusal", "body_rates", "LINK_LOSS_GUARD",
           "K_CORRECT", "K_REFUSE", "MAX_THRUST_ERROR_DEG", "GCS_PD_SCALE", "TARGET_SET_PARAM",
           "CHECK_PARAMS", "CHECK_SPAN_S", "CHECK_AMPLITUDE_RAD", "CHECK_SWING", "CHECK_SETTLE_S",
           "CHECK_LEAD_S", "INAIR_CHECK", "check_cascade", "check_points", "EDGE_TICK_S",
           "TUNE_YAW", "RATE_I_DECADE", "GYRO_FILTER_PARAM",
           "YAW_RATE_I_DECADE", "YAW_AFTER_ROLL_PITCH_S", "RING_RMS_RAD_S", "yaw_wait_over",
           "HAND_ROLL_PITCH_FIRST", "roll_pitch_names", "beside_yaw",
           "YawDesign",
           "yaw_design", "yaw_names"]

#: relative error of the measured ``k`` above which the rates are scaled to it
K_CORRECT = 0.02
#: ... and above which the tune is refused (a rate loop that is not what was written)
K_REFUSE = 0.25
#: P, I or D output (normalised) that shows the rate loop is not pure feed-forward
PID_ACTIVE = 1e-3
#: target-to-body thrust angle that stops the tune (ArduPilot scales the feed-forward
#: down from 30 deg and drops it at 60)
MAX_THRUST_ERROR_DEG = 28.0
#: PID_TUNING samples with a feed-forward output above this (normalised) measure ``k``
MIN_FF = 0.01
#: samples per axis before ``k`` is judged
MIN_SAMPLES = 25
#: ATTITUDE_TARGET and PID_TUNING rates asked for (Hz)
STREAM_HZ = 50.0
#: largest target-to-body thrust angle and heading difference accepted on the ground before
#: the take-off (ArduCopter resets the target to the body while landed; a target left from
#: an earlier flight, 84 deg off after a crash, spun the SITL at the take-off)
GROUND_ALIGNMENT_DEG = (5.0, 10.0)
#: hold between the hand-over's stages (s): each stage's transient settles
STAGE_HOLD_S = 0.3
#: ArduCopter's switch of the rate feed-forward (the attitude target's own rate). Off, an
#: attitude set point becomes the onboard target at once instead of being shaped towards
#: it: the hand-over sets the target onto the body that way before angle P comes back (the
#: target integrated the rates sent open loop and drifted off the body; angle P would snap
#: the vehicle there under the altitude relay: docs/ardupilot.md)
TARGET_SET_PARAM = "ATC_RATE_FF_ENAB"
#: how long the body's own attitude is sent as the target before angle P is written (s):
#: a dozen set points at 250 Hz, so that one has surely been applied
ALIGN_HOLD_S = 0.05
#: factor on the identified roll/pitch PDs while the ground station flies them on this
#: path (``SequenceConfig.gcs_attitude_pd_scale``: on Kd, its square on Kc; the written
#: gains are not scaled). The designed PD keeps ~17 deg of phase margin at a ~70 rad/s
#: crossover on ArduCopter SITL's quad; the GCS loop's stream jitter and telemetry lag took
#: it unstable at full gain (roll diverged within 0.2 s). Both gains halved, 8 ms of delay
#: more than identified left 0-18 deg (identified models of five runs), and pitch rang at
#: 200 deg/s rms beside the yaw relay; Kd halved and Kc quartered leaves 18-41 deg
GCS_PD_SCALE = 0.5
#: the yaw hold's output limit on this path (normalised yaw command)
YAW_LIMIT = 0.5
#: yaw is relay-tested next to roll and pitch and written at the hand-over (off: held on
#: the vehicle's own yaw gains throughout, which are restored)
TUNE_YAW = True
#: the identified yaw model's (T_prop, T1, tau) may lie this factor outside the attitude
#: classifier's domain (its scale search reaches a little past the box) before yaw is
#: refused as out of the domain
YAW_DOMAIN_SLACK = 2.0
#: a drag time constant past the domain is accepted where the domain's edge model's drag
#: pole differs from the identified one by less than this phase at the crossover (deg)
YAW_T1_PHASE_DEG = 5.0
#: ArduCopter's yaw rate loop low-passes its error (``ATC_RAT_YAW_FLTE``, 2.5 Hz by default),
#: a lag the identified PD (designed without it) may not survive: the written filter is the
#: vehicle's own raised in steps of this factor up to the cap (Hz) until it does
YAW_FLTE_STEP = 1.25
YAW_FLTE_MAX_HZ = 40.0
#: ... i.e. until the scale the cascade check leaves the gains is this share of the scale
#: they keep with no error filter at all
YAW_FLTE_KEEP = 0.95
#: the in-air check of the written roll/pitch gains flies on this path (off: on ArduCopter
#: SITL what it measures at the written loops' 85-130 rad/s crossovers fits no linear model
#: of the cascade, 17-56 deg of phase from the prediction, and written loops predicted at PM
#: 38-48 deg rang at 21 Hz with a motor at its minimum, which the cascade model, without the
#: rate loop's gyro low-pass, does not predict: docs/ardupilot.md; the gains are checked on
#: the cascade's model at the hand-over instead, :func:`mrft_gcs.flight.onboard.rate_loop_gains`)
INAIR_CHECK = False
#: set while the in-air check flies (restored after it): ArduCopter's angle P runs through a
#: square-root controller that is linear only below (accel/2)/P^2 of error (0.2-0.5 deg at
#: the written angle P 35-49), and the set point sent is shaped (ATC_INPUT_TC, the
#: acceleration limit) before it becomes the target. With no acceleration limit the angle
#: P is linear (the small-signal loop flown, exactly) and the shaping a 10 ms lag, so a
#: 2 deg square wave measures the written loop; the input is ATTITUDE_TARGET either way.
#: The target's own rate is not fed forward either (:data:`TARGET_SET_PARAM` 0: the set point
#: becomes the target as it comes): with it, the closed loop from the target is near 1 at the
#: crossover whatever the plant, and inverting it for the plant read margins of 108-120 deg
#: on loops predicted at 54; without it the loop's feedback path, which alone sets the margin,
#: is what the square wave measures (:func:`check_cascade`)
CHECK_PARAMS = {"ATC_ACCEL_R_MAX": 0.0, "ATC_ACCEL_P_MAX": 0.0, "ATC_INPUT_TC": 0.0,
                TARGET_SET_PARAM: 0.0}
#: the in-air check's measured cycles span at least this on this path (s): crossovers of
#: 60-90 rad/s give 3 cycles of 0.2-0.3 s, too few ATTITUDE_TARGET samples at 250 Hz
CHECK_SPAN_S = 1.0
#: the in-air check's square wave on this path (rad): the check flies with angle P linear
#: (:data:`CHECK_PARAMS`), nothing bounds a swing that grows; 1 deg (half the torque
#: path's) keeps a 20 deg loop's resonance near 3 deg
CHECK_AMPLITUDE_RAD = math.radians(1.0)
#: a swing off the check's centre past this many square-wave amplitudes stops the check
#: (the vehicle's own gains back, landing): a loop at the 15 deg floor peaks at ~3.8x,
#: one left to grow flipped ArduCopter SITL at the tilt limit
CHECK_SWING = 5.0
#: the check's centre held this long after its last square wave, before :data:`CHECK_PARAMS`
#: are put back (s): with no input shaping the onboard target's rate is 1/0.01 s times the
#: set point's error, and the shaping put back in the middle of a swing carried the target
#: on to 49 deg of pitch on ArduCopter SITL (the tilt limit then landed it)
CHECK_SETTLE_S = 0.5
#: the check's centre flown this long, the input shaping still on, before :data:`CHECK_PARAMS`
#: go in (s): the sequence's own set point (the x/y hold's lean) may lie degrees off the centre,
#: and the shaping (ATC_INPUT_TC 0.15 s by default) brings the vehicle there smoothly; the
#: shaping is put back with the centre still held (the check's settle)
CHECK_LEAD_S = 0.5
#: roll/pitch: the written rate I's zero sits this factor below the written loop's crossover
#: on the cascade (0: rate I written 0, the identified PD alone). With P alone the rate loop
#: leaves a rate error wherever the body must be held against a torque or the target's
#: rate feed-forward asks for a rate the drag resists; the I removes it at the cost of
#: atan(1/10) = 6 deg of phase at the crossover (the gains scaled down where that takes
#: the margin below 15 deg: :func:`~mrft_gcs.flight.onboard.rate_loop_gains`)
RATE_I_DECADE = 10.0
#: ArduCopter's gyro low-pass (Hz, second order): the rate loop closes on the filtered gyro,
#: the angle loop on the AHRS attitude, so its lag sits in the rate feedback alone
GYRO_FILTER_PARAM = "INS_GYRO_FILTER"
#: yaw: the rate I's zero this factor below the written loop's crossover, as
#: :data:`RATE_I_DECADE` for roll and pitch (0: rate I written 0). With P alone the heading
#: keeps ``d / Kc`` of error under a yaw torque ``d`` (the motors' own torque imbalance,
#: a yaw-twisted frame); the I removes it
YAW_RATE_I_DECADE = 10.0
#: once roll and pitch are identified, yaw's relay gets this long more for a steady cycle
#: (s) before it gives up to the vehicle's own yaw gains (counted from the end of roll and
#: pitch's own hand-over where :data:`HAND_ROLL_PITCH_FIRST`): yaw's zero-gain window
#: closes only when yaw is done
YAW_AFTER_ROLL_PITCH_S = 4.0
#: roll and pitch go onto the onboard cascade (their written gains) as soon as both are
#: identified, yaw's relay going on beside them through the feed-forward; off: all three
#: are handed over together once yaw is done, roll and pitch on the ground station's PDs
#: meanwhile (they rang at 170-250 deg/s there beside the yaw relay at full gain)
HAND_ROLL_PITCH_FIRST = True
#: roll or pitch body-rate rms (rad/s, over :data:`RING_TAU_S`) on the ground station's PDs
#: that ends yaw's test at once, so that the hand-over puts roll and pitch on the onboard
#: loop: a PD that rings shakes the heading (no steady yaw cycle comes) and, left to ring,
#: flips the vehicle. Relay tests swing the body at 20-35 deg/s rms, the PDs at rest at
#: under 10; ringing ran at 100-230
RING_RMS_RAD_S = math.radians(80.0)
#: time constant of the body-rate rms (s), and how long after roll and pitch are both
#: identified it is first judged (their relays' last swings pass first)
RING_TAU_S = 0.25
RING_AFTER_S = 0.5
_ATTITUDE_TARGET_ID = 83
_PID_TUNING_ID = 194
_AXES = ("roll", "pitch", "yaw")

#: The link-loss guard installed once the gains are zero onboard (an ArduPilot Lua script
#: that restores the backed-up gains and lands: :mod:`mrft_gcs.link.failsafe`):
#: ``f(link, client, backup) -> note``. None: no guard; the report then says that link loss
#: in the zero-gain window is unprotected.
LINK_LOSS_GUARD: Callable[[VehicleLink, ParamClient, Path], str] | None = rate_path_guard


def rate_path_refusal(profile: AutopilotProfile, fw: Firmware) -> str | None:
    """Why the rate path cannot fly ``fw`` with ``profile``; None if it can.

    >>> from mrft_gcs.profiles import load_profile
    >>> rate_path_refusal(load_profile("ardupilot"),
    ...                   Firmware(AutopilotFamily.ARDUPILOT, 2, (4, 7, 0), "dev")) is None
    True
    >>> rate_path_refusal(load_profile("sitl"), Firmware(AutopilotFamily.PX4, 2))[:27]
    'profile sitl has no [rate_p'
    >>> rate_path_refusal(load_profile("px4"), Firmware(AutopilotFamily.PX4, 2))[:33]
    'PX4 (version not reported): the p'
    """
    if profile.rate_path is None:
        return (f"profile {profile.name} has no [rate_path] (the rate loop reduced to "
                f"feed-forward is spelled out for ArduCopter and PX4 only)")
    if fw.family is AutopilotFamily.PX4 and profile.family is AutopilotFamily.PX4:
        # PX4's channel is measured (docs/px4.md) but this sequence is ArduCopter's
        return (f"{fw.name}: the profile's [rate_path] channel is measured on PX4 SITL "
                f"(docs/px4.md) but the rate path's sequence is not built for PX4 (it flies "
                f"GUIDED_NOGPS, checks k on PID_TUNING and aligns ATTITUDE_TARGET; PX4 needs "
                f"OFFBOARD, k from its log and its own hand-over)")
    if fw.family is not AutopilotFamily.ARDUPILOT:
        return f"{fw.name}: the rate path is proven on ArduCopter only"
    return None


# ---------------------------------------------------------------------- rotation numerics
def _rotation(q: np.ndarray) -> np.ndarray:
    """3x3 matrix of the unit quaternion ``q`` (w, x, y, z)."""
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


@dataclass(frozen=True)
class Alignment:
    """The onboard attitude target against the body.

    Attributes
    ----------
    thrust_error_rad : float
        Angle between the target's and the body's thrust axes (rad).
    heading_error_rad : float
        Target yaw minus body yaw, wrapped to [-pi, pi] (rad).
    target_to_body : ndarray, shape (3, 3)
        Rotates a vector from the target frame into the body frame (what ArduPilot does to
        the feed-forward rate).
    """

    thrust_error_rad: float
    heading_error_rad: float
    target_to_body: np.ndarray


def alignment(target_rpy: tuple[float, float, float],
              body_rpy: tuple[float, float, float]) -> Alignment:
    """How far the onboard target is from the body (ZYX Euler angles in rad).

    >>> a = alignment((0.0, 0.0, 0.3), (0.0, 0.0, 0.0))
    >>> round(a.thrust_error_rad, 6), round(a.heading_error_rad, 6)
    (0.0, 0.3)
    >>> (a.target_to_body @ [1.0, 0.0, 0.0]).round(3).tolist()  # target x, seen by the body
    [0.955, 0.296, 0.0]
    """
    rt, rb = (_rotation(np.array(quat_from_euler(*target_rpy))),
              _rotation(np.array(quat_from_euler(*body_rpy))))
    tb = rb.T @ rt
    cos_thrust = float(np.clip(rt[:, 2] @ rb[:, 2], -1.0, 1.0))
    heading = (target_rpy[2] - body_rpy[2] + math.pi) % (2 * math.pi) - math.pi
    return Alignment(math.acos(cos_thrust), heading, tb)


def body_rates(torque: np.ndarray, gyro: np.ndarray, ff: np.ndarray, rate_p: np.ndarray,
               target_to_body: np.ndarray | None = None) -> np.ndarray:
    """The rates to send so that the onboard rate loop puts out ``torque``.

    The loop (angle P zero) puts out ``ff d + P (d - gyro)`` for the desired body rate
    ``d``, which is the rate sent rotated from the target into the body frame. Hence
    ``d = (torque + P gyro) / (ff + P)`` and the rate sent is ``R^T d``.

    Parameters
    ----------
    torque, gyro, ff, rate_p : ndarray, shape (3,)
        Roll, pitch, yaw: normalised torque, measured body rate (rad/s), the feed-forward
        and rate-P gains in effect onboard (normalised per rad/s).
    target_to_body : ndarray, shape (3, 3), optional
        :attr:`Alignment.target_to_body`; None: aligned.

    >>> body_rates(np.array([0.1, 0, 0]), np.zeros(3), np.ones(3), np.zeros(3)).tolist()
    [0.1, 0.0, 0.0]
    >>> body_rates(np.array([0.1, 0, 0]), np.array([0.5, 0, 0]), np.zeros(3),
    ...            np.full(3, 0.1)).round(6).tolist()
    [1.5, 0.0, 0.0]
    """
    d = (torque + rate_p * gyro) / (ff + rate_p)
    return d if target_to_body is None else target_to_body.T @ d


# ---------------------------------------------------------------------- k from PID_TUNING
@dataclass(frozen=True)
class FeedForwardCheck:
    """The rate loop as PID_TUNING showed it, one axis.

    ``k_measured`` is the median of ``FF / desired`` over samples with a feed-forward output
    above :data:`MIN_FF`; ``pid_max`` the largest |P|, |I| or |D| output seen.
    ``verdict`` is ``ok``, ``corrected`` or ``refused``.
    """

    axis: str
    samples: int
    k_set: float
    k_measured: float
    pid_max: float
    verdict: str

    def line(self) -> str:
        return (f"{self.axis} k {self.k_measured:.4g} measured ({self.k_set:g} set, "
                f"{self.samples} PID_TUNING samples, P/I/D at most {self.pid_max:.2g}): "
                f"{self.verdict}")


def check_feed_forward(axis: str, k_set: float, desired: np.ndarray, ff: np.ndarray,
                       pid_abs: np.ndarray) -> FeedForwardCheck:
    """Judge one axis of PID_TUNING samples (arrays of equal length; see the class).

    >>> d = np.linspace(0.05, 0.5, 30)
    >>> check_feed_forward("roll", 1.0, d, 1.0 * d, np.zeros(30)).verdict
    'ok'
    >>> check_feed_forward("roll", 1.0, d, 0.9 * d, np.zeros(30)).verdict
    'corrected'
    >>> check_feed_forward("roll", 1.0, d, 1.0 * d, np.full(30, 0.01)).verdict
    'refused'
    """
    use = (np.abs(ff) > MIN_FF) & (np.abs(desired) > 0)
    k = float(np.median(ff[use] / desired[use])) if use.any() else math.nan
    pid = float(np.max(pid_abs)) if len(pid_abs) else 0.0
    err = abs(k / k_set - 1.0) if math.isfinite(k) else math.inf
    verdict = ("refused" if err > K_REFUSE or pid > PID_ACTIVE
               else "corrected" if err > K_CORRECT else "ok")
    return FeedForwardCheck(axis, int(use.sum()), k_set, k, pid, verdict)


# ---------------------------------------------------------------------- yaw's written gains
def yaw_names(params: RatePathParams) -> dict[str, str]:
    """ArduCopter's yaw cascade names from the profile's ``[rate_path]``: angle P, rate
    P/I/D and the rate loop's target and error filters (``<rate P less P>I``, ...)."""
    prefix = params.rate_p[2].removesuffix("P")
    return {"angle_p": params.angle_p[2], "rate_p": params.rate_p[2], "rate_i": prefix + "I",
            "rate_d": prefix + "D", "fltt": prefix + "FLTT", "flte": prefix + "FLTE"}


@dataclass(frozen=True)
class YawDesign:
    """The yaw gains to write, or why none are.

    Attributes
    ----------
    values : dict
        Parameter -> value (angle P ``Kc/Kd``, rate P ``Kd``, rate I ``Kd w_i`` with its
        zero ``w_i`` below the crossover (:data:`YAW_RATE_I_DECADE`; 0 where none keeps the
        margin), D 0); empty where refused.
    cascade : CascadeGains or None
        The identified gains checked (and scaled) on ArduCopter's yaw cascade: on the
        identified model, or where the domain's edge model needs the smaller scale, on that.
    edge : InnerModel or None
        The domain's edge model the gains were also checked on (T1 past the domain).
    refusal : str or None
        Why nothing is written (the vehicle keeps its own yaw gains).
    """

    values: dict[str, float]
    cascade: CascadeGains | None
    edge: InnerModel | None = None
    refusal: str | None = None
    #: the vehicle's rate-error filter where the written one differs (Hz), else None
    flte_from_hz: float | None = None

    def note(self) -> str:
        """How the written gains were checked."""
        if self.cascade is None:
            return ""
        out = self.cascade.note()
        if self.flte_from_hz is not None:
            keep = 100 * (1 - YAW_FLTE_KEEP)
            out += (f"; the rate-error filter {self.flte_from_hz:g} -> "
                    f"{self.cascade.error_filter_hz:g} Hz, the lowest that costs the gains at "
                    f"most {keep:.0f} % against no filter" if self.cascade.error_filter_hz > 0 else
                    f"; the rate-error filter {self.flte_from_hz:g} Hz switched off (every "
                    f"frequency up to {YAW_FLTE_MAX_HZ:g} Hz cost the gains more than "
                    f"{keep:.0f} %)")
        if self.edge is not None:
            out += (f"; T1 past the classifier's domain, so also checked on its edge model "
                    f"(T1 {self.edge.T1:g} s, K {self.edge.K:.3g}: the same gain and, within "
                    f"{YAW_T1_PHASE_DEG:g} deg, phase at the crossover), the smaller scale kept")
        return out


def _t1_phase_deg(t1_a: float, t1_b: float, w: float) -> float:
    """Phase difference of the drag poles ``1/(T1 s + 1)`` of two models at ``w`` (deg)."""
    return abs(math.degrees(math.atan(w * t1_a) - math.atan(w * t1_b)))


def _yaw_rate_i(c: CascadeGains, model: InnerModel, edge: InnerModel | None,
                target_filter_hz: float, error_filter_hz: float) -> CascadeGains:
    """``c`` (the scaled yaw gains) with a rate I as roll and pitch get it
    (:func:`~mrft_gcs.flight.onboard.rate_loop_gains`, zero :data:`YAW_RATE_I_DECADE` below
    the crossover, lower where the margin needs it, none where even the lowest does not keep
    it); with an edge model, the lower of the two models' zeros, its margin the smaller."""
    found = [rate_loop_gains(mm, c.gains, target_filter_hz, error_filter_hz,
                             decade=YAW_RATE_I_DECADE) for mm in (model, edge) if mm is not None]
    if any(f.integrator_refused or not f.integrator_zero_rad_s > 0 for f in found):
        return dataclasses.replace(c, integrator_refused=True)
    wi = min(f.integrator_zero_rad_s for f in found)
    checked = [cascade_gains(mm, c.gains, target_filter_hz, error_filter_hz=error_filter_hz,
                             integrator_zero_rad_s=wi) for mm in (model, edge) if mm is not None]
    worst = min(checked, key=lambda k: k.pm_deg)
    if worst.scale < 1.0:  # the two models' zeros differ, and the lower one misses the margin
        return dataclasses.replace(c, integrator_refused=True)
    return dataclasses.replace(c, pm_deg=worst.pm_deg, wc_rad_s=worst.wc_rad_s,
                               integrator_zero_rad_s=wi)


def yaw_design(ident: Identification, names: Mapping[str, str], target_filter_hz: float,
               error_filter_hz: float) -> YawDesign:
    """Yaw's written gains: the identified PD on ArduCopter's yaw cascade (its target and
    error filters, the 400 Hz loop; :func:`~mrft_gcs.flight.onboard.cascade_gains`), scaled
    down where it falls short of the margin, with a rate I (:func:`_yaw_rate_i`) whose zero
    sits below the crossover as far as the margin needs (the P gains are not lowered for it).

    Refused where the identified model lies outside the attitude classifier's domain by more
    than :data:`YAW_DOMAIN_SLACK` (its gains would be a guess), with one exception: a drag
    time constant T1 past the domain's largest. A multirotor's yaw has little drag (T1 of
    several seconds), and far above ``1/T1`` the plant ``K/(s (T1 s + 1))`` is
    ``(K/T1)/s^2`` whatever T1: the domain's edge model (T1 at its largest, K scaled to keep
    ``K/T1``) then has the same response at the loop's crossover. Where its drag pole's phase
    there differs by less than :data:`YAW_T1_PHASE_DEG`, the gains are checked on both models
    and the smaller scale kept; otherwise refused.

    >>> from mrft_gcs.identify import Identification
    >>> from mrft_gcs.loops import LoopKind
    >>> from mrft_gcs.pd_design import PD
    >>> names = {"angle_p": "A", "rate_p": "P", "rate_i": "I", "rate_d": "D"}
    >>> def ident(T_prop, T1, tau):
    ...     return Identification(LoopKind.ATTITUDE, InnerModel(3.0, T_prop, T1, tau), 0, 1.0,
    ...                           -0.7, 0.05, 0.3, 0.05, PD(1.0, 0.1))
    >>> d = yaw_design(ident(0.03, 0.5, 0.01), names, 20.0, 2.5)
    >>> g = d.cascade.gains
    >>> d.refusal is None, d.edge is None, d.values["A"] == g.Kc / g.Kd
    (True, True, True)
    >>> d.values["I"] == g.Kd * d.cascade.integrator_zero_rad_s > 0, d.cascade.pm_deg >= 15
    (True, True)
    >>> yaw_design(ident(0.03, 9.0, 0.01), names, 20.0, 2.5).edge.T1  # integrating drag
    2.0
    >>> yaw_design(ident(0.9, 1.0, 0.01), names, 20.0, 2.5).refusal[:40]
    'the identified yaw model (T_prop 0.9 s, '
    """
    m = ident.model
    if not isinstance(m, InnerModel):
        return YawDesign({}, None, refusal="identified as no attitude model")
    p = np.array([m.T_prop, m.T1, m.tau])
    lo, hi = D_ATT.lo / YAW_DOMAIN_SLACK, D_ATT.hi * YAW_DOMAIN_SLACK
    inside = (p >= lo) & (p <= hi)
    t1_max = D_ATT.high[1]
    integrating = bool(m.T1 > t1_max)
    domain = (f"the identified yaw model (T_prop {m.T_prop:.3g} s, T1 {m.T1:.3g} s, tau "
              f"{m.tau:.3g} s) lies outside the attitude classifier's domain (T_prop "
              f"{D_ATT.low[0]:g}-{D_ATT.high[0]:g}, T1 {D_ATT.low[1]:g}-{t1_max:g}, tau "
              f"{D_ATT.low[2]:g}-{D_ATT.high[2]:g} s, x{YAW_DOMAIN_SLACK:g} either way)")
    if not (inside[0] and inside[2] and (inside[1] or integrating)):
        return YawDesign({}, None, refusal=f"{domain}: its gains would be a guess")
    edge = (dataclasses.replace(m, K=m.K * t1_max / m.T1, T1=t1_max) if integrating
            else None)

    def check(fe: float, gains: PD) -> CascadeGains:
        # the smaller scale of the identified and (T1 past the domain) the edge model
        c = cascade_gains(m, gains, target_filter_hz, error_filter_hz=fe)
        if edge is not None:
            ce = cascade_gains(edge, gains, target_filter_hz, error_filter_hz=fe)
            c = ce if ce.scale < c.scale else c
        return c

    fe, c = error_filter_hz, check(error_filter_hz, ident.gains)
    unfiltered = check(0.0, ident.gains).scale
    if error_filter_hz > 0 and c.scale < YAW_FLTE_KEEP * unfiltered:
        # the error filter is the rate P's noise filter: raised only as far as the gains need
        # (within YAW_FLTE_KEEP of what they keep with none); off where no frequency up to
        # the cap does
        fe, k = 0.0, 1
        while (cand := math.ceil(2.0 * error_filter_hz * YAW_FLTE_STEP ** k) / 2.0
               ) <= YAW_FLTE_MAX_HZ:
            if check(cand, ident.gains).scale >= YAW_FLTE_KEEP * unfiltered:
                fe = cand
                break
            k += 1
        c = check(fe, ident.gains)
    if edge is not None:
        off = _t1_phase_deg(m.T1, t1_max, c.wc_rad_s)
        if not off < YAW_T1_PHASE_DEG:
            return YawDesign({}, c, edge, refusal=(
                f"{domain}, and the domain's edge model differs by {off:.0f} deg at the "
                f"crossover (more than {YAW_T1_PHASE_DEG:g}): its gains would be a guess"))
    if not (c.scale > 0 and math.isfinite(c.pm_deg)):
        return YawDesign({}, c, edge, refusal=f"no gain keeps its margin on ArduCopter's yaw "
                                              f"cascade ({c.note()})")
    if YAW_RATE_I_DECADE > 0:
        c = _yaw_rate_i(c, m, edge, target_filter_hz, fe)
    g = c.gains
    values = {names["angle_p"]: g.Kc / g.Kd, names["rate_p"]: g.Kd, names["rate_i"]: c.rate_i,
              names["rate_d"]: 0.0}
    if "flte" in names:
        values[names["flte"]] = fe
    return YawDesign(values, c, edge, flte_from_hz=error_filter_hz if fe != error_filter_hz
                     else None)


def yaw_wait_over(waited_s: float, rp_rms: np.ndarray, onboard: bool = False) -> str | None:
    """Why yaw's relay stops waiting for a steady cycle, ``waited_s`` after roll and pitch
    were identified (``onboard``: after they went onto the onboard cascade), their body
    rates at ``rp_rms`` (rad/s, roll and pitch) on the ground station's PDs (or onboard);
    None: it waits on.

    >>> yaw_wait_over(1.0, np.radians([5.0, 8.0])) is None
    True
    >>> yaw_wait_over(1.0, np.radians([5.0, 200.0]))[:40]
    "pitch rang on the ground station's PD (2"
    >>> yaw_wait_over(0.2, np.radians([5.0, 200.0])) is None  # its relay's last swings
    True
    >>> yaw_wait_over(YAW_AFTER_ROLL_PITCH_S + 0.1, np.zeros(2))[:30]
    'no steady relay cycle within 4'
    """
    worst = float(np.max(rp_rms))
    if waited_s > RING_AFTER_S and worst > RING_RMS_RAD_S:
        where = "the onboard cascade" if onboard else "the ground station's PD"
        return (f"{_AXES[int(np.argmax(rp_rms))]} rang on {where} "
                f"({math.degrees(worst):.0f} deg/s rms body rate, limit "
                f"{math.degrees(RING_RMS_RAD_S):.0f}) {waited_s:.1f} s after roll and pitch "
                f"were {'handed over' if onboard else 'identified'}: yaw's test ended so that "
                f"the hand-over comes at once")
    if waited_s > YAW_AFTER_ROLL_PITCH_S:
        return (f"no steady relay cycle within {YAW_AFTER_ROLL_PITCH_S:g} s of roll and pitch "
                f"{'onboard' if onboard else 'identified'}")
    return None


def roll_pitch_names(params: RatePathParams) -> tuple[str, ...]:
    """The test parameters that roll and pitch's own hand-over puts to their final values:
    their rate loops' (``<rate P less P>*``), feed-forwards, angle P and acceleration limits
    (``ATC_ACCEL_R_MAX``/``P_MAX``). Yaw's, the shared ones (the rate feed-forward switch,
    boosts, ...) and ACRO's stay for the hand-over after yaw.

    >>> from mrft_gcs.profiles import load_profile
    >>> names = roll_pitch_names(load_profile("ardupilot").rate_path)
    >>> "ATC_RAT_RLL_I" in names and "ATC_ACCEL_P_MAX" in names and "ATC_ANG_PIT_P" in names
    True
    >>> any("YAW" in n for n in names) or "ATC_RATE_FF_ENAB" in names
    False
    """
    prefixes = tuple(n.removesuffix("P") for n in params.rate_p[:2])
    own = {*params.rate_p[:2], *params.ff[:2], *params.angle_p[:2],
           "ATC_ACCEL_R_MAX", "ATC_ACCEL_P_MAX"}
    return tuple(n for n in params.test_params if n in own or n.startswith(prefixes))


def _rotation_euler(roll: float, pitch: float, yaw: float) -> np.ndarray:
    return _rotation(np.array(quat_from_euler(roll, pitch, yaw)))


def _euler(q: tuple[float, float, float, float]) -> tuple[float, float, float]:
    """ZYX Euler angles (rad) of the unit quaternion ``q`` (w, x, y, z).

    >>> [round(v, 9) for v in _euler(quat_from_euler(0.1, -0.2, 2.5))]
    [0.1, -0.2, 2.5]
    """
    w, x, y, z = q
    return (math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y)),
            math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x)))),
            math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))


def beside_yaw(yaw_torque: float, yaw_rate: float, ff: float, rate_p: float,
               desired_rpy: tuple[float, float, float],
               target_to_body: np.ndarray | None = None) -> tuple[float, float, float]:
    """The body rates to send with the attitude set point ``desired_rpy`` (ZYX Euler, rad)
    so that, roll and pitch held onboard, yaw's rate loop (angle P 0) puts out
    ``yaw_torque``.

    The body's yaw rate must be ``d = (torque + P r) / (ff + P)`` (:func:`body_rates`);
    ArduCopter rotates the attitude target's rate into the body frame, so the target's rate
    is ``R^T (0, 0, d)``; it takes the rates sent as the desired attitude's
    (``ang_vel_target = q_desired * rates``), hence they are that rotated back.

    >>> [round(v, 6) for v in beside_yaw(0.1, 0.0, 1.0, 0.0, (0.0, 0.0, 1.2))]
    [0.0, 0.0, 0.1]
    >>> w = beside_yaw(0.1, 0.0, 1.0, 0.0, (0.2, 0.0, 0.0))  # a rolled set point
    >>> (_rotation_euler(0.2, 0.0, 0.0) @ w).round(6).tolist()  # the target's rate
    [0.0, 0.0, 0.1]
    """
    d = (yaw_torque + rate_p * yaw_rate) / (ff + rate_p)
    w_t = np.array([0.0, 0.0, d]) if target_to_body is None else target_to_body.T @ [0, 0, d]
    v = _rotation_euler(*desired_rpy).T @ w_t
    return float(v[0]), float(v[1]), float(v[2])


# ---------------------------------------------------------------------- streaming state

#: ArduCopter's main loop period on the SITL and most boards (s): ATTITUDE_TARGET samples one
#: tick apart bracket a square wave's edge exactly (the target changes at a tick)
EDGE_TICK_S = 0.0025


def check_cascade(cascade: OnboardCascade) -> OnboardCascade:
    """The cascade the in-air check flies: the written one with the target's own rate not fed
    forward (:data:`CHECK_PARAMS`); the feedback path, and so the margin, is the written
    loop's."""
    return dataclasses.replace(cascade, target_rate_ff=False)


def _edges(t: np.ndarray, u: np.ndarray, amplitude: float) -> list[tuple[int, float]]:
    """``(index, new level)`` of each step of a held square wave ``u`` at times ``t``."""
    out = []
    for i in range(1, len(u)):
        if abs(u[i] - u[i - 1]) > amplitude:
            out.append((i, float(u[i])))
    return out


def check_points(probe: SquareWaveProbe) -> tuple[dict[Loop, tuple[np.ndarray, np.ndarray,
                                                                    np.ndarray]], dict[Loop, str]]:
    """Closed-loop points of the rate path's check and, per loop, how its input was timed.

    With the target's rate not fed forward the onboard target is the set point sent, from
    the tick after it arrives. At a 50-80 rad/s crossover 1 ms is 3-5 deg of phase, finer
    than ATTITUDE_TARGET's 2.5-5 ms spacing: each edge of the square wave sent is put where
    the vehicle's record brackets it, at the send time plus the delay that edges bracketed by
    samples one tick apart measure (the mean of those: the link and the wait for the tick),
    moved onto the nearest tick the bracket leaves (the target changes at a tick). Where fewer
    than 4 edges are bracketed that closely, the delay is the mean middle of the brackets;
    where the record does not show an edge at all, the loop is not measured (no points)."""
    c = np.asarray(probe.cmd, float)
    ts = np.asarray(sorted(probe.smp), float)
    y = np.asarray([probe.smp[t] for t in ts], float)
    t_cmd = c[:, 0] - probe.offset  # on the vehicle clock, less an unknown constant
    tt = np.asarray(sorted(probe.tracked), float)
    out: dict[Loop, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    how: dict[Loop, str] = {}
    for i, lp in enumerate((Loop.ROLL, Loop.PITCH)):
        p = probe.plans.get(lp)
        if p is None:
            continue
        ut = np.asarray([probe.tracked[t][i] for t in tt], float) if tt.size else tt
        sent = _edges(t_cmd, c[:, 1 + i], p.amplitude)
        brackets: list[tuple[float, float, float, float]] = []  # sent, prev, new, level
        for k, level in sent:
            ts_k = t_cmd[k]
            j = np.flatnonzero((tt > ts_k - 0.002) & (np.abs(ut - level) < 0.5 * p.amplitude))
            if j.size == 0 or j[0] == 0 or tt[j[0]] - ts_k > 0.05:
                break
            brackets.append((ts_k, float(tt[j[0] - 1]), float(tt[j[0]]), level))
        if len(brackets) < len(sent) or not brackets:
            how[lp] = "none: ATTITUDE_TARGET did not show every edge of the square wave"
            continue
        tight = [new - ts_k for ts_k, prev, new, _ in brackets
                 if new - prev <= 1.4 * EDGE_TICK_S]
        if len(tight) >= 4:
            med = float(np.median(tight))
            lag = float(np.mean([x for x in tight if abs(x - med) <= 2 * EDGE_TICK_S]))
            how[lp] = (f"the set point as sent, each edge at the tick where ATTITUDE_TARGET "
                       f"brackets it nearest {lag * 1e3:.1f} ms after sending (the mean of "
                       f"{len(tight)} of {len(brackets)} edges bracketed one tick apart)")
        else:  # the middle of the brackets, on average
            lag = float(np.mean([0.5 * (prev + new) - ts_k for ts_k, prev, new, _ in brackets]))
            how[lp] = (f"the set point as sent, each edge at the tick where ATTITUDE_TARGET "
                       f"brackets it nearest {lag * 1e3:.1f} ms after sending (the mean middle "
                       f"of the brackets: {len(tight)} of {len(brackets)} one tick apart)")
        # the target changes at a tick: of the ticks the bracket leaves, the one nearest the
        # send time plus that delay
        t_sw = [new - EDGE_TICK_S * round(min(max(new - ts_k - lag, 0.0), new - prev - 1e-3)
                                          / EDGE_TICK_S)
                for ts_k, prev, new, _ in brackets]
        # the wave's start as late as its edges came (its first level is the one it leaves)
        start = t_cmd[0] + float(np.mean([t - b[0] for t, b in zip(t_sw, brackets,
                                                                    strict=True)]))
        t_u = np.concatenate(([start], t_sw))
        u = np.concatenate(([float(c[0, 1 + i])], [b[3] for b in brackets]))
        t0 = start + p.period_s  # the first cycle lets the start transient die out
        out[lp] = harmonic_points(t_u, u, ts, y[:, i], p.period_s, t0, p.cycles)
    return out, how


class RateChannel:
    """Torque set points -> body-rate set points, on the stream's ticks.

    Holds what the onboard rate loop is believed to be (feed-forward and rate P per axis,
    updated as the hand-over writes them) and the latest onboard attitude target.
    """

    def __init__(self, params: RatePathParams) -> None:
        self.params = params
        self.reset()

    def reset(self) -> None:
        self.ff = np.array(self.params.k, dtype=float)
        self.rate_p = np.zeros(3)
        self.target: AttitudeSetpoint | None = None
        self.released = False  # True: zero rates (the onboard angle loop holds the target)
        self.hold_body = False  # True: the body's attitude as the attitude set point
        self.last: Alignment | None = None
        self.worst_thrust_rad = 0.0
        self.worst_heading_rad = 0.0
        self.last_thrust = 0.0
        #: roll and pitch body rates' mean square (rad^2/s^2, over RING_TAU_S) and the
        #: vehicle time of the sample it last took
        self.rp_ms = np.zeros(2)
        self._t_rate_s = math.nan
        #: roll and pitch held onboard, yaw's torque sent as the feed-forward beside the
        #: sequence's roll/pitch attitude (``refs()``: roll, pitch set points, rad)
        self.rp_onboard = False
        self.refs: Callable[[], tuple[float, float]] | None = None
        #: the desired heading sent (rad): the target's own, as it integrates yaw's rates
        self.yaw_d = math.nan
        self._t_yaw_d = math.nan
        self._att_refs: tuple[float, float] | None = None  # from the sequence's attitude

    @property
    def rp_rms(self) -> np.ndarray:
        """Roll and pitch body rates' rms over the last :data:`RING_TAU_S` (rad/s)."""
        return np.sqrt(self.rp_ms)

    def _see_rates(self, s: FlightState) -> None:
        dt = s.t_att_s - self._t_rate_s
        self._t_rate_s = s.t_att_s
        if not dt > 0:
            return  # ticks between telemetry samples repeat the state
        a = min(1.0, dt / RING_TAU_S)
        self.rp_ms += a * (np.array([s.p_rad_s, s.q_rad_s]) ** 2 - self.rp_ms)

    def see_target(self, sp: AttitudeSetpoint) -> None:
        self.target = sp

    def step(self, out: ActuatorTarget, s: FlightState | None) -> RateTarget | AttitudeTarget:
        """The rate set point that makes the onboard loop put out ``out``'s torques; once
        :attr:`hold_body`, the body's attitude as an attitude set point instead (the
        hand-over sets the onboard target onto it)."""
        self.last_thrust = out.thrust
        if s is not None:
            self._see_rates(s)
        if self.hold_body and s is not None:
            rates = None
            if self.rp_onboard and not self.released:  # yaw's test goes on meanwhile
                self.yaw_d, self._t_yaw_d = s.yaw_rad, time.monotonic()
                rates = beside_yaw(out.yaw, s.r_rad_s, self.ff[2], self.rate_p[2],
                                   (s.roll_rad, s.pitch_rad, s.yaw_rad))
            return AttitudeTarget(out.t_s, quat_from_euler(s.roll_rad, s.pitch_rad, s.yaw_rad),
                                  out.thrust, rates)
        if self.released or s is None:
            return RateTarget(out.t_s, 0.0, 0.0, 0.0, out.thrust)
        tb = None
        if self.target is not None:
            tgt = self.target
            a = alignment((tgt.roll_rad, tgt.pitch_rad, tgt.yaw_rad),
                          (s.roll_rad, s.pitch_rad, s.yaw_rad))
            self.last, tb = a, a.target_to_body
            self.worst_thrust_rad = max(self.worst_thrust_rad, a.thrust_error_rad)
            self.worst_heading_rad = max(self.worst_heading_rad, abs(a.heading_error_rad))
        if self.rp_onboard:
            return self._beside(out, s, tb)
        w = body_rates(np.array([out.roll, out.pitch, out.yaw]),
                       np.array([s.p_rad_s, s.q_rad_s, s.r_rad_s]), self.ff, self.rate_p, tb)
        return RateTarget(out.t_s, float(w[0]), float(w[1]), float(w[2]), out.thrust)


    def step_attitude(self, out: AttitudeTarget, s: FlightState,
                      yaw_torque: float) -> RateTarget | AttitudeTarget:
        """Roll and pitch onboard, the sequence flying attitude set points (its side tests):
        ``out``'s roll and pitch as the set point, yaw's ``yaw_torque`` (its relay's, which
        the sequence no longer steps) beside them, as :meth:`step` sends them."""
        roll, pitch, _ = _euler(out.q_wxyz)
        self._att_refs = (roll, pitch)
        return self.step(ActuatorTarget(out.t_s, 0.0, 0.0, yaw_torque, out.thrust), s)

    def _beside(self, out: ActuatorTarget, s: FlightState,
                tb: np.ndarray | None) -> AttitudeTarget:
        """Roll and pitch onboard: the sequence's roll/pitch set points as the attitude, at
        the heading the target integrates (so that ArduCopter's shaping adds no yaw rate of
        its own), and yaw's torque as the body-rate feed-forward (:func:`beside_yaw`)."""
        roll, pitch = (self._att_refs if self._att_refs is not None else
                       self.refs() if self.refs is not None else (0.0, 0.0))
        now = time.monotonic()
        if not math.isfinite(self.yaw_d):
            self.yaw_d, self._t_yaw_d = s.yaw_rad, now
        rates = beside_yaw(out.yaw, s.r_rad_s, self.ff[2], self.rate_p[2],
                           (roll, pitch, self.yaw_d), tb)
        # the heading moves at the target's yaw rate (small tilts: the rate about its z)
        d = (out.yaw + self.rate_p[2] * s.r_rad_s) / (self.ff[2] + self.rate_p[2])
        self.yaw_d += d * min(0.1, max(0.0, now - self._t_yaw_d))
        self._t_yaw_d = now
        return AttitudeTarget(out.t_s, quat_from_euler(roll, pitch, self.yaw_d), out.thrust,
                              rates)


# ---------------------------------------------------------------------- the path
class RatePath:
    """One tune's rate path: test parameters, conversion, checks, hand-over, restore.

    The api calls :meth:`wrap` (the stream's set points), :meth:`engage` (after arming),
    :meth:`check` (main loop), :meth:`split` and :meth:`hand_over` (write-back),
    :meth:`abort` (before landing on any abort) and :meth:`restore_rest` (always, last).
    """

    def __init__(self, link: VehicleLink, params: RatePathParams, backup_dir: Path) -> None:
        self.link = link
        self.params = params
        self.backup_dir = backup_dir
        self.channel = RateChannel(params)
        self.notes: list[str] = []
        self.backup: Path | None = None  # originals of every test parameter
        self.originals: dict[str, float] = {}
        self.known: dict[str, Param] = {}  # name -> value before the tune, with its type
        self.restored: set[str] = set()  # test parameters back at their final value
        self.checks: dict[str, FeedForwardCheck] = {}
        self.t_engaged: float | None = None
        self.zero_gain_s = math.nan
        self.staged: dict[str, float] = {}  # the tune's written values among test params
        self.rate_i: dict[str, float] = {}  # roll/pitch rate I to write (name -> value)
        #: roll/pitch rate D to write: its name -> (rate P name, D per unit of rate P, s)
        self.rate_d: dict[str, tuple[str, float]] = {}
        #: the roll/pitch rate loop's error and D low-passes as read at :meth:`engage` (Hz;
        #: not test parameters: they stay as they are); None: not read
        self.rp_filters: dict[int, tuple[float, float]] | None = None
        #: the gyro low-pass the rate loop closes on (Hz; 0: none or not read)
        self.gyro_hz = 0.0
        self.handed_over = False
        self.changes: tuple[ParamChange, ...] = ()
        self.yaw_note: str | None = None  # how yaw was held, where not the default hold
        #: yaw's relay (None: held on the vehicle's own gains throughout), the identifier
        #: it is handed to (``f(snapshot) -> Identification``), what came of it
        self.yaw: YawRelay | None = None
        self.identify: Callable[[CycleSnapshot], Identification] | None = None
        self.yaw_ident: Identification | None = None
        self.yaw_written: YawDesign | None = None
        self.yaw_flte = 0.0  # the vehicle's own yaw rate-error filter (Hz; 0: none)
        self.yaw_staged: dict[str, float] = {}
        self._yaw_gcs_s = math.nan  # monotonic time the yaw gains were designed
        self._t_rp_s = math.nan  # monotonic time roll and pitch were first seen identified
        #: largest roll, pitch body-rate rms on the ground station's PDs while yaw waited
        self.rp_rms_max = np.zeros(2)
        #: roll and pitch on the onboard cascade ahead of yaw (:meth:`hand_over_roll_pitch`)
        self.rp_onboard = False
        #: each axis' zero-gain window (s): from :meth:`engage` until its gains are onboard
        self.zero_gain_axes_s: dict[str, float] = {}
        self._onboard_axes: set[int] = set()  # PID_TUNING axes no longer pure feed-forward
        self._stack = contextlib.ExitStack()
        self._targets = self._stack.enter_context(link.subscribe(AttitudeSetpoint))
        self._pid = self._stack.enter_context(link.subscribe(PidTuning))
        self._pid_rows: dict[int, list[tuple[float, float, float]]] = {1: [], 2: [], 3: []}
        self._checking = False

    def close(self) -> None:
        self._stack.close()

    # -------------------------------------------------------------- stream
    def wrap(self, tick: Callable[[FlightState | None], Setpoint | None]
             ) -> Callable[[FlightState | None], Setpoint | None]:
        """The stream's per-tick function with torques sent as rates."""
        channel, targets = self.channel, self._targets

        def rate_tick(s: FlightState | None) -> Setpoint | None:
            out = tick(s)
            while (sp := targets.get(0.0)) is not None:
                if isinstance(sp, AttitudeSetpoint):
                    channel.see_target(sp)
            if isinstance(out, ActuatorTarget):
                return channel.step(out, s)
            if (isinstance(out, AttitudeTarget) and channel.rp_onboard and not self.handed_over
                    and s is not None and self.yaw is not None):
                # roll and pitch onboard, the side tests on attitude set points: yaw's relay
                # (or, once done, its PD) still flies through the feed-forward until its
                # hand-over
                _, _, yaw_ref = _euler(out.q_wxyz)
                u = self.yaw.step(yaw_ref, s.yaw_rad, s.r_rad_s, s.t_att_s)
                return channel.step_attitude(out, s, u)
            return out

        return rate_tick

    def _ask(self, message_id: int, rate_hz: float) -> bool:
        return self.link.ask_message_interval(message_id, rate_hz)

    # -------------------------------------------------------------- engage
    def engage(self, client: ParamClient) -> None:
        """Write the test parameters (armed, on the ground; backed up first) and ask for
        ATTITUDE_TARGET and PID_TUNING. The zero-gain window starts here."""
        if not self._ask(_ATTITUDE_TARGET_ID, STREAM_HZ):
            raise LinkError("the vehicle refused to stream ATTITUDE_TARGET, which the rate "
                            "path needs to align its rates: use --actuation attitude")
        self._ask(_PID_TUNING_ID, STREAM_HZ)
        # read before the zero-gain window opens (the roll/pitch design models them)
        self.rp_filters = {axis: self._rp_filters(client, axis) for axis in (0, 1)}
        self.gyro_hz = self._gyro_filter_hz(client)
        result = client.write(dict(self.params.test_params), self.backup_dir, label="rate-test")
        self.backup = result.backup_path
        self.originals = {c.name: c.old for c in result.changes}
        self.known = {e.param.name: e.param for e in read_params_file(self.backup)}
        # the written yaw gains are checked through the vehicle's own rate-error filter
        flte = self.originals.get(yaw_names(self.params)["flte"], 0.0)
        self.yaw_flte = float(flte) if math.isfinite(flte) and flte > 0 else 0.0
        self.t_engaged = time.monotonic()
        self._checking = True
        self.channel.worst_thrust_rad = self.channel.worst_heading_rad = 0.0
        changed = sum(1 for c in result.changes if c.old != c.new)
        self.notes.append(
            f"rate path: {changed} test parameters set after arming (rate loop reduced to "
            f"feed-forward k {'/'.join(f'{k:g}' for k in self.params.k)}, angle P 0; backup "
            f"{self.backup}); restored at the hand-over, the written gains kept")
        if LINK_LOSS_GUARD is not None:
            self.notes.append(LINK_LOSS_GUARD(self.link, client, self.backup))
        else:
            self.notes.append("rate path: link loss in the zero-gain window is unprotected "
                              "onboard (no link-loss guard installed): GUID_TIMEOUT only "
                              "levels the attitude target, the gains stay zero")

    def yaw_hold(self, beta: float | None = None,
                 identify: Callable[[CycleSnapshot], Identification] | None = None
                 ) -> YawHold | YawRelay | None:
        """The ground station's yaw hold on this path: the vehicle's own yaw gains (angle P
        times rate P, and rate P; the rate I left out), read before the test parameters
        zeroed them. The default hold (Kc 0.2) let ArduCopter SITL's yaw drift 20 deg
        during the side tests. None where the values are not known.

        With the attitude relay's ``beta`` and an ``identify`` (and :data:`TUNE_YAW`): a
        yaw relay (:class:`~mrft_gcs.flight.phases.yaw.YawRelay`) around that hold, whose
        cycles :meth:`check` identifies and whose gains the hand-over writes."""
        names = (self.params.angle_p[2], self.params.rate_p[2])
        if not all(n in self.originals for n in names):
            return None
        ang, rate = (self.originals[n] for n in names)
        if not (ang > 0 and rate > 0):
            return None
        self.yaw_note = (f"yaw is not tuned: the ground station held it during the tests on "
                         f"the vehicle's own yaw gains (Kc {ang * rate:.3g} /rad, Kd "
                         f"{rate:.3g} s/rad on the normalised yaw command, rate I left out), "
                         f"which are restored afterwards")
        hold = YawHold(ang * rate, rate, limit=YAW_LIMIT)
        if not (TUNE_YAW and beta is not None and identify is not None):
            return hold
        self.identify = identify
        self.yaw = YawRelay(hold, beta)
        return self.yaw

    def _yaw_step(self) -> None:
        """Identify yaw's steady cycles where they wait, design its written gains, and fly
        the identified PD (times :data:`GCS_PD_SCALE`) until the hand-over; or give up to
        the vehicle's own gains with the reason."""
        relay, identify = self.yaw, self.identify
        if relay is None or identify is None or (snap := relay.take()) is None:
            return
        try:
            ident = identify(snap)
        except MrftError as err:
            relay.give_up(f"its relay cycle was not identified ({err})")
            return
        self.yaw_ident = ident
        final = self._final(keep_written=False)
        n = yaw_names(self.params)
        fltt = final.get(n["fltt"], 0.0)
        design = yaw_design(ident, n, fltt if math.isfinite(fltt) else 0.0, self.yaw_flte)
        self.yaw_written = design
        if design.refusal is not None:
            relay.give_up(design.refusal)
            return
        self.yaw_staged = dict(design.values)
        if not self.handed_over:
            self.staged.update(self.yaw_staged)
        self._yaw_gcs_s = time.monotonic()
        relay.apply(GCS_PD_SCALE * ident.gains.Kc, GCS_PD_SCALE * ident.gains.Kd)

    def _yaw_outcome(self) -> None:
        """The report's line on yaw (``yaw_note``), once the hand-over writes or not."""
        relay = self.yaw
        if relay is None:
            return
        if not relay.done:
            relay.give_up("the tests ended before its relay cycle was steady")
        when = ""
        if math.isfinite(relay.t_ready_s) and math.isfinite(relay.t_first_s):
            when = (f"; steady cycles {relay.t_ready_s - relay.t_first_s:.1f} s after "
                    f"lift-off (relay from {relay.t_relay_s - relay.t_first_s:.1f} s, h "
                    f"{relay.h:.3g}, largest heading error "
                    f"{math.degrees(relay.max_error_rad):.1f} deg, its zero followed the cycle "
                    f"up to {math.degrees(relay.max_zero_rad):.1f} deg off the set point)")
        ident, design = self.yaw_ident, self.yaw_written
        if relay.state is YawState.TUNED and ident is not None and design is not None:
            m, c = ident.model, design.cascade
            assert isinstance(m, InnerModel) and c is not None
            vals = ", ".join(f"{k} {v:.4g}" for k, v in design.values.items())
            self.yaw_note = (
                f"yaw tuned on the rate path: identified by the attitude classifier (K "
                f"{m.K:.3g}, T_prop {m.T_prop:.3g} s, T1 {m.T1:.3g} s, tau {m.tau:.3g} s; "
                f"period {ident.period_s:.3f} s, amplitude {math.degrees(ident.amplitude):.2f} "
                f"deg; PD Kc {ident.gains.Kc:.3g}, Kd {ident.gains.Kd:.3g}), written {vals}: "
                f"{design.note()}{when}")
        else:
            if ident is not None and isinstance(ident.model, InnerModel):
                m = ident.model
                when += (f"; identified K {m.K:.3g}, T_prop {m.T_prop:.3g} s, T1 {m.T1:.3g} s, "
                         f"tau {m.tau:.3g} s, period {ident.period_s:.3f} s")
            if math.isfinite(self._t_rp_s):
                rp = np.degrees(self.rp_rms_max)
                when += (f"; roll/pitch body rates on the ground station's PDs while yaw waited "
                         f"up to {rp[0]:.0f}/{rp[1]:.0f} deg/s rms")
            self.yaw_note = (f"yaw held on its own gains: {relay.why}; the ground station "
                             f"held it on the vehicle's own yaw gains, which are restored"
                             f"{when}")
        self.notes.extend(relay.events)

    def yaw_outcome(self, t_start_s: float) -> YawOutcome | None:
        """Yaw's relay test for the report (None: yaw was not relay-tested); ``t_start_s``
        the take-off command's vehicle time."""
        relay = self.yaw
        if relay is None:
            return None
        ident, design = self.yaw_ident, self.yaw_written
        tuned = (relay.state is YawState.TUNED and design is not None and bool(design.values)
                 and self.handed_over)
        c = design.cascade if tuned and design is not None else None
        why = (relay.why if relay.state is YawState.HELD and relay.why else
               "the tune stopped before its gains were written" if relay.state is YawState.TUNED
               else "the tune stopped before its relay cycle was steady")
        return YawOutcome(
            state="tuned" if tuned else "held", reason=None if tuned else why,
            beta=relay.beta, h=relay.h, bias=relay.bias, band=relay.rules.band_rad,
            period_s=ident.period_s if ident else math.nan,
            amplitude=ident.amplitude if ident else math.nan, identification=ident,
            gains=c.gains if c is not None else None,
            written=dict(design.values) if tuned and design is not None else {},
            pm_predicted_deg=c.pm_deg if c is not None else math.nan,
            crossover_rad_s=c.wc_rad_s if c is not None else math.nan,
            steady_after_s=relay.t_ready_s - t_start_s, max_error_rad=relay.max_error_rad,
            zero_moved_rad=relay.max_zero_rad, note=self.yaw_note or "")

    def require_aligned(self, timeout_s: float = 1.5) -> Alignment:
        """Before the take-off: the onboard target must sit on the body (ATTITUDE_TARGET
        against ATTITUDE, as the stream sees them); otherwise the tune stops on the ground."""
        end = time.monotonic() + timeout_s
        a = None
        while time.monotonic() < end:
            a = self.channel.last
            if a is not None and (math.degrees(a.thrust_error_rad) <= GROUND_ALIGNMENT_DEG[0]
                                  and abs(math.degrees(a.heading_error_rad))
                                  <= GROUND_ALIGNMENT_DEG[1]):
                self.notes.append(
                    f"rate path: onboard target on the body before the take-off "
                    f"({math.degrees(a.thrust_error_rad):.1f} deg thrust, "
                    f"{math.degrees(a.heading_error_rad):+.1f} deg heading)")
                return a
            time.sleep(0.05)
        seen = ("no ATTITUDE_TARGET seen" if a is None else
                f"{math.degrees(a.thrust_error_rad):.0f} deg thrust, "
                f"{math.degrees(a.heading_error_rad):+.0f} deg heading")
        raise SafetyAbort(f"rate path: the onboard attitude target is not on the body before "
                          f"the take-off ({seen}): not taking off; disarm, re-arm and retry")

    # -------------------------------------------------------------- checks
    def check(self) -> None:
        """Measure ``k`` from PID_TUNING and the target's alignment; correct or refuse."""
        rows = self._pid_rows
        while (ev := self._pid.get(0.0)) is not None:
            if (not (self._checking and isinstance(ev, PidTuning)) or ev.axis not in rows
                    or ev.axis in self._onboard_axes):
                continue
            rows[ev.axis].append((ev.desired, ev.ff, max(abs(ev.p), abs(ev.i), abs(ev.d))))
            if len(rows[ev.axis]) > 2000:
                del rows[ev.axis][:1000]
        if self._checking:
            for axis in (1, 2, 3):
                if axis not in self._onboard_axes:
                    self._judge(axis)
        self._yaw_step()
        if self.t_engaged is not None and (self.channel.worst_thrust_rad
                                           > math.radians(MAX_THRUST_ERROR_DEG)):
            raise SafetyAbort(
                f"rate path: the onboard attitude target drifted "
                f"{math.degrees(self.channel.worst_thrust_rad):.0f} deg from the body (more "
                f"than {MAX_THRUST_ERROR_DEG:.0f} deg; ArduPilot scales its feed-forward down "
                f"from 30): test stopped, gains restored, landing commanded")

    def _judge(self, axis: int) -> None:
        name = _AXES[axis - 1]
        a = np.array(self._pid_rows[axis]).reshape(-1, 3)
        big = np.abs(a[:, 1]) > MIN_FF
        if name in self.checks and self.checks[name].verdict != "refused":
            # judged: P, I and D must stay off while the ground station flies
            if len(a) and float(np.max(a[:, 2])) > PID_ACTIVE:
                raise SafetyAbort(f"rate path: the {name} rate loop put out P/I/D "
                                  f"{float(np.max(a[:, 2])):.3g} (not pure feed-forward): "
                                  f"test stopped, gains restored, landing commanded")
            return
        if int(big.sum()) < MIN_SAMPLES:
            return
        k_set = self.params.k[axis - 1]
        chk = check_feed_forward(name, k_set, a[:, 0], a[:, 1], a[:, 2])
        self.checks[name] = chk
        self.notes.append(f"rate path: {chk.line()}")
        if chk.verdict == "refused":
            raise SafetyAbort(f"rate path: {chk.line()}: the rate loop is not the feed-forward "
                              f"the test needs; test stopped, gains restored, landing "
                              f"commanded")
        if chk.verdict == "corrected":
            self.channel.ff[axis - 1] = chk.k_measured
        self._pid_rows[axis] = []

    # -------------------------------------------------------------- write-back
    def split(self, values: Mapping[str, float]) -> dict[str, float]:
        """The write-back's values less those that are test parameters (kept for
        :meth:`hand_over`, which writes them staged; after it, already written)."""
        test = self.params.test_params
        if not self.handed_over:
            self.staged = {n: v for n, v in values.items() if n in test}
            self.staged.update({n: v for n, v in self.rate_i.items() if n in self.staged})
            # rate D at its share of the rate P in effect (after any range clamp)
            self.staged.update({n: round(r * self.staged[p], 6)
                                for n, (p, r) in self.rate_d.items()
                                if n in self.staged and p in self.staged})
            self.staged.update(self.yaw_staged)
        return {n: v for n, v in values.items() if n not in test}

    def _final(self, keep_written: bool = True) -> dict[str, float]:
        """Each test parameter's value after the tune: the written gain, else its own."""
        staged = self.staged if keep_written else {}
        return {n: staged.get(n, self.originals.get(n, v))
                for n, v in self.params.test_params.items()}

    def _write(self, client: ParamClient, values: Mapping[str, float]) -> None:
        """Every value read back; all were backed up at :meth:`engage` (no read first)."""
        values = {n: v for n, v in values.items() if n not in self.restored}
        if values:
            client.write_known(values, self.known)
            self.restored.update(values)

    def hand_over(self, client: ParamClient, hold: Callable[[float], None]
                  ) -> tuple[ParamChange, ...]:
        """Give attitude control back to the autopilot while the ground station flies.

        1. rate P (roll, pitch: the written Kd; yaw: its own) - the rates sent invert it;
        2. feed-forward back to the vehicle's own values - likewise;
        3. rates to zero; the onboard attitude target set onto the body (the rate
           feed-forward switched off, :data:`TARGET_SET_PARAM`, and the body's attitude
           sent as the set point, which then becomes the target unshaped); then the
           written angle P, the feed-forward switch and every other test parameter.

        ``hold(s)`` keeps the stream checked in between. Returns the written gains among
        the test parameters as changes from their values before the tune. Done once: a
        second call (the write-back after an early hand-over) returns the same changes.
        """
        if self.handed_over:
            return self.changes
        self._yaw_outcome()
        self.staged.update(self.yaw_staged)
        self._checking = False  # the rate loop is no longer pure feed-forward from here
        final, p = self._final(), self.params
        t0 = time.monotonic()
        self._write(client, {n: final[n] for n in p.rate_p})
        self.channel.rate_p = np.array([final[n] for n in p.rate_p])
        hold(STAGE_HOLD_S)
        self._write(client, {n: final[n] for n in p.ff})
        self.channel.ff = np.array([final[n] for n in p.ff])
        hold(STAGE_HOLD_S)
        self.channel.released = True
        hold(0.02)  # a zero-rate set point out before the angle loop comes back
        off = self.channel.last
        aligned = TARGET_SET_PARAM in p.test_params
        if aligned:
            # not recorded as restored: an abort from here puts the vehicle's own value back
            client.write_known({TARGET_SET_PARAM: 0.0}, self.known)
            self.channel.hold_body = True
            hold(ALIGN_HOLD_S)
        rest = {n: final[n] for n in p.angle_p}
        if aligned:  # the target shaped again from here, starting on the body
            rest[TARGET_SET_PARAM] = final[TARGET_SET_PARAM]
        rest.update({n: v for n, v in final.items() if n not in rest})
        self._write(client, rest)
        t_done = time.monotonic()
        if self.t_engaged is not None:
            self.zero_gain_s = t_done - self.t_engaged
            for name in _AXES:
                self.zero_gain_axes_s.setdefault(name, self.zero_gain_s)
        axes = self.zero_gain_axes_s
        self.notes.append(
            f"rate path: zero-gain window {self.zero_gain_s:.1f} s (test parameters written "
            f"after arming to the written gains in effect"
            + (f"; roll and pitch onboard after {axes['roll']:.1f} s, yaw after "
               f"{axes['yaw']:.1f} s" if self.rp_onboard and axes else "")
            + "); hand-over in "
            f"{t_done - t0:.2f} s (rate P, feed-forward, then angle P and the rest); largest "
            f"target-to-body misalignment {math.degrees(self.channel.worst_thrust_rad):.1f} "
            f"deg thrust, {math.degrees(self.channel.worst_heading_rad):.1f} deg heading "
            f"(compensated)"
            + ("" if off is None else
               f"; {math.degrees(off.thrust_error_rad):.1f} deg thrust, "
               f"{math.degrees(off.heading_error_rad):+.1f} deg heading at the hand-over, "
               + ("the target set onto the body before angle P came back" if aligned else
                  "left for angle P to close")))
        self.handed_over = True
        self.changes = tuple(ParamChange(n, self.originals.get(n, math.nan), v)
                             for n, v in self.staged.items())
        return self.changes

    def roll_pitch_due(self, roll_pitch_tuned: bool) -> bool:
        """True once roll and pitch are identified, where they go onboard ahead of yaw
        (:data:`HAND_ROLL_PITCH_FIRST`), yaw's relay still runs (done, or none: the one
        hand-over writes all three at once) and neither hand-over has run."""
        yaw_running = self.yaw is not None and not self.yaw.done
        return (HAND_ROLL_PITCH_FIRST and roll_pitch_tuned and yaw_running
                and not self.rp_onboard and not self.handed_over and self.backup is not None)

    def hand_over_roll_pitch(self, client: ParamClient, hold: Callable[[float], None],
                             refs: Callable[[], tuple[float, float]]) -> None:
        """Roll and pitch onto the onboard cascade, yaw's relay test going on meanwhile.

        :meth:`hand_over`'s stages on roll and pitch's parameters alone
        (:func:`roll_pitch_names`; :meth:`split` staged their written values): rate P, then
        the feed-forward (the rates sent invert each), then the onboard target set onto the
        body (the rate feed-forward switched off, the body's attitude sent with yaw's rate
        beside it, :func:`beside_yaw`) and their angle P and the rest written, the switch
        back on. From then the set point is ``refs()`` (the sequence's roll, pitch in rad) as
        an attitude with yaw's torque as its body-rate feed-forward. PID_TUNING of roll and
        pitch is no longer judged (their P, I and D are on). Yaw, the shared parameters and
        the rate feed-forward switch's final value wait for :meth:`hand_over`.
        """
        if self.rp_onboard or self.handed_over:
            return
        p, channel = self.params, self.channel
        final = self._final()
        names = roll_pitch_names(p)
        t0 = time.monotonic()
        # roll and pitch's rate loops are no longer pure feed-forward from the first write
        self._onboard_axes.update((1, 2))
        self._write(client, {n: final[n] for n in p.rate_p[:2]})
        channel.rate_p[:2] = [final[n] for n in p.rate_p[:2]]
        hold(STAGE_HOLD_S)
        self._write(client, {n: final[n] for n in p.ff[:2]})
        channel.ff[:2] = [final[n] for n in p.ff[:2]]
        hold(STAGE_HOLD_S)
        off = channel.last
        aligned = TARGET_SET_PARAM in p.test_params
        channel.refs = refs
        channel.yaw_d = math.nan
        channel.rp_onboard = True
        if aligned:
            # not recorded as restored: an abort from here puts the vehicle's own value back
            client.write_known({TARGET_SET_PARAM: 0.0}, self.known)
            channel.hold_body = True
            hold(ALIGN_HOLD_S)
        rest = {n: final[n] for n in p.angle_p[:2]}
        rest.update({n: final[n] for n in names if n not in rest})
        try:
            self._write(client, rest)
            if aligned:  # the test's value (yaw's feed-forward needs it) until hand_over
                client.write_known({TARGET_SET_PARAM: p.test_params[TARGET_SET_PARAM]},
                                   self.known)
        finally:
            channel.hold_body = False
        self.rp_onboard = True
        t_done = time.monotonic()
        self._t_rp_s = t_done  # yaw's wait counts from here
        if self.t_engaged is not None:
            self.zero_gain_axes_s["roll"] = self.zero_gain_axes_s["pitch"] = (
                t_done - self.t_engaged)
        self.notes.append(
            f"rate path: roll and pitch onto the onboard cascade "
            f"{self.zero_gain_axes_s.get('roll', math.nan):.1f} s after the test parameters "
            f"(their zero-gain window), in {t_done - t0:.2f} s (rate P, feed-forward, then "
            f"angle P and the rest), yaw's relay test going on beside them"
            + ("" if off is None else
               f"; the target {math.degrees(off.thrust_error_rad):.1f} deg thrust off the "
               f"body" + (", set onto it first" if aligned else "")))

    def target_filter_hz(self, axis: int) -> float:
        """The rate-target filter (Hz; 0: none) the onboard ``axis`` (0 roll, 1 pitch) flies
        after the hand-over: the vehicle's own ``<rate P name less P>FLTT``, which the test
        parameters zero and the hand-over puts back."""
        name = self.params.rate_p[axis].removesuffix("P") + "FLTT"
        hz = self._final().get(name, 0.0)
        return float(hz) if math.isfinite(hz) and hz > 0 else 0.0

    def _rp_filters(self, client: ParamClient, axis: int) -> tuple[float, float]:
        """``(FLTE, FLTD)`` of roll/pitch ``axis`` as the vehicle has them (Hz; 0: none):
        an unread FLTE is taken as none (ArduCopter's default), an unread FLTD as
        :data:`~mrft_gcs.flight.structure.DEFAULT_D_HZ`."""
        prefix = self.params.rate_p[axis].removesuffix("P")
        out = []
        for suffix, default in (("FLTE", 0.0), ("FLTD", DEFAULT_D_HZ)):
            try:
                v = float(client.read(prefix + suffix).value)
            except MrftError:
                v = default
            out.append(v if math.isfinite(v) and v >= 0 else default)
        return out[0], out[1]

    def _gyro_filter_hz(self, client: ParamClient) -> float:
        """The vehicle's ``INS_GYRO_FILTER`` (Hz): the low-pass on the gyro its rate loop
        closes on; 0 (none) where it has no such parameter or a value that is no cutoff."""
        try:
            v = float(client.read(GYRO_FILTER_PARAM).value)
        except MrftError:
            return 0.0
        return v if math.isfinite(v) and v > 0 else 0.0

    def rp_structure(self, axis: int) -> OnboardStructure:
        """How ArduCopter closes ``axis`` (0 roll, 1 pitch) after the hand-over: its own
        rate-target filter (:meth:`target_filter_hz`), error and D low-passes (read at
        :meth:`engage`), its gyro filter (:data:`GYRO_FILTER_PARAM`, read there too), and
        rate D at ArduCopter's own ratio to rate P
        (:data:`~mrft_gcs.flight.structure.RATE_D_OVER_P_S`, where
        :data:`~mrft_gcs.flight.structure.WRITE_RATE_D`)."""
        fe, fd = (self.rp_filters or {}).get(axis, (0.0, DEFAULT_D_HZ))
        return OnboardStructure(self.target_filter_hz(axis), "ArduCopter's cascade",
                                RATE_D_OVER_P_S if WRITE_RATE_D else 0.0, fd, fe,
                                gyro_hz=self.gyro_hz)

    def roll_pitch_gains(self, model: InnerModel, gains: PD, axis: int,
                         delay_out_s: float = 0.0) -> CascadeGains:
        """The written gains of ``axis`` (0 roll, 1 pitch) designed on ArduCopter's cascade
        as it flies them after the hand-over (:meth:`rp_structure`): the identified
        gains where they keep the margin there, or gains with rate D where that lowers the
        ISE (:func:`~mrft_gcs.flight.structure.cascade_design`), with a rate I of
        :data:`RATE_I_DECADE`, on ``model`` less ``delay_out_s`` of the ground station's
        delay (s). :meth:`split` writes the I and D in place of the 0 the PD mapping gives."""
        c = cascade_design(model, gains, self.rp_structure(axis), decade=RATE_I_DECADE,
                           delay_out_s=delay_out_s)
        prefix = self.params.rate_p[axis].removesuffix("P")
        self.rate_i[prefix + "I"] = c.rate_i
        if c.d_over_p_s > 0:
            self.rate_d[prefix + "D"] = (self.params.rate_p[axis], c.d_over_p_s)
        else:
            self.rate_d.pop(prefix + "D", None)
        return c

    def cascade(self, client: ParamClient, axis: int) -> OnboardCascade:
        """The onboard attitude cascade of ``axis`` (0 roll, 1 pitch) after the hand-over,
        for the in-air check: the rate loop's target filter and feed-forward as restored
        (the vehicle's own), its error filter as read (not a test parameter; 0 if the
        vehicle has none). Names are ArduCopter's (``<rate P less P>FLTT``/``FLTE``)."""
        final = self._final()
        prefix = self.params.rate_p[axis].removesuffix("P")
        fltt = final.get(prefix + "FLTT", math.nan)
        try:
            flte = client.read(prefix + "FLTE").value
        except MrftError:
            flte = 0.0
        # the written rate I and D (roll_pitch_gains) close the loop too: I / P, D / P
        p, i = final.get(self.params.rate_p[axis], 0.0), final.get(prefix + "I", 0.0)
        d = final.get(prefix + "D", 0.0)
        wi = i / p if p > 0 and math.isfinite(i) and i > 0 else 0.0
        r = d / p if p > 0 and math.isfinite(d) and d > 0 else 0.0
        fd = (self.rp_filters or {}).get(axis, (0.0, DEFAULT_D_HZ))[1]
        return OnboardCascade(fltt if math.isfinite(fltt) else 0.0, flte,
                              final.get(self.params.ff[axis], 0.0), integrator_zero_rad_s=wi,
                              d_over_p_s=r, d_filter_hz=fd if r > 0 else 0.0,
                              gyro_hz=self.gyro_hz)

    @contextlib.contextmanager
    def small_signal(self, client: ParamClient) -> Iterator[None]:
        """:data:`CHECK_PARAMS` for the in-air check (backed up first), put back after it;
        a failed put-back is noted (the backup named) rather than raised over the check's
        own outcome."""
        result = client.write(CHECK_PARAMS, self.backup_dir, label="check")
        known = {e.param.name: e.param for e in read_params_file(result.backup_path)}
        try:
            yield
        finally:
            try:
                client.write_known({c.name: c.old for c in result.changes}, known)
            except MrftError as err:
                self.notes.append(f"rate path: the in-air check's settings were not put back "
                                  f"({err}): restore {result.backup_path} by hand")

    def rewritten(self, changes: tuple[ParamChange, ...]) -> tuple[ParamChange, ...]:
        """Record gains re-written after the hand-over (the in-air check's re-design): those
        among the test parameters become the staged values (their old value stays the one
        from before the tune). Returns the other changes."""
        rest = []
        for c in changes:
            if c.name in self.params.test_params and self.handed_over:
                self.staged[c.name] = c.new
            else:
                rest.append(c)
        self.changes = tuple(ParamChange(n, self.originals.get(n, math.nan), v)
                             for n, v in self.staged.items())
        return tuple(rest)

    def keep_integrator_zero(self, values: Mapping[str, float]) -> dict[str, float]:
        """``values`` (gains re-written after the hand-over, their rate I and D as the PD
        mapping gives them: 0) with each roll/pitch rate I and D at the new rate P times the
        ratio written at the hand-over (``I / P``, ``D / P``), which the in-air check's
        cascade model holds."""
        out, final = dict(values), self._final()
        for name in self.params.rate_p[:2]:
            p0 = final.get(name, 0.0)
            for suffix in ("I", "D"):
                x_name = name.removesuffix("P") + suffix
                x0 = final.get(x_name, 0.0)
                if name in out and x_name in out and p0 > 0 and math.isfinite(x0) and x0 > 0:
                    out[x_name] = out[name] * x0 / p0
        return out

    def inner_due(self, roll_pitch_tuned: bool) -> bool:
        """True once roll and pitch are identified and the hand-over has not run: the side
        tests then fly on the written gains onboard (as on the attitude path), and the
        zero-gain window closes there. A yaw relay must be done too (identified or given
        up: it gives up within its own time limit)."""
        if roll_pitch_tuned and not self.handed_over and (self.rp_onboard
                                                          or not HAND_ROLL_PITCH_FIRST):
            self._yaw_wait()
        yaw_done = self.yaw is None or self.yaw.done
        return roll_pitch_tuned and yaw_done and not self.handed_over and self.backup is not None

    def _yaw_wait(self) -> None:
        """Roll and pitch are identified (onboard, or on the ground station's PDs): yaw's
        relay gives up where they ring (:data:`RING_RMS_RAD_S`) or after
        :data:`YAW_AFTER_ROLL_PITCH_S`, so that the hand-over comes."""
        relay, now = self.yaw, time.monotonic()
        if not math.isfinite(self._t_rp_s):
            self._t_rp_s = now
        if relay is None or relay.done or relay.state is YawState.READY:
            return  # READY: its cycles are being identified
        waited, rms = now - self._t_rp_s, self.channel.rp_rms
        if waited > RING_AFTER_S:
            self.rp_rms_max = np.maximum(self.rp_rms_max, rms)
        if (why := yaw_wait_over(waited, rms, self.rp_onboard)) is not None:
            relay.give_up(why)

    def merged_backup(self, other: str | None) -> str:
        """A backup file with the values from before the tune of every parameter it wrote:
        ``other`` (the write-back's own backup) plus the written test parameters' originals
        (the write-back itself saw them at their test values)."""
        assert self.backup is not None
        entries = {e.param.name: e.param for e in read_params_file(self.backup)
                   if e.param.name in self.staged}
        if other:
            for e in read_params_file(other):
                entries.setdefault(e.param.name, e.param)
        path = self.backup_dir / f"{self.backup.stem.replace('rate-test', 'backup')}.params"
        write_params_file(path, entries.values(), self.link.target_system,
                          self.link.target_component, stack=self.link.family.value)
        return str(path)

    # -------------------------------------------------------------- abort, restore
    def abort(self, client: ParamClient) -> None:
        """Before a landing command on any abort: zero rates, then the vehicle's own gains
        back (a landing on zero gains would tumble)."""
        self.channel.released = True
        self.channel.hold_body = False
        self._checking = False
        self.restored -= set(self.staged)  # an abort puts the vehicle's own values back
        with contextlib.suppress(MrftError):
            self.link.send_rate_target(RateTarget(0.0, 0.0, 0.0, 0.0, self.channel.last_thrust))
        self.restore_rest(client, keep_written=False)

    def restore_rest(self, client: ParamClient, keep_written: bool = True) -> None:
        """Every test parameter not yet back, at its value from before the tune (with
        ``keep_written``, the tune's written gains instead where it wrote them)."""
        if self.backup is None:
            return
        left = {n: v for n, v in self._final(keep_written).items() if n not in self.restored}
        if not left:
            return
        try:
            self._write(client, left)
        except MrftError as err:
            self.notes.append(f"rate path: the test parameters were not all restored ({err}): "
                              f"restore {self.backup} by hand")
        else:
            self.notes.append(f"rate path: {len(left)} test parameters restored")


def check_profile(profile: AutopilotProfile) -> RatePathParams:
    """The profile's ``[rate_path]`` or a UsageError saying what to use instead."""
    if profile.rate_path is None:
        raise UsageError(f"profile {profile.name} has no [rate_path]: use --actuation "
                         f"attitude or torque")
    return profile.rate_path
