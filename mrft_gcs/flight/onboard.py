"""From the gains of the GCS-side loop to the gains written to the autopilot.

During a live tune the relay runs on the ground station: each command answers a
telemetry sample and acts on the vehicle some time after it, so the process the
identification sees carries more delay than the autopilot's own loop will. The
identified PD is right for the GCS-side loop (it runs there during the side
tests and the hover); the written gains are re-targeted to the onboard loop:

``gains_onboard = gains_identified * PD*(model, tau - d) / PD*(model, tau)``

per gain, where ``PD*`` is the ISE-optimal PD (docs/method.md) of the identified model and
``d`` the GCS delay. The ratio keeps the identification's choice of tuning rule
and only moves it by the change the delay makes. ``d`` is never allowed to take
more than half of the identified delay (the correction is steep: over-correcting
erodes the phase margin on the true process).

``d`` is measured (:func:`measure_gcs_delay`): over the identified cycles, how old each
telemetry sample was when the first command answering it left, counted from the earliest
the link delivers a sample stamped with that vehicle time: the lower envelope of
receive-minus-vehicle time kept up to date over the session
(:mod:`mrft_gcs.link.clock`: drift and slips of the vehicle's clock tracked; a .tlog
reader places commands on the vehicle clock through the same fit, so dry-run measures the
same on the session's log). Telemetry and the stream's ticks are not synchronised: at
250 Hz both, their phase is fixed for a session at whatever it happened to be, so this
age is anywhere from 0 to 4 ms from one tune to the next (measured live: session means
1.4-4.9 ms), plus the reader's and the stream's lateness on a loaded machine. The link's
own latency both ways is not in these ages: it is the round trip of a message the vehicle
answers at once (TIMESYNC), added to ``d`` where the link check timed it; a round trip
also holds the vehicle's and the readers' handling, so the plausible range starts
:data:`ROUND_TRIP_SLACK_S` below it. Left in, it makes the written gains those of a loop
with up to twice the link's latency more delay than the autopilot's: cautious.
Without a measurement (too few samples) or
with an implausible one (most ages at the clip, a mean over 1.5 setpoint periods plus the
link's one-way latency, a vehicle clock that slipped during the cycles or drifts over
1000 ppm), ``d`` is half a setpoint period (:func:`gcs_delay_s`), the mean of an
unsynchronised wait, and the plausible range starts at 0.

Robust over what is left open (:func:`robust_onboard_gains`): the onboard loop's delay is
``tau - d_true`` with ``d_true`` anywhere in the plausible range ``[d_lo, d_hi]``; removing
more than ``d_true`` leaves it less margin than designed, so the written gains must keep
a phase margin of :data:`PM_ROBUST_DEG` on the model with ``tau - d_lo``: ``d`` is held
back towards 0 until they do.

A busy host: a vehicle whose loop falls behind real time slips its clock; ages counted
from a clock offset taken once grow with every slip, so the clock is modelled and
implausible measurements are rejected (:mod:`mrft_gcs.link.clock`).

Why it matters: a short-delay attitude loop loses a few % of J per millisecond of GCS delay
left in its gains, and a fixed guess is wrong both ways with the session's phase; the
identification does not resolve all of the GCS delay either, hence the cap below. The
figures behind each choice: docs/writing-gains.md.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from mrft_gcs.identify import Identification
from mrft_gcs.link.clock import ClockFit
from mrft_gcs.loops import Loop, LoopKind
from mrft_gcs.pd_design import frequency_grid, ise, margins, optimal_pd
from mrft_gcs.plant import (
    PD,
    InnerModel,
    SideModel,
    closed_inner_response,
    inner_response,
    loop_response,
    side_response,
)

__all__ = ["onboard_gains", "gcs_delay_s", "command_delay_s", "retarget_delay_s",
           "first_answers", "GcsDelay", "measure_gcs_delay", "Retarget",
           "robust_onboard_gains", "PM_ROBUST_DEG", "ROUND_TRIP_SLACK_S", "SideRetarget",
           "onboard_side_gains", "SideLoop", "shared_side_gains", "SHARED_ISE_SLACK",
           "onboard_extra_delay_s", "CAP_SHARE", "CERTAIN_CAP_SHARE",
           "POSITION_LOOP_MIN_HZ", "RATE_TARGET_MIN_HZ", "CascadeGains", "cascade_gains",
           "CASCADE_LOOP_HZ", "rate_loop_gains", "RATE_I_LOWEST", "PositionLoopRate",
           "cascade_controller", "cascade_process", "cascade_delay_out_s",
           "POSITION_RATE_PARAMS", "read_position_rate", "vehicle_position_rate",
           "ALT_UNSURE_TOP_PROB", "ALT_UNSURE_EXTRA_PM_DEG", "ALT_UNSURE_RAMP",
           "ALT_ONBOARD_DELAY_MIN_S",
           "robust_pm_deg", "pooled_attitude", "pooled_note",
           "POOL_ATTITUDE_LAGS"]


def gcs_delay_s(setpoint_period_s: float) -> float:
    """Delay re-targeted out of the identified inner loops for a GCS relay (s).

    >>> gcs_delay_s(0.004)
    0.002
    """
    return 0.5 * setpoint_period_s


#: ages over this many setpoint periods are a stall, not the loop's steady delay: clipped
AGE_CLIP_PERIODS = 3.0
#: fewer aged samples than this in a window: no measurement
MIN_AGED_SAMPLES = 20
#: a measurement with more than this share of its ages at the clip is a stalled clock
#: or stream, not the loop's delay: rejected
CLIP_SHARE_MAX = 0.25
#: a mean age over this many setpoint periods (plus the link's one-way latency) is
#: implausible: a first answer waits at most one period for its tick
MEAN_MAX_PERIODS = 1.5
#: a vehicle clock drifting more than this against the ground station's is not measured
SKEW_MAX_PPM = 1000.0
#: the phase margin the written gains keep on the onboard loop over the plausible range
PM_ROBUST_DEG = 15.0
#: the most of the identified delay a re-target may take out: an identification may put
#: some of the delay into the lags, which no margin check on the model can see
CAP_SHARE = 0.75
#: the most of the identified delay the least plausible GCS delay (measured: the link's
#: round trip, the ages) may take out where that is more than :data:`CAP_SHARE`
CERTAIN_CAP_SHARE = 0.95
#: the onboard position loop's rate allowed for where the vehicle does not say what it is
#: (Hz; the slowest either firmware runs by default): its sample-and-hold is delay the
#: altitude and side loops have onboard and did not have during the GCS-side tests
POSITION_LOOP_MIN_HZ = 50.0
#: x and y share one PD (:func:`shared_side_gains`): how much more ISE than its own design
#: (as a share of it) the loop with the faster design is left with
SHARED_ISE_SLACK = 0.05
#: the lowest rate-target low-pass (Hz) an autopilot's attitude loop is allowed to have
#: unseen (ArduPilot's ATC_RAT_*_FLTT): it slows the closed attitude loop the side loops
#: are flown behind
RATE_TARGET_MIN_HZ = 10.0
#: what a timed round trip may hold beyond the link's own delay both ways (s): the vehicle
#: answering at its next loop (4 ms at 250 Hz, 1 ms at 1 kHz) and the readers; taken off
#: the round trip for the least GCS delay that is plausible
ROUND_TRIP_SLACK_S = 0.002
#: an altitude classifier whose likeliest shape has less probability than this is unsure
#: between shapes that split the lag differently between the slow pole and the fast lags;
#: the cycle fits both, but the fast lags it leaves out cost margin onboard
ALT_UNSURE_TOP_PROB = 0.6
#: the extra phase margin (deg) the written gains of such an altitude loop keep on its
#: identified model (:func:`robust_pm_deg`), all of it from :data:`ALT_UNSURE_RAMP` below
#: :data:`ALT_UNSURE_TOP_PROB` down, in proportion above
ALT_UNSURE_EXTRA_PM_DEG = 6.0
ALT_UNSURE_RAMP = 0.1
#: whether roll and pitch are designed on their fast lags pooled (:func:`pooled_attitude`)
POOL_ATTITUDE_LAGS = True
#: the least delay a vehicle's own altitude loop has onboard (s: ESC and motor protocol, the
#: position estimate): an altitude re-target leaves at least this much of the identified
#: delay, which may have put part of the GCS delay into the lags (T1, T_prop) instead
ALT_ONBOARD_DELAY_MIN_S = 0.005


def first_answers(sample_t_s, ages_s) -> np.ndarray:
    """Per distinct sample time, the age at the first command that answered it (s).

    A command that answers the same sample again (no new sample by its tick) adds no delay
    to the loop: the relay switched on the first.

    >>> first_answers([1.0, 1.0, 1.004, 1.008, 1.008], [0.001, 0.005, 0.002, 0.0, 0.004])
    array([0.001, 0.002, 0.   ])
    """
    t = np.asarray(sample_t_s, dtype=float)
    a = np.asarray(ages_s, dtype=float)
    ok = np.isfinite(t) & np.isfinite(a)
    t, a = t[ok], a[ok]
    order = np.lexsort((a, t))
    t, a = t[order], a[order]
    return a[np.diff(t, prepend=-np.inf) > 0]
def command_delay_s(ages_s, setpoint_period_s: float) -> float:
    """The GCS delay of a relay loop from its samples' ages (s; NaN: too few).

    The mean age, each clipped to :data:`AGE_CLIP_PERIODS` setpoint periods.

    >>> command_delay_s([0.002] * 24 + [0.2], 0.004)  # the stall counts as 12 ms
    0.0024
    >>> command_delay_s([0.002] * 5, 0.004)
    nan
    """
    a = np.asarray(ages_s, dtype=float)
    a = a[np.isfinite(a)]
    if a.size < MIN_AGED_SAMPLES:
        return float("nan")
    return round(float(np.mean(np.clip(a, 0.0, AGE_CLIP_PERIODS * setpoint_period_s))), 9)


def retarget_delay_s(ages_s, setpoint_period_s: float) -> tuple[float, bool]:
    """The delay to re-target out of a relay loop's written gains (s), and whether it was
    measured: :func:`command_delay_s` of the ages, else half a period (:func:`gcs_delay_s`).

    >>> retarget_delay_s([], 0.004)
    (0.002, False)
    """
    d = command_delay_s(ages_s, setpoint_period_s)
    return (d, True) if np.isfinite(d) else (gcs_delay_s(setpoint_period_s), False)


def onboard_gains(ident: Identification, delay_s: float) -> PD:
    """Gains for the onboard loop of an identified inner loop, ``delay_s`` less delay.

    Side loops (and ``delay_s <= 0``) keep the identified gains.

    >>> from mrft_gcs.loops import LoopKind
    >>> m = InnerModel(K=40.0, T_prop=0.02, T1=0.25, tau=0.02)
    >>> i = Identification(LoopKind.ATTITUDE, m, 0, 1.0, -0.8, 0.1, 0.25, 0.03, PD(1.0, 0.1))
    >>> g = onboard_gains(i, 0.004)
    >>> g.Kc > 1.0 and g.Kd > 0.1
    True
    """
    m = ident.model
    if not isinstance(m, InnerModel) or not delay_s > 0:
        return ident.gains
    d = min(delay_s, 0.5 * m.tau)

    def best(tau: float) -> PD:
        w = frequency_grid(m.T_prop, m.T1, tau)
        return optimal_pd(inner_response(m.K, m.T_prop, m.T1, tau, w)[0], w).pd

    p0, p1 = best(m.tau), best(m.tau - d)
    return PD(ident.gains.Kc * p1.Kc / p0.Kc, ident.gains.Kd * p1.Kd / p0.Kd)


@dataclass(frozen=True)
class GcsDelay:
    """The GCS delay of one relay loop: what was measured, what is plausible, what to use.

    Attributes
    ----------
    estimate_s : float
        The delay to re-target by, before the robust check (s): the measurement when
        plausible, else half a setpoint period.
    lo_s, hi_s : float
        The plausible range of the true GCS delay (s).
    measured_s : float
        The mean first-answer age, each clipped at :data:`AGE_CLIP_PERIODS` periods (s;
        NaN: too few samples).
    measured : bool
        The ages' measurement is in ``estimate_s`` (it was plausible).
    why : str
        Why the measurement was not used ("" when it was).
    round_trip_s : float
        The link's timed round trip included in ``estimate_s`` (s; 0: none).
    """

    estimate_s: float
    lo_s: float
    hi_s: float
    measured_s: float
    measured: bool
    why: str = ""
    round_trip_s: float = 0.0


def measure_gcs_delay(ages_s, setpoint_period_s: float, *, sample_t_s=None,
                      clock: ClockFit | None = None, latency_s: float = 0.0,
                      round_trip_s: float = 0.0, round_trip_spread_s: float = 0.0) -> GcsDelay:
    """The GCS delay of a relay loop from its samples' ages, checked for plausibility.

    Parameters
    ----------
    ages_s : array (m,)
        How old each sample was when a command answering it left (s), on ``clock``.
    setpoint_period_s : float
        The stream's period (s).
    sample_t_s : array (m,), optional
        The samples' vehicle times (s): only the first answer of each counts
        (:func:`first_answers`), and a slip of ``clock`` between the first and last is
        a reason to reject.
    clock : ClockFit, optional
        The clock model the ages were measured on: its slips, skew, spread and stamp
        resolution widen or reject the measurement.
    latency_s : float
        The link's one-way latency where measured (s), allowed on top of the ages.
    round_trip_s : float
        The link's round trip where timed by a message the vehicle answers at once
        (TIMESYNC, median; s; 0: not timed). Each telemetry sample comes down and each
        command goes up over it, so it is part of the GCS delay: added to the estimate
        and, less :data:`ROUND_TRIP_SLACK_S` (the vehicle's and the readers' handling
        that a timed round trip holds and the loop need not), to the plausible range.
    round_trip_spread_s : float
        How far the round trips spread above their median (s; e.g. p90 - p50): a busy
        host delays the readers and inflates the median, so the plausible range starts
        that much lower too.

    Examples
    --------
    >>> g = measure_gcs_delay([0.002] * 30, 0.004)
    >>> g.measured, g.estimate_s, g.lo_s
    (True, 0.002, 0.002)
    >>> g = measure_gcs_delay([0.012] * 30, 0.004)  # every age at the clip
    >>> g.measured, g.estimate_s, g.lo_s, g.why
    (False, 0.002, 0.0, '100 % of the ages at the 12.0 ms clip')
    >>> g = measure_gcs_delay([0.002] * 30, 0.004, round_trip_s=0.010)  # 5 ms each way
    >>> round(g.estimate_s, 6), round(g.lo_s, 6), round(g.hi_s, 6)
    (0.012, 0.01, 0.016)
    >>> g = measure_gcs_delay([0.002] * 30, 0.004, round_trip_s=0.010, round_trip_spread_s=0.005)
    >>> round(g.lo_s, 6)  # a jittery round trip: less of it is sure to be the link's
    0.005
    """
    rtt = round_trip_s if math.isfinite(round_trip_s) and round_trip_s > 0 else 0.0
    spread_rtt = round_trip_spread_s if math.isfinite(round_trip_spread_s) else 0.0
    link_lo = max(0.0, rtt - max(spread_rtt, 0.0) - ROUND_TRIP_SLACK_S)
    p = setpoint_period_s
    a = np.asarray(ages_s, dtype=float)
    if sample_t_s is not None:
        t = np.asarray(sample_t_s, dtype=float)
        window = (float(np.nanmin(t)), float(np.nanmax(t))) if len(t) else None
        a = first_answers(t, a)
    else:
        a, window = a[np.isfinite(a)], None
    hi_default = p + latency_s

    def fallback(why: str, measured_s: float = math.nan) -> GcsDelay:
        return GcsDelay(gcs_delay_s(p) + rtt, link_lo, hi_default + rtt, measured_s, False,
                        why, rtt)

    if a.size < MIN_AGED_SAMPLES:
        return fallback(f"{a.size} samples, too few to measure")
    clip = AGE_CLIP_PERIODS * p
    m = round(float(np.mean(np.clip(a, 0.0, clip))), 9)
    share = float(np.mean(a >= clip - 1e-9))
    if share > CLIP_SHARE_MAX:
        return fallback(f"{share:.0%} of the ages at the {clip * 1e3:.1f} ms clip".replace(
            "%", " %"), m)
    if m > MEAN_MAX_PERIODS * p + latency_s:
        return fallback(f"mean age {m * 1e3:.1f} ms is over {MEAN_MAX_PERIODS:g} setpoint "
                        f"periods plus the link's latency", m)
    spread = 0.0
    if clock is not None and not clock.empty:
        if abs(clock.skew_ppm) > SKEW_MAX_PPM:
            return fallback(f"the vehicle clock drifts {clock.skew_ppm:.0f} ppm against the "
                            f"ground station's", m)
        if window is not None and (slips := clock.slips_between(*window)):
            steps = ", ".join(f"{sl.step_s * 1e3:+.1f} ms" for sl in slips)
            return fallback(f"the vehicle clock slipped during the cycles ({steps})", m)
        spread = (clock.spread_s if math.isfinite(clock.spread_s) else 0.0) + clock.resolution_s
    return GcsDelay(m + rtt, max(0.0, m - spread) + link_lo, m + spread + hi_default + rtt, m,
                    True, "", rtt)


@dataclass(frozen=True)
class Retarget:
    """Gains written for the onboard loop, and the delay re-targeted out of them.

    Attributes
    ----------
    gains : PD
    delay_s : float
        The delay re-targeted out (s; 0: the identified gains).
    pm_deg : float
        Phase margin of ``gains`` on the identified model with ``tau - gcs.lo_s`` (deg;
        NaN: not an inner loop).
    gcs : GcsDelay
    cap_s : float
        The most that may be re-targeted: :data:`CAP_SHARE` of the identified delay (s).
    extra_s : float
        Delay the onboard loop may add unseen by the ground station, allowed for (s).
    structure : str
        The onboard controller structure the gains were designed on, where it is not the
        plain PD ("": the PD; :func:`mrft_gcs.flight.structure.structured_retarget`).
    d_over_p_s : float
        Rate D written as this share of rate P (s; 0: D written as 0), where the design on
        the structure chose one.
    """

    gains: PD
    delay_s: float
    pm_deg: float
    gcs: GcsDelay
    cap_s: float = math.inf
    extra_s: float = 0.0
    structure: str = ""
    d_over_p_s: float = 0.0

    @property
    def aimed_s(self) -> float:
        """The re-target aimed at before the margin check (s)."""
        return min(self.gcs.estimate_s, self.cap_s)

    @property
    def held_back(self) -> bool:
        """Less was re-targeted than the estimate (within the cap) to keep the margin."""
        return self.delay_s < self.aimed_s - 1e-9

    def note(self) -> str:
        """``re-targeted by X ms (measured Y ms, plausible Z..W ms)`` and why, if so."""
        g = self.gcs
        got = (f"measured {g.measured_s * 1e3:.1f} ms" if g.measured
               else f"not measured: {g.why}" if math.isnan(g.measured_s)
               else f"measured {g.measured_s * 1e3:.1f} ms, rejected: {g.why}")
        if g.round_trip_s > 0:
            got += f"; link round trip {g.round_trip_s * 1e3:.1f} ms"
        out = (f"re-targeted by {self.delay_s * 1e3:.1f} ms ({got}; plausible "
               f"{g.lo_s * 1e3:.1f}..{g.hi_s * 1e3:.1f} ms)")
        if self.extra_s > 0:
            out += (f"; up to {self.extra_s * 1e3:.1f} ms more onboard allowed for (its "
                    f"position loop's rate)")
        if self.held_back:
            out += (f", held back from {self.aimed_s * 1e3:.1f} ms to keep PM "
                    f"{self.pm_deg:.0f} deg at {g.lo_s * 1e3:.1f} ms"
                    + (" and that" if self.extra_s > 0 else ""))
        if self.structure:
            out += (f"; designed on the autopilot's structure ({self.structure}), PM "
                    f"{self.pm_deg:.0f} deg at {g.lo_s * 1e3:.1f} ms")
        return out


def _pm_deg(gains: PD, m: InnerModel, tau: float) -> float:
    w = frequency_grid(m.T_prop, m.T1, tau)
    L = loop_response(gains.Kc, gains.Kd, inner_response(m.K, m.T_prop, m.T1, tau, w), w)[0]
    mg = margins(L, w)
    return mg.pm_deg if mg.stable else -math.inf


def robust_pm_deg(ident: Identification, pm_min_deg: float = PM_ROBUST_DEG) -> float:
    """The phase margin (deg) the written gains of ``ident`` keep on its identified model:
    ``pm_min_deg``, plus up to :data:`ALT_UNSURE_EXTRA_PM_DEG` for an altitude loop whose
    classifier was unsure (its likeliest shape's probability under
    :data:`ALT_UNSURE_TOP_PROB`; all of it :data:`ALT_UNSURE_RAMP` below). Unsure there
    means the identified model may have put part of the fast lags (delay, propeller) into
    a slower ``T1``: the cycle's harmonics fit either, the onboard loop has the lags. A
    sure classifier's loop keeps ``pm_min_deg``: its J is not raised.

    >>> from mrft_gcs.identify.result import ClassifierVote, Diagnostics
    >>> from mrft_gcs.loops import LoopKind
    >>> m = InnerModel(K=70.0, T_prop=0.03, T1=3.7, tau=0.036)
    >>> vote = ClassifierVote(1, (1, 5, 2), 0.5, 0.0, 1, (0.47, 0.46, 0.05))
    >>> i = Identification(LoopKind.ALTITUDE, m, 0, 0.6, -0.7, 0.1, 0.56, 0.03, PD(3.8, 0.7),
    ...                    Diagnostics(classifier=vote))
    >>> robust_pm_deg(i)
    21.0
    >>> robust_pm_deg(dataclasses.replace(i, kind=LoopKind.ATTITUDE))
    15.0
    >>> v = dataclasses.replace(vote, probs=(0.55, 0.4, 0.05))  # half-way unsure
    >>> round(robust_pm_deg(dataclasses.replace(i, diagnostics=Diagnostics(classifier=v))), 6)
    18.0
    """
    vote = ident.diagnostics.classifier
    if ident.kind is not LoopKind.ALTITUDE or vote is None or not vote.probs:
        return pm_min_deg
    share = min(max((ALT_UNSURE_TOP_PROB - vote.probs[0]) / ALT_UNSURE_RAMP, 0.0), 1.0)
    return pm_min_deg + ALT_UNSURE_EXTRA_PM_DEG * share


def robust_onboard_gains(ident: Identification, gcs: GcsDelay,
                         pm_min_deg: float = PM_ROBUST_DEG, *, onboard_extra_s: float = 0.0,
                         cap_share: float = CAP_SHARE,
                         certain_share: float = CERTAIN_CAP_SHARE) -> Retarget:
    """:func:`onboard_gains` re-targeted by as much of ``gcs.estimate_s`` as keeps a phase
    margin of ``pm_min_deg`` on the identified model with ``tau - gcs.lo_s`` (the least
    GCS delay that is plausible, hence the most onboard delay); bisected towards the
    gains designed for that most onboard delay.

    ``onboard_extra_s`` is delay the onboard loop may add that the GCS-side loop did not
    have and the ground station cannot see (s; the position loop's sample-and-hold, see
    :func:`onboard_extra_delay_s`): the margin check takes all of it (more delay onboard,
    held back further; below 0, the gains of a loop with more delay than identified). The
    re-target is never more than ``cap_share`` of the identified delay, or the measured GCS
    delay (``gcs.estimate_s`` where ``gcs.measured``, else the least plausible, ``gcs.lo_s``)
    up to ``certain_share`` of it where that is more: a slow link's measured latency does not
    stay in the written gains.
    An altitude loop whose classifier was unsure keeps up to :data:`ALT_UNSURE_EXTRA_PM_DEG`
    more than ``pm_min_deg`` (:func:`robust_pm_deg`): its re-target is held back further.
    An altitude re-target never leaves less than :data:`ALT_ONBOARD_DELAY_MIN_S` of the
    identified delay: a GCS delay the identified delay cannot hold beside the vehicle's
    own went into the identified lags, where removing it from the delay does not take it.

    Examples
    --------
    >>> from mrft_gcs.loops import LoopKind
    >>> m = InnerModel(K=40.0, T_prop=0.02, T1=0.3, tau=0.012)
    >>> w = frequency_grid(m.T_prop, m.T1, m.tau)
    >>> pd = optimal_pd(inner_response(m.K, m.T_prop, m.T1, m.tau, w)[0], w).pd
    >>> i = Identification(LoopKind.ATTITUDE, m, 0, 1.0, -0.8, 0.1, 0.25, 0.03, pd)
    >>> r = robust_onboard_gains(i, GcsDelay(0.003, 0.0025, 0.008, 0.003, True))
    >>> r.delay_s, r.pm_deg >= 15.0
    (0.003, True)
    >>> r = robust_onboard_gains(i, GcsDelay(0.006, 0.0, 0.008, math.nan, False, "x"))
    >>> r.held_back, 0.0 < r.delay_s < 0.006, round(r.pm_deg)
    (True, True, 15)
    >>> r = robust_onboard_gains(i, GcsDelay(0.003, 0.0025, 0.008, 0.003, True),
    ...                          onboard_extra_s=0.004)
    >>> r.held_back, r.pm_deg >= 15.0
    (True, True)
    """
    m = ident.model
    extra = max(float(onboard_extra_s), 0.0)
    if not isinstance(m, InnerModel) or not (gcs.estimate_s > 0 or extra > 0):
        return Retarget(ident.gains, 0.0, math.nan, gcs)
    # a measured GCS delay (the ages on a synced clock), else the least plausible one (the
    # link's timed round trip), goes out up to certain_share of the identified delay whatever
    # cap_share says; the margin is still checked at the least plausible
    certain = gcs.estimate_s if gcs.measured else gcs.lo_s
    cap = max(cap_share * m.tau, min(certain, certain_share * m.tau))
    if ident.kind is LoopKind.ALTITUDE:
        cap = min(cap, max(m.tau - ALT_ONBOARD_DELAY_MIN_S, 0.0))
    lo_d = min(gcs.lo_s, cap) - extra  # the most onboard delay: tau - lo_d
    tau_on = max(m.tau - lo_d, 1e-6)
    d = min(gcs.estimate_s, cap)

    def best(tau: float) -> PD:
        w = frequency_grid(m.T_prop, m.T1, tau)
        return optimal_pd(inner_response(m.K, m.T_prop, m.T1, tau, w)[0], w).pd

    p0 = best(m.tau)

    def gains(dd: float) -> PD:
        if dd == 0:
            return ident.gains
        p1 = best(max(m.tau - dd, 1e-6))
        return PD(ident.gains.Kc * p1.Kc / p0.Kc, ident.gains.Kd * p1.Kd / p0.Kd)

    pm_min_deg = robust_pm_deg(ident, pm_min_deg)
    g = gains(d)
    pm = _pm_deg(g, m, tau_on)
    if pm < pm_min_deg:
        # largest re-target that keeps the margin, to 0.1 ms, from the gains designed for
        # the most onboard delay (their margin there is the design's)
        lo, hi = min(lo_d, 0.0) if extra > 0 else 0.0, d
        g_lo = gains(lo)
        pm_lo = _pm_deg(g_lo, m, tau_on)
        while hi - lo > 1e-4:
            mid = 0.5 * (lo + hi)
            g_mid = gains(mid)
            pm_mid = _pm_deg(g_mid, m, tau_on)
            if pm_mid >= pm_min_deg:
                lo, g_lo, pm_lo = mid, g_mid, pm_mid
            else:
                hi = mid
        d, g, pm = round(lo, 6), g_lo, pm_lo
    return Retarget(g, d, pm, gcs, cap, extra)


def pooled_attitude(roll: Identification, pitch: Identification
                    ) -> tuple[Identification, Identification]:
    """Roll and pitch with their fast lags pooled: the design's models for the onboard loops.

    Both axes fly on the same motors, sensors and link, so the propeller lag ``T_prop`` and
    the delay ``tau`` are one pair measured twice. One relay cycle pins its model at the
    cycle's frequency only: above it (where the onboard loop crosses over, 2-3 x higher once
    the GCS delay is out) a model that put some of the delay into ``T_prop`` or ``T1`` is off
    by several degrees, one way or the other, independently per axis. Each axis here gets the
    mean of the two ``T_prop`` and the mean of the two ``tau``, and its own ``T1`` and ``K``
    re-fitted so that its model still passes exactly through its own relay point (gain and
    phase at ``2 pi / period_s``): the cycle's constraint is kept, the split is averaged.
    The identified gains (flown GCS-side) stay. Where either is not an attitude loop's inner
    model, or an axis's phase at its cycle cannot be met with a ``T1`` (the needed lag is
    outside 0-90 deg), or :data:`POOL_ATTITUDE_LAGS` is off, both are returned unchanged.

    Examples
    --------
    >>> m1, m2 = InnerModel(180.0, 0.027, 0.42, 0.028), InnerModel(460.0, 0.020, 1.25, 0.027)
    >>> r = Identification(LoopKind.ATTITUDE, m1, 0, 1.0, -0.7, 0.06, 0.39, 0.11, PD(0.3, 0.04))
    >>> p = dataclasses.replace(r, model=m2, period_s=0.39)
    >>> pr, pp = pooled_attitude(r, p)
    >>> round(pr.model.T_prop, 4), round(pp.model.tau, 4), pr.gains == r.gains
    (0.0235, 0.0275, True)
    >>> w0 = 2 * math.pi / 0.39
    >>> g0, g1 = (inner_response(m.K, m.T_prop, m.T1, m.tau, [w0])[0, 0] for m in (m1, pr.model))
    >>> bool(np.isclose(g0, g1))
    True
    """
    models = (roll.model, pitch.model)
    if not (POOL_ATTITUDE_LAGS and roll.kind is LoopKind.ATTITUDE
            and pitch.kind is LoopKind.ATTITUDE
            and all(isinstance(m, InnerModel) for m in models)):
        return roll, pitch
    mr, mp = models
    assert isinstance(mr, InnerModel) and isinstance(mp, InnerModel)
    tp, tau = 0.5 * (mr.T_prop + mp.T_prop), 0.5 * (mr.tau + mp.tau)
    out = []
    for ident, m in ((roll, mr), (pitch, mp)):
        if not (math.isfinite(ident.period_s) and ident.period_s > 0):
            return roll, pitch
        w = 2 * math.pi / ident.period_s
        # the slow pole takes the lag the pooled fast lags leave of the phase at the cycle
        lag = math.atan(w * m.T1) + w * (m.tau - tau) + math.atan(w * m.T_prop) - math.atan(
            w * tp)
        if not 0.0 < lag < 0.5 * math.pi - 1e-6:
            return roll, pitch
        t1 = math.tan(lag) / w
        k = float(abs(inner_response(m.K, m.T_prop, m.T1, m.tau, [w])[0, 0])) * w * math.hypot(
            1.0, w * tp) * math.hypot(1.0, w * t1)
        out.append(dataclasses.replace(ident, model=InnerModel(k, tp, t1, tau)))
    return out[0], out[1]


def pooled_note(roll: Identification, pitch: Identification, pooled: Identification) -> str:
    """The report's line for roll and pitch designed on ``pooled`` fast lags
    (:func:`pooled_attitude`; ms).

    >>> r = Identification(LoopKind.ATTITUDE, InnerModel(180.0, 0.027, 0.42, 0.028), 0, 1.0,
    ...                    -0.7, 0.06, 0.39, 0.11, PD(0.3, 0.04))
    >>> p = dataclasses.replace(r, model=InnerModel(460.0, 0.020, 1.25, 0.027))
    >>> pooled_note(r, p, pooled_attitude(r, p)[0])[:74]
    'roll and pitch written gains designed on their fast lags pooled (one motor'
    """
    def lags(i: Identification) -> str:
        m = i.model
        return (f"T_prop {m.T_prop * 1e3:.1f}, tau {m.tau * 1e3:.1f}"
                if isinstance(m, InnerModel) else "-")

    return (f"roll and pitch written gains designed on their fast lags pooled (one motor lag "
            f"and one delay, measured by both relays): roll {lags(roll)}, pitch {lags(pitch)} "
            f"-> {lags(pooled)} ms, each axis's slow pole and gain re-fitted through its own "
            f"relay cycle")


# ----------------------------------------------------------------------- side loops
@dataclass(frozen=True)
class SideRetarget:
    """Side gains written behind the written attitude gains.

    Attributes
    ----------
    gains : PD
    share : float
        How much of the move from the identified gains to those of the onboard cascade
        the margin over the plausible range allowed (1: all). Below 1, ``gains`` are the
        better (on the nominal cascade) of that shrunk move and the ISE-optimal PD under
        the same margin.
    pm_deg : float
        Phase margin of ``gains`` on the onboard cascade with the attitude loop at the
        least plausible GCS delay (deg).
    """

    gains: PD
    share: float
    pm_deg: float

    def note(self) -> str:
        out = "re-designed behind the written attitude gains"
        if self.share < 1.0:
            out += (f" (held back for PM {self.pm_deg:.0f} deg over the plausible GCS delay, "
                    f"an unseen rate-target filter and position-loop rate)")
        return out


def _side_process(inner: InnerModel, inner_pd: PD, tau: float, side: SideModel,
                  w: np.ndarray, target_hz: float = 0.0, d_over_p_s: float = 0.0,
                  d_hz: float = 0.0) -> np.ndarray:
    """The side cascade behind ``inner_pd``; ``target_hz`` > 0: with the angle P's rate
    target low-passed there (ArduPilot's FLTT), ``u = Kd (F Kc/Kd e - w)``, and with a rate
    D ``d_over_p_s`` times rate P on that rate error (low-passed at ``d_hz``, 0: none)."""
    g = inner_response(inner.K, inner.T_prop, inner.T1, max(tau, 1e-6), w)[0]
    if target_hz > 0:
        s = 1j * w
        f = 1.0 / (1.0 + s / (2 * np.pi * target_hz))
        fd = 1.0 / (1.0 + s / (2 * np.pi * d_hz)) if d_hz > 0 else 1.0
        g = g * (1.0 + d_over_p_s * s * fd)  # D multiplies both paths: fold it into g
        t_att = f * inner_pd.Kc * g / (1.0 + (f * inner_pd.Kc + inner_pd.Kd * s) * g)
    else:
        t_att = closed_inner_response(inner_pd.Kc, inner_pd.Kd, g[None, :], w)[0]
    return t_att * side_response(side.K, side.T2, side.tau, w)[0]


def onboard_side_gains(side: Identification, inner: Identification, inner_rt: Retarget,
                       pm_min_deg: float = PM_ROBUST_DEG, *,
                       onboard_extra_s: float = 0.5 / POSITION_LOOP_MIN_HZ,
                       target_hz: float | None = None, d_hz: float = 0.0) -> SideRetarget:
    """Side gains for the autopilot's cascade: behind the attitude gains it is written.

    A side loop is identified behind the ground station's attitude PD (``inner.gains``)
    on the attitude loop with the GCS delay; the autopilot flies it behind the written
    attitude gains (``inner_rt.gains``) on its own, faster loop (``tau - inner_rt.delay_s``).
    The side part (``K e^{-tau s}/((T2 s + 1) s)``, the position's delay relative to the
    angle's) is the same on both sides. As :func:`onboard_gains`, each gain moves by the
    ratio of the ISE-optimal PDs of the two cascades; the move is shrunk (in log) until
    the gains keep ``pm_min_deg`` with the attitude loop at the least plausible GCS delay
    (``inner_rt.gcs.lo_s``) and at the delay re-targeted, also with the attitude loop's
    rate target low-passed at :data:`RATE_TARGET_MIN_HZ` (a filter the ground station
    cannot read: ArduPilot-like cascades have one). ``onboard_extra_s``: delay the
    onboard position loop may add (s, :func:`onboard_extra_delay_s`), half of it designed
    for, all of it checked. Where the margin holds the move back, the ISE-optimal PD of the
    nominal cascade under that margin is taken instead when it is better.

    ``target_hz``: the attitude loop's rate-target low-pass where the vehicle said what it
    is (Hz, 0: none; :func:`mrft_gcs.flight.structure.read_structure`): the nominal cascade
    and every check then have that filter instead of the unseen :data:`RATE_TARGET_MIN_HZ`
    one. The attitude loop's rate D (``inner_rt.d_over_p_s`` times rate P, on the rate error
    behind that filter, low-passed at ``d_hz``) is in every onboard cascade.

    Examples
    --------
    >>> from mrft_gcs.loops import LoopKind
    >>> mi = InnerModel(K=40.0, T_prop=0.02, T1=0.3, tau=0.03)
    >>> ii = Identification(LoopKind.ATTITUDE, mi, 0, 1.0, -0.8, 0.1, 0.25, 0.03, PD(2.0, 0.2))
    >>> ms = SideModel(K=9.8, T2=1.5, tau=0.01)
    >>> si = Identification(LoopKind.SIDE, ms, 0, 1.0, -0.8, 0.1, 1.0, 0.1, PD(0.3, 0.25))
    >>> rt = robust_onboard_gains(ii, GcsDelay(0.012, 0.010, 0.016, 0.002, True, "", 0.01))
    >>> r = onboard_side_gains(si, ii, rt)
    >>> r.gains.Kc > 0.3, r.pm_deg >= 15.0
    (True, True)
    """
    case = _side_case(side, inner, inner_rt, pm_min_deg, onboard_extra_s, target_hz, d_hz)
    return case.result if case is not None else SideRetarget(side.gains, 0.0, math.nan)


@dataclass(frozen=True)
class _SideCase:
    """One side loop's onboard cascades (nominal, and those the margin is checked on) on
    the grid ``w``, the tuning rule's ``scale`` (identified over ISE-optimal gains on the
    GCS-side cascade) and its own design."""

    w: np.ndarray
    nominal: np.ndarray
    worst: tuple[np.ndarray, ...]
    scale: PD
    result: SideRetarget

    def pm(self, g: PD) -> float:
        """The least phase margin of ``g`` over the checked cascades (deg; -inf: unstable)."""
        s = 1j * self.w
        out = math.inf
        for G in self.worst:
            m = margins((g.Kc + g.Kd * s) * G, self.w)
            out = min(out, m.pm_deg if m.stable else -math.inf)
        return out

    def ise(self, g: PD) -> float:
        """ISE of ``g`` on the nominal cascade, in the tuning rule's units."""
        return ise(g.Kc / self.scale.Kc, g.Kd / self.scale.Kd, self.nominal, self.w)


def _side_case(side: Identification, inner: Identification, inner_rt: Retarget,
               pm_min_deg: float, onboard_extra_s: float, target_hz: float | None,
               d_hz: float) -> _SideCase | None:
    """The work of :func:`onboard_side_gains` (None: not an inner and a side model)."""
    mi, ms = inner.model, side.model
    if not isinstance(mi, InnerModel) or not isinstance(ms, SideModel):
        return None
    w = frequency_grid(mi.T_prop, mi.T1, mi.tau, extra_T=(ms.T2, ms.tau))
    s = 1j * w
    extra = max(float(onboard_extra_s), 0.0)
    g_gcs = _side_process(mi, inner.gains, mi.tau, ms, w)
    known = target_hz is not None and math.isfinite(target_hz) and target_hz >= 0
    f_on = float(target_hz) if known else 0.0  # type: ignore[arg-type]
    dd = (inner_rt.d_over_p_s, d_hz) if f_on > 0 else (0.0, 0.0)
    g_on = _side_process(mi, inner_rt.gains, mi.tau - inner_rt.delay_s, ms, w, f_on, *dd)
    lo = min(inner_rt.gcs.lo_s, inner_rt.delay_s)
    g_lo = g_on if lo >= inner_rt.delay_s else _side_process(
        mi, inner_rt.gains, mi.tau - lo, ms, w, f_on, *dd)
    worst = [g_lo, g_on] if known else [
        g_lo, g_on, _side_process(mi, inner_rt.gains, mi.tau - lo, ms, w, RATE_TARGET_MIN_HZ)]
    worst = [G * np.exp(-extra * s) for G in worst]
    p0, p1 = optimal_pd(g_gcs, w).pd, optimal_pd(g_on * np.exp(-0.5 * extra * s), w).pd

    def gains(share: float) -> PD:
        return PD(side.gains.Kc * (p1.Kc / p0.Kc) ** share,
                  side.gains.Kd * (p1.Kd / p0.Kd) ** share)

    def pm(g: PD) -> float:
        out = math.inf
        for G in worst:
            m = margins((g.Kc + g.Kd * s) * G, w)
            out = min(out, m.pm_deg if m.stable else -math.inf)
        return out

    best, share = gains(1.0), 1.0
    pm_best = pm(best)
    if pm_best < pm_min_deg:
        a, b = 0.0, 1.0  # the largest share that keeps the margin, to 1 %
        best, pm_best = side.gains, pm(side.gains)
        while b - a > 0.01:
            mid = 0.5 * (a + b)
            g = gains(mid)
            p = pm(g)
            if p >= pm_min_deg:
                a, best, pm_best = mid, g, p
            else:
                b = mid
        share = a
        # the shrunk move keeps the identified tuning rule; the ISE-optimal PD of the
        # nominal cascade under the margin over the plausible range may do better
        g_nom = g_on * np.exp(-0.5 * extra * s)
        scale = PD(side.gains.Kc / p0.Kc, side.gains.Kd / p0.Kd)

        def cost(x: np.ndarray) -> float:
            g = PD(float(np.exp(x[0])), float(np.exp(x[1])))
            short = max(0.0, pm_min_deg - pm(PD(g.Kc * scale.Kc, g.Kd * scale.Kd)))
            q = ise(g.Kc, g.Kd, g_nom, w)
            return q * (1.0 + 0.05 * short + 0.02 * short ** 2) if np.isfinite(q) else 1e12

        x0 = np.log([best.Kc / scale.Kc, best.Kd / scale.Kd])
        res = minimize(cost, x0, method="Nelder-Mead",
                       options={"xatol": 1e-4, "fatol": 1e-9, "maxiter": 400})
        cand = PD(float(np.exp(res.x[0])) * scale.Kc, float(np.exp(res.x[1])) * scale.Kd)
        pm_cand = pm(cand)
        if pm_cand >= pm_min_deg and (
                pm_best < pm_min_deg  # even the identified gains fall short
                or ise(cand.Kc / scale.Kc, cand.Kd / scale.Kd, g_nom, w)
                < ise(best.Kc / scale.Kc, best.Kd / scale.Kd, g_nom, w)):
            best, pm_best = cand, pm_cand
    return _SideCase(w, g_on * np.exp(-0.5 * extra * s), tuple(worst),
                     PD(side.gains.Kc / p0.Kc, side.gains.Kd / p0.Kd),
                     SideRetarget(best, share, float(pm_best)))


@dataclass(frozen=True)
class SideLoop:
    """What :func:`onboard_side_gains` designs one side loop from (see there).

    Attributes
    ----------
    side, inner : Identification
        The side loop's and its attitude loop's identifications.
    inner_rt : Retarget
        The attitude loop's written gains (:func:`robust_onboard_gains`).
    target_hz : float or None
        The attitude loop's rate-target low-pass (Hz; None: not read).
    d_hz : float
        Its rate D's low-pass (Hz; 0: none).
    """

    side: Identification
    inner: Identification
    inner_rt: Retarget
    target_hz: float | None = None
    d_hz: float = 0.0


def shared_side_gains(loops: Sequence[SideLoop], pm_min_deg: float = PM_ROBUST_DEG, *,
                      onboard_extra_s: float = 0.5 / POSITION_LOOP_MIN_HZ
                      ) -> dict[int, SideRetarget]:
    """One PD for side loops that share the autopilot's parameters (x and y: one position P
    and one velocity P on both firmwares), designed for all of them.

    Each loop's own design (:func:`onboard_side_gains`) is for its own cascade: behind
    attitude gains written apart for roll and pitch, x's and y's differ. Writing the
    smaller of each gain (what one parameter pair of two designs falls back on) leaves the
    faster loop well below its own, with more margin than asked. Here, from those smaller
    gains up to the faster design (on a log scale, in 2.5 % steps), the first that leaves
    every loop's nominal ISE within :data:`SHARED_ISE_SLACK` of its own design's is taken
    (none: the one nearest the designs' ISE, either way), under ``pm_min_deg`` on every
    loop's checked cascades (as :func:`onboard_side_gains`). Where no blend keeps the
    margin on both, or the designs agree, the smaller gains are kept.

    Returns
    -------
    dict
        ``{index in loops: SideRetarget}``: the shared gains, with each loop's own share
        and its margin (deg) under them; a loop not designable (not a side and an
        attitude model) keeps its identified gains and is left out of the shared design.

    Examples
    --------
    >>> from mrft_gcs.loops import LoopKind
    >>> mp = InnerModel(K=40.0, T_prop=0.02, T1=0.3, tau=0.03)
    >>> mr = InnerModel(K=40.0, T_prop=0.02, T1=0.3, tau=0.02)
    >>> ip = Identification(LoopKind.ATTITUDE, mp, 0, 1.0, -0.8, 0.1, 0.25, 0.03, PD(2.0, 0.2))
    >>> ir = Identification(LoopKind.ATTITUDE, mr, 0, 1.0, -0.8, 0.1, 0.25, 0.03, PD(2.6, 0.22))
    >>> ms = SideModel(K=9.8, T2=1.5, tau=0.01)
    >>> si = Identification(LoopKind.SIDE, ms, 0, 1.0, -0.8, 0.1, 1.0, 0.1, PD(0.3, 0.25))
    >>> d = GcsDelay(0.012, 0.010, 0.016, 0.002, True, "", 0.01)
    >>> x = SideLoop(si, ip, robust_onboard_gains(ip, d))
    >>> y = SideLoop(si, ir, robust_onboard_gains(ir, d))
    >>> r = shared_side_gains([x, y])
    >>> r[0].gains == r[1].gains, min(r[0].pm_deg, r[1].pm_deg) >= 15.0
    (True, True)
    """
    extra = max(float(onboard_extra_s), 0.0)
    cases = {i: _side_case(lp.side, lp.inner, lp.inner_rt, pm_min_deg, extra, lp.target_hz,
                           lp.d_hz) for i, lp in enumerate(loops)}
    out = {i: SideRetarget(loops[i].side.gains, 0.0, math.nan)
           for i, c in cases.items() if c is None}
    live = {i: c for i, c in cases.items() if c is not None}
    if not live:
        return out
    own = [c.result.gains for c in live.values()]
    small = PD(min(g.Kc / g.Kd for g in own) * min(g.Kd for g in own),
               min(g.Kd for g in own))
    best = small
    if len(own) == 2 and own[0] != own[1]:
        ref = {i: c.ise(c.result.gains) for i, c in live.items()}
        fast = max(own, key=lambda g: g.Kd)
        lo = np.log([[small.Kc, small.Kd], [fast.Kc, fast.Kd]])

        def ratios(g: PD) -> list[float]:
            return [c.ise(g) / ref[i] for i, c in live.items()]

        # from the smaller gains up to the faster design (on a log scale): the least move
        # that brings both loops' ISE within SHARED_ISE_SLACK of their own designs'. Every
        # step up takes margin from the slower loop, whose model alone then stands between
        # it and the truth
        blends = [PD(*map(float, np.exp((1 - a) * lo[0] + a * lo[1])))
                  for a in np.linspace(0.0, 1.0, 41)]
        ok = [g for g in blends if min(c.pm(g) for c in live.values()) >= pm_min_deg]
        near = [g for g in ok if max(ratios(g)) <= 1.0 + SHARED_ISE_SLACK]
        if near:
            best = near[0]
        elif ok:  # none that near: the blend nearest both designs (either way)
            best = min(ok, key=lambda g: max(abs(math.log(r)) for r in ratios(g)))
    for i, c in live.items():
        out[i] = SideRetarget(best, c.result.share, float(c.pm(best)))
    return out


def onboard_extra_delay_s(loop: Loop, position_hz: float = POSITION_LOOP_MIN_HZ) -> float:
    """Delay the autopilot's ``loop`` may have that the GCS-side loop had not, unseen (s).

    Altitude and x/y are flown onboard by the position loop at ``position_hz`` (Hz; read
    from the vehicle, :func:`vehicle_position_rate`; not finite or not positive:
    :data:`POSITION_LOOP_MIN_HZ`): its hold adds half a period. The relay tests commanded
    thrust and attitude directly. Roll and pitch: none (the rate loop runs at the rate the
    tests' torque commands were applied at).

    >>> onboard_extra_delay_s(Loop.ALTITUDE), onboard_extra_delay_s(Loop.ROLL)
    (0.01, 0.0)
    >>> onboard_extra_delay_s(Loop.X, 400.0)
    0.00125
    """
    if loop in (Loop.ROLL, Loop.PITCH):
        return 0.0
    hz = float(position_hz)
    return 0.5 / (hz if math.isfinite(hz) and hz > 0 else POSITION_LOOP_MIN_HZ)


# ----------------------------------------------------------------------- position loop rate
#: the parameters that set the position loop's rate, per firmware (docs/onboard-rates.md):
#: ArduCopter runs its position controller in the main loop (SCHED_LOOP_RATE, Hz); PX4's
#: mc_pos_control runs on each vehicle_local_position, which EKF2 publishes once per filter
#: update: every round(EKF2_PREDICT_US / IMU period) samples of vehicle_imu (IMU_INTEG_RATE)
POSITION_RATE_PARAMS: dict[str, tuple[str, ...]] = {
    "ardupilot": ("SCHED_LOOP_RATE",), "px4": ("EKF2_PREDICT_US", "IMU_INTEG_RATE")}
#: the rates a read value may give (Hz): ArduPilot clamps SCHED_LOOP_RATE to 50-2000 Hz,
#: PX4's IMU down-sampler EKF2_PREDICT_US to 1-100 ms; outside, the firmware is not one
#: whose rule is known here and the fallback is taken
_ARDUPILOT_HZ = (50.0, 2000.0)
_PX4_PREDICT_US = (1000.0, 100000.0)
_PX4_INTEG_HZ = (50.0, 4000.0)


@dataclass(frozen=True)
class PositionLoopRate:
    """The rate the autopilot runs the loop the written altitude and x/y gains go into.

    Attributes
    ----------
    hz : float
        The position loop's rate (Hz).
    source : str
        What it came from: the parameters read, or why the fallback was taken.
    read : bool
        True where ``hz`` came from the vehicle, False where it is the fallback
        :data:`POSITION_LOOP_MIN_HZ`.
    """

    hz: float = POSITION_LOOP_MIN_HZ
    source: str = f"not read: {POSITION_LOOP_MIN_HZ:g} Hz assumed"
    read: bool = False

    @property
    def hold_s(self) -> float:
        """Delay the loop's sample-and-hold adds, allowed for onboard (s)."""
        return 0.5 / self.hz

    def as_dict(self) -> dict[str, object]:
        return {"hz": self.hz, "hold_ms": self.hold_s * 1e3, "read": self.read,
                "source": self.source}


def _fallback(why: str) -> PositionLoopRate:
    return PositionLoopRate(POSITION_LOOP_MIN_HZ,
                            f"{why}: {POSITION_LOOP_MIN_HZ:g} Hz assumed", False)


def read_position_rate(values: Mapping[str, float], family: str = "") -> PositionLoopRate:
    """The position loop's rate from parameter ``values`` read from the vehicle.

    ``values`` holds what the vehicle answered (a name it lacks is absent). The names of
    ``family`` (``"ardupilot"``, ``"px4"``) are looked at first, then the other's (a
    vehicle may run another firmware than its profile says). Absent or implausible:
    :data:`POSITION_LOOP_MIN_HZ` with the reason.

    >>> read_position_rate({"SCHED_LOOP_RATE": 400.0}, "ardupilot").hz
    400.0
    >>> r = read_position_rate({"EKF2_PREDICT_US": 10000.0, "IMU_INTEG_RATE": 250.0}, "px4")
    >>> r.hz, r.read
    (83.33333333333333, True)
    >>> read_position_rate({"EKF2_PREDICT_US": 10000.0}, "px4").hz
    100.0
    >>> r = read_position_rate({"SCHED_LOOP_RATE": 0.0}, "ardupilot")
    >>> r.hz, r.read, r.source
    (50.0, False, 'SCHED_LOOP_RATE = 0 implausible (50-2000 Hz): 50 Hz assumed')
    >>> read_position_rate({}, "px4").source
    'neither SCHED_LOOP_RATE nor EKF2_PREDICT_US read: 50 Hz assumed'
    """
    order = ("px4", "ardupilot") if family == "px4" else ("ardupilot", "px4")
    for fam in order:
        name = POSITION_RATE_PARAMS[fam][0]
        if name in values:
            v = float(values[name])
            return _ardupilot_rate(v) if fam == "ardupilot" else _px4_rate(
                v, values.get(POSITION_RATE_PARAMS["px4"][1]))
    return _fallback("neither SCHED_LOOP_RATE nor EKF2_PREDICT_US read")


def _ardupilot_rate(v: float) -> PositionLoopRate:
    lo, hi = _ARDUPILOT_HZ
    if not (math.isfinite(v) and lo <= v <= hi):
        return _fallback(f"SCHED_LOOP_RATE = {v:g} implausible ({lo:g}-{hi:g} Hz)")
    return PositionLoopRate(v, f"SCHED_LOOP_RATE = {v:g} Hz read (ArduCopter's main loop)",
                            True)


def _px4_rate(predict_us: float, integ_hz: float | None) -> PositionLoopRate:
    lo, hi = _PX4_PREDICT_US
    if not (math.isfinite(predict_us) and lo <= predict_us <= hi):
        return _fallback(f"EKF2_PREDICT_US = {predict_us:g} implausible "
                         f"({lo:g}-{hi:g} us)")
    ilo, ihi = _PX4_INTEG_HZ
    if integ_hz is not None and math.isfinite(integ_hz) and ilo <= integ_hz <= ihi:
        # the filter runs every n IMU samples, n rounded half up as PX4's roundf
        n = max(1, math.floor(predict_us * 1e-6 * integ_hz + 0.5))
        return PositionLoopRate(float(integ_hz) / n, (
            f"EKF2_PREDICT_US = {predict_us:g} us, IMU_INTEG_RATE = {integ_hz:g} Hz read "
            f"(EKF2 every {n} IMU samples)"), True)
    return PositionLoopRate(1e6 / predict_us,
                            f"EKF2_PREDICT_US = {predict_us:g} us read (EKF2's filter update)",
                            True)


def vehicle_position_rate(read: Callable[[str], float | None], family: str = ""
                          ) -> PositionLoopRate:
    """The position loop's rate of a vehicle, asking it through ``read`` (a parameter's
    value, None where the vehicle has no such parameter): its family's names first, the
    other family's where the first is not answered (:func:`read_position_rate`).

    >>> vehicle_position_rate({"SCHED_LOOP_RATE": 500.0}.get, "px4").hz
    500.0
    >>> vehicle_position_rate({}.get, "ardupilot").read
    False
    """
    order = ("px4", "ardupilot") if family == "px4" else ("ardupilot", "px4")
    values: dict[str, float] = {}
    for fam in order:
        first, *rest = POSITION_RATE_PARAMS[fam]
        v = read(first)
        if v is None:
            continue
        values[first] = float(v)
        for name in rest:
            if (w := read(name)) is not None:
                values[name] = float(w)
        break
    return read_position_rate(values, family)


# ----------------------------------------------------------------------- ArduCopter's cascade
#: the rate loop's rate on ArduCopter (Hz, SCHED_LOOP_RATE default): its sample-and-hold is
#: half a period of delay in the written attitude loop
CASCADE_LOOP_HZ = 400.0


def _lag(s: np.ndarray, hz: float) -> np.ndarray | float:
    """``1 / (1 + s / (2 pi hz))``, or 1 for ``hz`` 0 (no filter)."""
    return 1.0 / (1.0 + s / (2 * np.pi * hz)) if hz > 0 else 1.0


def _lag2(s: np.ndarray, hz: float) -> np.ndarray | float:
    """Second-order Butterworth low-pass at ``hz`` (ArduPilot's ``LowPassFilter2p``, taken
    continuous: its bilinear design is prewarped to ``hz``), or 1 for ``hz`` 0 (no filter)."""
    if not hz > 0:
        return 1.0
    x = s / (2 * np.pi * hz)
    return 1.0 / (1.0 + math.sqrt(2.0) * x + x * x)


def cascade_controller(gains: PD, w: np.ndarray, target_hz: float = 0.0, error_hz: float = 0.0,
                       integrator_zero_rad_s: float = 0.0, d_over_p_s: float = 0.0,
                       d_hz: float = 0.0, gyro_hz: float = 0.0
                       ) -> tuple[np.ndarray, np.ndarray]:
    """``(Cr, Cy)`` of ArduCopter's attitude cascade on written ``gains``: ``u = Cr r - Cy y``
    on ``w`` (rad/s). The one model of that cascade, which every design and check of written
    roll/pitch/yaw gains goes through (:func:`cascade_gains`,
    :func:`mrft_gcs.flight.structure.structure_controller`).

    Angle P ``Kc/Kd`` makes a rate target, low-passed at ``target_hz`` (``ATC_RAT_*_FLTT``);
    the rate error (that target less the gyro) is low-passed at ``error_hz`` (``FLTE``) and
    goes through ``AC_PID``: P ``Kd``, I ``Kd w_i`` (``integrator_zero_rad_s``), D
    ``Kd d_over_p_s`` on the filtered error's derivative low-passed at ``d_hz`` (``FLTD``).
    The gyro the rate error is taken on is low-passed at ``gyro_hz`` (``INS_GYRO_FILTER``,
    second order, :func:`_lag2`); the angle error is on the AHRS attitude, not that filter:

    ``u = (1 + w_i / s + r s F_D) F_E (Kc F_T (x - y) - Kd s F_G y)``

    (0 for any filter: none). The square-root angle controller is taken linear.

    >>> Cr, Cy = cascade_controller(PD(2.0, 0.1), np.array([1.0]))
    >>> complex(Cr[0]), complex(Cy[0])
    ((2+0j), (2+0.1j))
    >>> Cr, Cy = cascade_controller(PD(2.0, 0.1), np.array([2.0]), integrator_zero_rad_s=1.0,
    ...                             d_over_p_s=0.5)
    >>> bool(np.isclose(Cr[0], 2 * (1 + 1 / 2j + 0.5 * 2j)))
    True
    """
    s = 1j * np.asarray(w, float)
    ft, fe = _lag(s, target_hz), _lag(s, error_hz)
    kernel = np.ones_like(s)
    if integrator_zero_rad_s > 0:
        kernel = kernel + integrator_zero_rad_s / s
    if d_over_p_s > 0:
        kernel = kernel + d_over_p_s * s * _lag(s, d_hz)
    Cr = kernel * fe * gains.Kc * ft
    return Cr, kernel * fe * (gains.Kc * ft + gains.Kd * s * _lag2(s, gyro_hz))


def cascade_process(model: InnerModel, w: np.ndarray) -> np.ndarray:
    """The process the written cascade closes, on ``w`` (rad/s): ``model`` with its
    identified delay (the ground station's part left in: the onboard loop has less) plus
    half a period of :data:`CASCADE_LOOP_HZ`. The model every check and design of written
    gains on ArduCopter's cascade on the rate path uses: re-targeted gains (hotter) took the
    loop near its margin there and lost the altitude relay (docs/ardupilot.md)."""
    return inner_response(model.K, model.T_prop, model.T1,
                          model.tau + 0.5 / CASCADE_LOOP_HZ, w)[0]


def cascade_delay_out_s(model: InnerModel, gcs: GcsDelay) -> float:
    """The ground station's delay to take out of ``model`` for the onboard cascade (s): the
    least plausible (``gcs.lo_s``, the most onboard delay, as :func:`robust_onboard_gains`
    checks its margin at), within the same cap (:data:`CAP_SHARE` of the identified delay,
    or the measured delay up to :data:`CERTAIN_CAP_SHARE` of it).

    >>> m = InnerModel(K=34.0, T_prop=0.0085, T1=0.095, tau=0.006)
    >>> cascade_delay_out_s(m, GcsDelay(0.011, 0.009, 0.015, 0.002, True))  # 95 % of tau
    0.0057
    >>> cascade_delay_out_s(m, GcsDelay(0.002, 0.0, 0.004, math.nan, False, "x"))
    0.0
    """
    certain = gcs.estimate_s if gcs.measured else gcs.lo_s
    cap = max(CAP_SHARE * model.tau, min(certain, CERTAIN_CAP_SHARE * model.tau))
    return round(max(min(gcs.lo_s, cap), 0.0), 9)


@dataclass(frozen=True)
class CascadeGains:
    """Roll or pitch gains for ArduCopter's attitude cascade, checked as it flies them.

    The cascade closes ``u = Kd (F_T(s) Kc/Kd (x - y) - s y)`` (angle P ``Kc/Kd`` into a rate
    target, low-passed by the rate loop's target filter ``F_T`` at ``target_filter_hz``,
    ``ATC_RAT_*_FLTT``; rate P ``Kd``), so its feedback is ``Kc F_T + Kd s``, not the
    ``Kc + Kd s`` the ground station flew, plus half a period of the loop's rate; rate I
    and D (:func:`cascade_controller`) where written. Angle P's
    square-root controller is linear within ``accel / P^2`` of error and softer beyond
    (a lower crossover): the linear loop is its worst case.

    Attributes
    ----------
    gains : PD
        The gains to write: the identified ones times ``scale`` (or, with rate D, the
        design of :func:`mrft_gcs.flight.structure.cascade_design`).
    scale : float
        1 where the identified gains keep ``pm_min_deg`` on the cascade; below, the largest
        factor on both that does.
    pm_deg : float
        Predicted phase margin of ``gains`` on the cascade (deg; -inf: unstable).
    pm_identified_deg : float
        ... of the identified gains (deg).
    target_filter_hz : float
        The rate-target filter modelled (Hz; 0: none).
    wc_rad_s : float
        Gain crossover of ``gains`` on the cascade (rad/s).
    """

    gains: PD
    scale: float
    pm_deg: float
    pm_identified_deg: float
    target_filter_hz: float
    wc_rad_s: float
    #: the rate loop's error filter modelled (Hz; 0: none): ArduCopter's yaw has one
    #: (``ATC_RAT_YAW_FLTE``, 2.5 Hz by default), on the rate P in the feedback path
    error_filter_hz: float = 0.0
    #: the zero of the rate loop's integrator (rad/s; 0: no rate I): the rate PID is
    #: ``Kd (1 + w_i / s)``, so rate I is ``Kd w_i`` (:attr:`rate_i`)
    integrator_zero_rad_s: float = 0.0
    #: a rate I was asked for but none keeps the margin (:func:`rate_loop_gains`)
    integrator_refused: bool = False
    #: rate D per unit of rate P (s; 0: D written 0), on the error's derivative low-passed
    #: at :attr:`d_hz` (``ATC_RAT_*_FLTD``; 0: none)
    d_over_p_s: float = 0.0
    d_hz: float = 0.0
    #: how rate D was decided (empty: it was not considered)
    d_note: str = ""
    #: the gyro low-pass on the rate feedback modelled (Hz; 0: none; ``INS_GYRO_FILTER``)
    gyro_hz: float = 0.0
    #: the ground station's delay taken out of the identified model (s; 0: all kept)
    delay_out_s: float = 0.0

    @property
    def rate_i(self) -> float:
        """Rate I to write (normalised output per rad of rate error; 0: none)."""
        return self.gains.Kd * self.integrator_zero_rad_s

    @property
    def rate_d(self) -> float:
        """Rate D to write (normalised output per rad/s^2 of rate error; 0: none)."""
        return round(self.gains.Kd * self.d_over_p_s, 9) if self.d_over_p_s > 0 else 0.0

    def note(self) -> str:
        f = (f"{self.target_filter_hz:g} Hz rate-target filter" if self.target_filter_hz > 0
             else "no rate-target filter")
        if self.error_filter_hz > 0:
            f += f", {self.error_filter_hz:g} Hz rate-error filter"
        if self.integrator_zero_rad_s > 0:
            f += (f", rate I {self.rate_i:.3g} (its zero at {self.integrator_zero_rad_s:.3g} "
                  f"rad/s, {self.wc_rad_s / self.integrator_zero_rad_s:.0f} x below the "
                  f"crossover)")
        elif self.integrator_refused:
            f += (f", no rate I (even with its zero {1 / RATE_I_LOWEST:.0f} x below the "
                  f"crossover it takes the margin under the floor)")
        if self.d_over_p_s > 0:
            f += (f", rate D {self.rate_d:.4g} ({self.d_over_p_s * 1e3:.1f} ms x rate P, "
                  f"through {self.d_hz:g} Hz)")
        if self.gyro_hz > 0:
            f += f", {self.gyro_hz:g} Hz gyro filter on the rate feedback"
        kept = ("the identified delay kept" if not self.delay_out_s > 0 else
                f"the identified delay less {self.delay_out_s * 1e3:.1f} ms of the ground "
                f"station's")
        out = (f"predicted PM {self.pm_deg:.0f} deg at {self.wc_rad_s:.0f} rad/s on ArduCopter's "
               f"cascade ({f}, {CASCADE_LOOP_HZ:g} Hz loop, {kept})")
        if self.scale < 1.0:
            out += (f"; the identified gains (PM {self.pm_identified_deg:.0f} deg there) scaled "
                    f"by {self.scale:.2f}")
        if self.d_note:
            out += f"; {self.d_note}"
        return out


def _cascade_pm(model: InnerModel, gains: PD, target_filter_hz: float,
                w: np.ndarray, error_filter_hz: float = 0.0,
                integrator_zero_rad_s: float = 0.0, d_over_p_s: float = 0.0,
                d_hz: float = 0.0, gyro_hz: float = 0.0) -> tuple[float, float]:
    wi = integrator_zero_rad_s
    Cy = cascade_controller(gains, w, target_filter_hz, error_filter_hz, wi, d_over_p_s,
                            d_hz, gyro_hz)[1]
    m = margins(Cy * cascade_process(model, w), w)
    # with a rate I the loop has two integrators: its phase starts at -180 deg, and below
    # it where the drag pole lies under the I's zero, which the Nyquist count of margins()
    # (written for one integrator) takes for an encirclement; the closed loop's poles decide
    stable = (_cascade_poles_stable(model, gains, target_filter_hz, error_filter_hz, wi,
                                    d_over_p_s, d_hz, gyro_hz=gyro_hz)
              if wi > 0 else m.stable)
    return (float(m.pm_deg) if stable else -math.inf), float(m.wc)


#: order of the Pade approximation of the loop's delay in :func:`_cascade_poles_stable`
_PADE_ORDER = 6


def _cascade_poles_stable(model: InnerModel, gains: PD, target_filter_hz: float,
                          error_filter_hz: float, integrator_zero_rad_s: float,
                          d_over_p_s: float = 0.0, d_hz: float = 0.0,
                          loop_delay_s: float = 0.5 / CASCADE_LOOP_HZ,
                          gyro_hz: float = 0.0) -> bool:
    """Whether the closed cascade of :func:`_cascade_pm` (with a rate I) has all its poles in
    the left half plane, the delay (``model.tau`` plus ``loop_delay_s``, s) as a Pade
    approximation of order :data:`_PADE_ORDER`."""
    n = _PADE_ORDER
    tau = model.tau + loop_delay_s
    c = [math.factorial(2 * n - k) * math.factorial(n)
         / (math.factorial(2 * n) * math.factorial(k) * math.factorial(n - k))
         for k in range(n + 1)]
    pade_num = np.array([c[k] * (-tau) ** k for k in range(n, -1, -1)])
    pade_den = np.array([c[k] * tau ** k for k in range(n, -1, -1)])

    def lag(hz: float) -> np.ndarray:  # 1 + s / (2 pi hz), or 1
        return np.array([1.0 / (2 * np.pi * hz), 1.0]) if hz > 0 else np.array([1.0])

    ft, fe, fd = lag(target_filter_hz), lag(error_filter_hz), lag(d_hz)
    wi, r = integrator_zero_rad_s, d_over_p_s
    # the PID's kernel 1 + w_i/s + r s / fd: (s fd + w_i fd + r s^2) / (s fd), the s
    # left out of both without an I (a common root at 0 is no pole of the loop)
    if wi > 0:
        k_num = np.polyadd(np.polymul([1.0, wi], fd), [r, 0.0, 0.0] if r > 0 else [0.0])
        k_den = np.polymul([1.0, 0.0], fd)
    else:
        k_num, k_den = np.polyadd(fd, [r, 0.0] if r > 0 else [0.0]), fd
    # the gyro filter's denominator (s / wg)^2 + sqrt2 s / wg + 1, or 1
    wg = 2 * np.pi * gyro_hz
    fg = (np.array([1.0 / wg ** 2, math.sqrt(2.0) / wg, 1.0]) if gyro_hz > 0
          else np.array([1.0]))
    # kernel (Kc / ft + Kd s / fg) / fe * K pade / (s (Tp s + 1) (T1 s + 1))
    ctrl = np.polyadd(gains.Kc * fg, np.polymul([gains.Kd, 0.0], ft))
    num = model.K * np.polymul(np.polymul(k_num, ctrl), pade_num)
    den = np.polymul(np.polymul(np.polymul(k_den, ft), fe), fg)
    den = np.polymul(den, np.polymul([1.0, 0.0], np.polymul([model.T_prop, 1.0],
                                                            [model.T1, 1.0])))
    den = np.polymul(den, pade_den)
    return bool(np.all(np.roots(np.polyadd(den, num)).real < 0))


def cascade_gains(model: InnerModel, gains: PD, target_filter_hz: float,
                  pm_min_deg: float = PM_ROBUST_DEG,
                  error_filter_hz: float = 0.0,
                  integrator_zero_rad_s: float = 0.0, d_over_p_s: float = 0.0,
                  d_hz: float = 0.0, gyro_hz: float = 0.0) -> CascadeGains:
    """The identified roll/pitch (or yaw) ``gains`` checked on ArduCopter's cascade (see
    :class:`CascadeGains`), on ``model`` with its identified delay (the ground station's
    delay left in: the onboard loop has less) plus half a loop period; scaled down together
    until they keep ``pm_min_deg`` where they do not. ``error_filter_hz``: the rate loop's
    error filter (Hz; 0: none). ``integrator_zero_rad_s``: a rate I with its zero there
    (rad/s; 0: none), kept at that frequency while the gains are scaled. ``d_over_p_s``: a
    rate D of that share of rate P, through ``d_hz`` (:func:`cascade_controller`).
    ``gyro_hz``: the gyro low-pass on the rate feedback (Hz; 0: none).

    Examples
    --------
    >>> m = InnerModel(K=34.0, T_prop=0.0085, T1=0.095, tau=0.006)
    >>> c = cascade_gains(m, PD(6.4, 0.21), 20.0)
    >>> c.scale, c.pm_deg > 20.0
    (1.0, True)
    >>> c = cascade_gains(m, PD(6.4, 0.21), 20.0, pm_min_deg=40.0)
    >>> c.scale < 1.0, round(c.pm_deg)
    (True, 40)
    """
    wi = max(float(integrator_zero_rad_s), 0.0)
    w = frequency_grid(model.T_prop, model.T1, model.tau,
                       extra_T=(1.0 / wi,) if wi > 0 else ())
    fe, dd = error_filter_hz, (max(float(d_over_p_s), 0.0), d_hz, gyro_hz)
    pm0, wc0 = _cascade_pm(model, gains, target_filter_hz, w, fe, wi, *dd)
    if pm0 >= pm_min_deg:
        return CascadeGains(gains, 1.0, pm0, pm0, target_filter_hz, wc0, fe, wi,
                            d_over_p_s=dd[0], d_hz=d_hz, gyro_hz=gyro_hz)
    lo, hi = 0.0, 1.0  # the largest factor that keeps the margin, to 0.1 %
    while hi - lo > 1e-3:
        mid = 0.5 * (lo + hi)
        pm_mid, _ = _cascade_pm(model, PD(gains.Kc * mid, gains.Kd * mid), target_filter_hz, w,
                                fe, wi, *dd)
        if pm_mid >= pm_min_deg:
            lo = mid
        else:
            hi = mid
    scaled = PD(gains.Kc * lo, gains.Kd * lo)
    pm, wc = _cascade_pm(model, scaled, target_filter_hz, w, fe, wi, *dd)
    return CascadeGains(scaled, round(lo, 3), pm, pm0, target_filter_hz, wc, fe, wi,
                        d_over_p_s=dd[0], d_hz=d_hz, gyro_hz=gyro_hz)


#: the lowest rate-I zero :func:`rate_loop_gains` moves to, as a share of the crossover
RATE_I_LOWEST = 0.01


def rate_loop_gains(model: InnerModel, gains: PD, target_filter_hz: float,
                    error_filter_hz: float = 0.0, pm_min_deg: float = PM_ROBUST_DEG,
                    decade: float = 0.0, d_over_p_s: float = 0.0,
                    d_hz: float = 0.0, gyro_hz: float = 0.0) -> CascadeGains:
    """Roll/pitch gains for ArduCopter's cascade with a rate I (``decade`` > 0).

    The P gains are those of :func:`cascade_gains` (the identified ones, scaled down where
    they fall short of ``pm_min_deg`` without an I). The I's zero sits ``decade`` times below
    their crossover on the cascade, or lower, down to :data:`RATE_I_LOWEST` of it, as far
    as keeping ``pm_min_deg`` with the I needs; where even that lowest zero does not keep
    it, no I (the P gains are never lowered for the I: a lower crossover with the same zero
    costs more phase, not less). ``decade`` 0: no rate I. ``d_over_p_s``, ``d_hz``: a rate
    D in the loop (:func:`cascade_gains`).

    >>> m = InnerModel(K=34.0, T_prop=0.0085, T1=0.095, tau=0.006)
    >>> c = rate_loop_gains(m, PD(6.4, 0.21), 20.0, decade=10.0)
    >>> c.gains == PD(6.4, 0.21), c.rate_i > 0, c.pm_deg >= 15.0
    (True, True, True)
    >>> round(c.wc_rad_s / c.integrator_zero_rad_s)
    10
    """
    c0 = cascade_gains(model, gains, target_filter_hz, pm_min_deg, error_filter_hz,
                       d_over_p_s=d_over_p_s, d_hz=d_hz, gyro_hz=gyro_hz)
    dd = (c0.d_over_p_s, c0.d_hz, gyro_hz)
    if not (decade > 0 and c0.scale > 0 and math.isfinite(c0.wc_rad_s)):
        return c0
    fe, g = error_filter_hz, c0.gains
    lowest = RATE_I_LOWEST * c0.wc_rad_s
    w = frequency_grid(model.T_prop, model.T1, model.tau, extra_T=(10.0 / lowest,))

    def pm(wi: float) -> float:
        return _cascade_pm(model, g, target_filter_hz, w, fe, wi, *dd)[0]

    wi = c0.wc_rad_s / decade
    if not pm(wi) >= pm_min_deg:
        if not pm(lowest) >= pm_min_deg:
            return dataclasses.replace(c0, integrator_refused=True)
        lo, hi = math.log(lowest), math.log(wi)  # the highest zero that keeps it, to 1 %
        while hi - lo > 0.01:
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if pm(math.exp(mid)) >= pm_min_deg else (lo, mid)
        wi = math.exp(lo)
    p, wc = _cascade_pm(model, g, target_filter_hz, w, fe, wi, *dd)
    return dataclasses.replace(c0, pm_deg=p, wc_rad_s=wc, integrator_zero_rad_s=wi)
