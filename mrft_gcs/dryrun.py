"""Dry-run: the identification of a live tune, on logged telemetry; touches nothing.

A session .tlog of this tool's own tune is first replayed through the tune's own sequence
(:func:`_replay_session`: :class:`~mrft_gcs.flight.source.ReplayVehicle` and
:class:`~mrft_gcs.flight.driver.SequenceDriver` with the bundled identification), so its
loops are identified by the code that identified them live; a log is taken for such a
session only where the replayed sequence reproduces its logged commands. Every other log,
and every loop the replay did not identify, goes through the relay-segment search below.

:func:`dry_run` reads a log (:func:`mrft_gcs.logs.decode_log`), finds the relay
tests in it (:func:`find_relay_segments`), and for each loop runs the pipeline of a
live tune (:func:`analyse_segment`): the live tune's own cycle watcher
(:class:`mrft_gcs.flight.cycles.CycleWatcher`) fed sample by sample, the classifier with
exact gain scaling (:func:`mrft_gcs.identify.identify`) on the cycles a tune identifies,
then residual analysis (:func:`mrft_gcs.residual.analyse_residual`). It returns a
:class:`DryRunResult` holding the identified models, residuals, the gains a tune
would write (inner loops re-targeted to the onboard loop as a tune writes them,
:func:`mrft_gcs.flight.onboard.onboard_gains`) and their parameter values; it never
opens a link.

Where relay tests come from
---------------------------
- **Explicit loop tables** (the documented CSV): ``u`` is the relay output.
- **Recorded setpoints**: torque commands (SET_ACTUATOR_CONTROL_TARGET roll and
  pitch, collective thrust for altitude) or attitude set points (x: -pitch,
  y: +roll, from SET_ATTITUDE_TARGET) that alternate between two levels.
- **Tilt set points behind the GCS attitude PDs** (x, y on the torque path): a
  live tune runs the x/y relays through its own attitude PDs, so only torques go
  on the wire. Once pitch (x) or roll (y) is identified, the PD
  ``torque = trim + Kc (ref - angle) - Kd rate`` is fitted to the torques and
  inverted (:func:`_side_segment`).
- **Relay signature in telemetry alone**: a sustained oscillation of an angle
  whose rate has a square-wave derivative (the relay's torque). The relay levels
  are not in the log, so ``h`` must then be given (CSV metadata or ``h=``).

Which sample a command answered
-------------------------------
A ground station's command answers the telemetry it had when it computed it, and
the live detector sees only those samples. A .tlog logs both directions in the
order the ground station saw them (:attr:`mrft_gcs.logs.DecodedLog.file_order`);
a sample that arrived while a command was being computed is logged before it, so
the order alone is off by a sample now and then. mrft-tune's own commands carry
fingerprints of the sample they answered: the yaw hold's torque on every command
(attitude, :func:`_answer_order`) and, once altitude runs on its PD, the thrust
(position, :func:`_answer_position`). Each sample is paired with the first command
that answered it; samples no command answered are dropped, as the live relay never
saw them. Without order (other formats), each sample takes the first command at or
after its time. Position loops whose relay ran on a ground station are measured as
the live tune measures them, through its complementary filter of position and
velocity (:class:`mrft_gcs.flight.noise.ComplementaryFilter`).

A relay stretch is a run of at least ``MIN_SWITCHES`` level changes, each level
held for two samples or more, alternating between two values; the last one in
the log is used (a tune ends each relay test by switching to the identified PD).
``h`` is half the level difference, the bias the mid level; ``beta`` and the set point
come from where the switches happen relative to the extremes (``e_switch = -beta e_max``,
per pair of half cycles, :func:`infer_relay`) and ``beta`` is snapped to the
classifier's beta when within 0.1, unless metadata gives it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from mrft_gcs.errors import IdentificationError, MrftError
from mrft_gcs.flight.cycles import CycleRules, CycleWatcher
from mrft_gcs.flight.onboard import (
    PositionLoopRate,
    Retarget,
    onboard_extra_delay_s,
    pooled_attitude,
    pooled_note,
    robust_onboard_gains,
    vehicle_position_rate,
)
from mrft_gcs.flight.structure import (
    OnboardStructure,
    rate_d_values,
    structured_retarget,
    vehicle_structure,
)
from mrft_gcs.identify import Identification, identify
from mrft_gcs.logs import decode_log, log_truncation, read_csv_metadata, summarize_log
from mrft_gcs.logs.describe import LogSummary
from mrft_gcs.logs.replay import DecodedLog, to_telemetry_log
from mrft_gcs.loops import SIDE_INNER, Loop, LoopKind
from mrft_gcs.plant import PD, InnerModel, SideModel
from mrft_gcs.residual import RelayTest, ResidualReport, analyse_residual
from mrft_gcs.residual.cycles import noise_std
from mrft_gcs.telemetry import ParamValue, TelemetryLog

if TYPE_CHECKING:
    from mrft_gcs.flight.onboard import GcsDelay
    from mrft_gcs.link.clock import ClockFit

__all__ = ["RelaySegment", "LoopResult", "DryRunResult", "find_relay_segments", "infer_beta",
           "infer_relay", "RelayInference", "analyse_segment", "dry_run", "MIN_SWITCHES"]

#: Level changes a relay stretch needs (three full cycles).
MIN_SWITCHES = 6
#: how many samples a ground-station command may lag the newest one logged before it (a
#: stalled ground station: 64 samples are 0.26 s at 250 Hz)
_BACK = 64
#: relay levels recovered through a PD hold to this fraction of the span (the PD gains are
#: known to ~1e-4; a side output taken as 0 while it was the bounding relay's 0.05 rad
#: would be 2e-3 off)
_LEVEL_TOL = 5e-3


@dataclass(frozen=True)
class RelaySegment:
    """One relay test found in a log.

    Attributes
    ----------
    loop : Loop
    t, u, y : arrays (m,)
        Time (s), relay output in the loop's input units (with bias), measured output.
    beta, h, bias : float
        The relay (``beta`` may be inferred, see ``beta_from``).
    source : str
        Where ``u`` came from (``"csv"``, ``"actuator"``, ``"attitude target"``,
        ``"attitude PD"``, ``"telemetry"``).
    beta_from : str
        ``"metadata"``, ``"switches"``, ``"domain"`` (inferred, within 0.1 of the beta a
        tune uses on that loop, and snapped to it) or ``"session"`` (the relay of the
        tune's own sequence, replayed over its session log: :func:`_replay_session`).
    gcs_period_s : float
        Period of the ground station's setpoint stream when the relay ran on a ground
        station (its commands are in the log), else 0.
    age_s : array (m,) or None
        With ``gcs_period_s``: how old each sample was when the command answering it was
        logged (s; command minus sample time on the log's vehicle clock, placed through
        the lower envelope of receive-minus-vehicle time tracked over the log, ``clock``).
        A live tune re-targets the written inner-loop gains by their mean over the
        identified cycles (:func:`mrft_gcs.flight.onboard.measure_gcs_delay`), as dry-run
        does here. Where
        the log cannot tell which sample a command answered (altitude, see
        :func:`_answer_position`), file order pairs it with the last one logged before
        it, which it may not have seen yet: the ages are then up to a period short.
    tilt : array (m,) or None
        x/y relays: the measured tilt along the axis at the times ``t`` (from ATTITUDE),
        which the side identification fits behind, as the live tune does.
    clock : ClockFit or None
        With ``age_s``: the log's clock fit (``DecodedLog.clock``), whose slips and skew
        decide whether the ages are plausible.
    setpoint, crossed : float
        The relay's set point inferred from the switches (units of ``y``) and the fraction
        of half cycles whose extreme lay beyond it (:class:`RelayInference`; NaN: not
        inferred).
    """

    loop: Loop
    t: np.ndarray
    u: np.ndarray
    y: np.ndarray
    beta: float
    h: float
    bias: float
    source: str
    beta_from: str
    gcs_period_s: float = 0.0
    tilt: np.ndarray | None = None
    age_s: np.ndarray | None = None
    clock: ClockFit | None = None
    setpoint: float = math.nan
    crossed: float = math.nan

    @property
    def duration_s(self) -> float:
        return float(self.t[-1] - self.t[0])


@dataclass(frozen=True)
class LoopResult:
    """What dry-run found for one loop: identification and residual, or why not.

    ``cycles`` are the ``(t, u, y)`` the identification used (the first steady
    cycles, as a live tune hands them over); ``gains`` the gains a tune would write:
    the identified ones, re-targeted to the onboard loop for inner loops whose relay
    ran on a ground station.
    """

    loop: Loop
    segment: RelaySegment
    steady: bool
    identification: Identification | None = None
    residual: ResidualReport | None = None
    notes: tuple[str, ...] = ()
    cycles: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    gains: PD | None = None
    #: the GCS delay re-targeted out of ``gains`` (s; NaN: not re-targeted)
    gcs_delay_s: float = math.nan
    #: rate D written as this share of rate P (s; 0: none; ArduPilot's structure)
    rate_d_over_p_s: float = 0.0

    def as_dict(self) -> dict:
        """The loop's entry of the tuning report (README's schema), as dry-run knows it."""
        ident = self.identification
        seg = self.segment
        out: dict = {"beta": seg.beta, "h": seg.h, "bias": seg.bias, "source": seg.source,
                     "steady": self.steady, "notes": list(self.notes)}
        if math.isfinite(seg.setpoint):
            out["setpoint"] = seg.setpoint
        if ident is not None:
            g = self.gains or ident.gains
            out.update(model=ident.model.as_dict(), **{"class": ident.class_index},
                       confidence=ident.confidence, period_s=ident.period_s,
                       amplitude=ident.amplitude, gains={"Kc": g.Kc, "Kd": g.Kd},
                       gains_identified={"Kc": ident.gains.Kc, "Kd": ident.gains.Kd})
        out["residual"] = self.residual.as_dict() if self.residual else None
        return out


@dataclass(frozen=True)
class DryRunResult:
    """Everything dry-run found in one log.

    Attributes
    ----------
    source : str
        The log file.
    summary : LogSummary
        Which signals the log holds.
    loops : tuple of LoopResult
        One per relay test found.
    searched : dict
        Per loop, what was looked at and why no relay test was found there.
    parameters : dict
        Parameter values a tune would write (empty without identified gains or profile).
    warnings : tuple of str
        One line per problem with the file that did not stop the analysis (a log cut
        short: :func:`mrft_gcs.logs.log_truncation`).
    """

    source: str
    summary: LogSummary
    loops: tuple[LoopResult, ...]
    searched: dict[str, str] = field(default_factory=dict)
    parameters: dict[str, float] = field(default_factory=dict)
    warnings: tuple[str, ...] = ()

    @property
    def found(self) -> bool:
        return bool(self.loops)

    def explanation(self) -> str:
        """Plain words: which loops, which signals, why nothing was identified."""
        lines = [f"{self.source}: no relay test found." if not self.loops else
                 f"{self.source}: relay tests on {', '.join(r.loop.value for r in self.loops)}."]
        found = self.summary.found()
        lines.append("signals in the log: " + (", ".join(found) if found else "none"))
        for loop, why in self.searched.items():
            lines.append(f"  {loop}: {why}")
        for r in self.loops:
            for n in r.notes:
                lines.append(f"  {r.loop.value}: {n}")
        if not self.loops:
            lines.append("dry-run identifies loops from relay tests (MRFT): record a tune "
                         "with 'mrft-tune tune' (it writes a .tlog) or give a CSV with "
                         "t,loop,u,y rows of a relay test.")
        return "\n".join(lines)


# ------------------------------------------------------------------ relay stretches
def _runs(u: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Piecewise-constant runs of ``u``: (start index, length, value)."""
    change = np.flatnonzero(np.abs(np.diff(u)) > tol) + 1
    starts = np.concatenate([[0], change])
    lengths = np.diff(np.concatenate([starts, [u.size]]))
    return starts, lengths, u[starts]


def _relay_stretch(u: np.ndarray, regular: bool = False,
                   level_tol: float = 1e-6) -> tuple[int, int, str]:
    """Last stretch of ``u`` alternating between two levels: (start, stop, why-not).

    ``regular``: each level must also be held about as long as the last time (within
    35 %), as in a steady relay oscillation (used for signs reconstructed from telemetry).
    A single sample of the other level just before the stretch belongs to it (a relay
    may switch back at once on its first sample). A level holds while ``u`` stays within
    ``level_tol`` of the signal's span.
    """
    if u.size < 2 * MIN_SWITCHES:
        return 0, 0, f"only {u.size} samples"
    span = float(np.ptp(u))
    if span <= 0:
        return 0, 0, "the command is constant"
    starts, lengths, vals = _runs(u, level_tol * max(span, 1e-9) + 1e-7)
    longest = 0
    last: tuple[int, int, float] | None = None
    i = 0
    m = 4 if regular else 2  # samples a level must be held
    while i < vals.size - 1:
        j = i
        a, b = vals[i], vals[i + 1]
        # a switch of at least 5 % of the signal's span (a relay can be small next to the
        # largest command of a flight); its levels repeat within 2 % of the switch
        tol = 0.02 * abs(a - b)
        if abs(a - b) > 0.05 * span and lengths[i] >= m:
            j = i + 1
            while (j + 1 < vals.size and lengths[j] >= m
                   and abs(vals[j + 1] - vals[j - 1]) <= tol
                   and (not regular or j < i + 2
                        or abs(lengths[j] - lengths[j - 2]) <= 0.35 * lengths[j - 2])):
                j += 1
            # A short last level stays when the relay ends with it (the tune switched to
            # the PD right after); a short level between two relay levels ends the stretch.
            ends = j + 1 == vals.size or abs(vals[j + 1] - vals[j - 1]) > tol
            if lengths[j] < m and (regular or not ends):
                j -= 1
            longest = max(longest, j - i)
            if j - i >= MIN_SWITCHES:
                last = (i, j, tol)
        i = max(j, i + 1)
    if last is None:
        distinct = np.unique(np.round(vals / max(0.02 * span, 1e-12))).size
        return 0, 0, (f"the command is not a two-level relay signal (longest two-level stretch "
                      f"has {longest} switches, need {MIN_SWITCHES}; {distinct} distinct levels)")
    i0, i1, tol = last
    if not regular and i0 > 0 and abs(vals[i0 - 1] - vals[i0 + 1]) <= tol:
        i0 -= 1
    return int(starts[i0]), int(starts[i1] + lengths[i1]), ""


@dataclass(frozen=True)
class RelayInference:
    """The relay's ``beta`` and set point, inferred from where it switched.

    Attributes
    ----------
    beta : float
        Median over pairs of consecutive half cycles (clipped to [-0.95, 0.95]).
    setpoint : float
        The relay's set point (units of ``y``).
    spread : float
        Median absolute deviation of the per-pair ``beta`` (0: every cycle agrees).
    pairs : int
        Pairs of half cycles used.
    crossed : float
        Fraction of half cycles whose extreme lies beyond the set point (1 for a relay
        oscillating about it; a cycle that has drifted off it is no MRFT test).
    """

    beta: float
    setpoint: float
    spread: float
    pairs: int
    crossed: float


def _local_fit(y: np.ndarray, lo: int, hi: int, at: float | None = None,
               low: bool = True) -> float:
    """A quadratic fitted to ``y[lo:hi]`` (noise-averaged): its value at index ``at``, or
    its extreme (``low``: the minimum) when ``at`` is None, kept within the window."""
    k = np.arange(max(lo, 0), min(hi, y.size))
    if k.size < 4:
        if at is not None:
            return float(np.interp(at, k, y[k]))
        return float(y[k].min() if low else y[k].max())
    c = np.polyfit(k - k.mean(), y[k], 2)
    if at is not None:
        return float(np.polyval(c, at - k.mean()))
    x = k - k.mean()
    if c[0] != 0 and ((low and c[0] > 0) or (not low and c[0] < 0)):
        v = -c[1] / (2 * c[0])
        if x[0] <= v <= x[-1]:
            return float(np.polyval(c, v))
    vals = np.polyval(c, x)
    return float(vals.min() if low else vals.max())


def infer_relay(u: np.ndarray, y: np.ndarray) -> RelayInference:
    """MRFT ``beta`` and set point from where the relay switched relative to the extremes.

    With ``e = r - y`` (``r``: the relay's set point), the relay leaves the high level
    when ``e <= -beta e_max`` (``e_max = r - y_min``, the largest error in that half
    cycle), and the low level when ``e >= -beta e_min`` (``e_min = r - y_max``). Both
    are one line: ``y_switch = (1 + beta) r - beta y_extreme``. Over two consecutive half
    cycles (one per level) the set point cancels, so each pair gives ``beta`` on its
    own, whatever the bias of the relay or of the plant moves the cycle off ``r``;
    ``beta`` is the median over pairs, ``r`` the median intercept. Extremes and switch
    levels are taken from quadratics fitted to the samples around them (a noisy maximum
    lies beyond the true one by about two noise deviations).

    Raises
    ------
    IdentificationError
        Fewer than three switches.
    """
    mid = 0.5 * (u.min() + u.max())
    high = u > mid
    sw = np.flatnonzero(high[1:] != high[:-1]) + 1
    ext, lvl, state = [], [], []
    for a, b in zip(sw[:-1], sw[1:], strict=False):
        if b >= y.size:
            continue
        w = int(np.clip((b - a) // 6, 2, 8))
        seg = y[a:b]
        i = a + int(np.argmin(seg) if high[a] else np.argmax(seg))
        ext.append(_local_fit(y, max(a, i - w), min(b, i + w + 1), low=bool(high[a])))
        # the threshold was crossed between the last two samples before the switch
        lvl.append(_local_fit(y, b - w, b + w, at=b - 0.5))
        state.append(bool(high[a]))
    if len(ext) < 2:
        raise IdentificationError("cannot infer the relay's beta: too few switches; give "
                                  "beta in the CSV metadata ('# beta=... h=...')")
    x, z, s = np.asarray(ext), np.asarray(lvl), np.asarray(state)
    pair = s[:-1] != s[1:]
    dx = x[:-1] - x[1:]
    pair &= np.abs(dx) > 0
    if not pair.any():
        raise IdentificationError("cannot infer the relay's beta: the half cycles do not "
                                  "alternate; give beta in the CSV metadata ('# beta=...')")
    b_k = -(z[:-1] - z[1:])[pair] / dx[pair]
    beta = float(np.clip(np.median(b_k), -0.95, 0.95))
    r = float(np.median(z + beta * x)) / (1.0 + beta)
    crossed = float(np.mean(np.where(s, x < r, x > r)))
    return RelayInference(beta, r, float(np.median(np.abs(b_k - np.median(b_k)))),
                          int(pair.sum()), crossed)


def infer_beta(u: np.ndarray, y: np.ndarray) -> float:
    """MRFT ``beta`` from where the relay switched (:func:`infer_relay`)."""
    return infer_relay(u, y).beta


# ------------------------------------------------------------------ commands and samples
@dataclass(frozen=True)
class _Commands:
    """Commands of one log table paired with the samples of a telemetry table.

    ``rows``: the telemetry rows used (time order); ``cmd``: for each, the index of the
    command that answered it; ``gcs_period_s``: the setpoint period when the commands
    are a ground station's (logged in order with the telemetry), else 0.
    """

    rows: np.ndarray
    cmd: np.ndarray
    gcs_period_s: float


def _pair(tab: np.ndarray, tab_order: np.ndarray | None, cmd_t: np.ndarray,
          cmd_order: np.ndarray | None) -> _Commands:
    """Which command answered which sample (see the module notes)."""
    if tab_order is None or cmd_order is None:
        # The command sent after measurement k is paired with sample k.
        idx = np.clip(np.searchsorted(cmd_t, tab[:, 0], side="left"), 0, cmd_t.size - 1)
        return _Commands(np.arange(len(tab)), idx, 0.0)
    by_file = np.argsort(tab_order, kind="stable")
    cmd_sorted = np.argsort(cmd_order, kind="stable")
    k = np.searchsorted(tab_order[by_file], cmd_order[cmd_sorted], side="right") - 1
    ok = k >= 0
    seen, first = np.unique(k[ok], return_index=True)
    rows = by_file[seen]
    cmd = cmd_sorted[ok][first]
    keep = np.argsort(rows, kind="stable")
    return _Commands(rows[keep], cmd[keep], _setpoint_period(cmd_t))


def _answer_order(log: TelemetryLog, order: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """File order with each torque command moved to just after the sample it answered.

    A ground station logs a command when it sends it; a sample that reached it while
    the command was being computed is logged before the command it did not take part
    in (on a loaded machine several samples can). mrft-tune's torque path holds yaw
    with a fixed PD (:class:`mrft_gcs.flight.controllers.YawHold`) on every command,
    ``yaw torque = Kc wrap(yaw_ref - yaw) - Kd r``, so the yaw torque tells which of the
    last few attitude samples a command answered: the one that gives the constant
    ``yaw_ref`` back (to float32 rounding). Commands where it tells nothing (on the
    ground, yaw torque at its limit, another ground station) keep their file order.
    Orders are doubled so that a moved command fits between two samples. Position
    samples are paired by ``"actuator/position"`` when :func:`_answer_position` could
    tell, else by ``"actuator"``. ``"yaw_ref"`` holds the yaw hold's heading.
    """
    a_ord, c_ord = order.get("attitude"), order.get("actuator")
    out = {k: 2 * np.asarray(v, dtype=np.int64) for k, v in order.items()}
    act, att = log.actuator, log.attitude
    if a_ord is None or c_ord is None or len(att) < 2 or not len(act):
        return out
    from mrft_gcs.flight.controllers import YawHold

    hold = YawHold()
    by_file = np.argsort(a_ord, kind="stable")
    att_f, a_sorted = att[by_file], a_ord[by_file]
    latest = np.searchsorted(a_sorted, c_ord, side="right") - 1
    tau = act[:, 3]
    free = (latest >= 0) & (tau != 0) & (np.abs(tau) < 0.999 * hold.hi)
    if free.sum() < 10:
        return out

    def ref(back: int) -> np.ndarray:
        i = np.clip(latest - back, 0, None)
        return att_f[i, 3] + (tau + hold.Kd * att_f[i, 6]) / hold.Kc

    def off(e: np.ndarray, centre: float) -> np.ndarray:
        return np.abs((e - centre + np.pi) % (2 * np.pi) - np.pi)

    def told(centre: float) -> float:
        """Share of the commands that give ``centre`` back from one of the last samples."""
        hit = np.zeros(int(free.sum()), dtype=bool)
        for b in range(_BACK):
            hit |= off(ref(b)[free], centre) < 2e-6
            if hit.all():
                break
        return float(hit.mean())

    # the heading: the median of the commands' answers from the latest logged sample, or
    # from the one before. Which of the two most commands answered depends on the phase
    # between the telemetry and the stream, fixed per session by chance (either can take
    # most, or they split about evenly); a median is exact where the share is near half
    # or more.
    share, centre = max((told(c), c) for c in (float(np.median(ref(b)[free]))
                                               for b in range(3)))
    if share < 0.5:
        return out  # not mrft-tune's yaw hold
    est = ref(0)
    out["yaw_ref"] = np.array([centre])  # the heading the yaw hold keeps (take-off heading)
    back = np.zeros(latest.size, dtype=np.int64)
    undecided = free & (off(est, centre) >= 2e-6)
    for b in range(1, _BACK):
        if not undecided.any():
            break
        hit = undecided & (latest - b >= 0) & (off(ref(b), centre) < 2e-6)
        back[hit] = b
        undecided &= ~hit
    moved = back > 0
    nxt = latest[moved] - back[moved] + 1  # the first sample the command did not see
    out["actuator"] = out["actuator"].copy()
    out["actuator"][moved] = 2 * a_sorted[nxt] - 1
    return out


def _robust_lstsq(A: np.ndarray, b: np.ndarray, rounds: int = 4) -> np.ndarray:
    """Least squares that drops, round by round, rows off by more than 5 x the median."""
    fit = np.ones(b.size, dtype=bool)
    coef = np.zeros(A.shape[1])
    for _ in range(rounds):
        coef = np.linalg.lstsq(A[fit], b[fit], rcond=None)[0]
        res = np.abs(A @ coef - b)
        fit = res <= 5 * float(np.median(res)) + 1e-12
    return coef


def _answer_position(log: TelemetryLog, order: dict[str, np.ndarray], after_s: float
                     ) -> dict[str, np.ndarray]:
    """Which position sample each command answered, once the altitude PD runs on the GCS.

    After its relay, altitude is held by a PD on the ground station:
    ``thrust = trim + Kc (z_ref - z) - Kd vz`` (up positive), linear in the position
    sample's ``z`` and ``vz``: ``thrust = c + Kc z + Kd vz`` in NED, fitted robustly to the
    commands after ``after_s``, each with the one of its last 8 position samples that fits
    best (starting from the newest; the identified gains are not needed). The thrust then
    tells which of the last position samples a command answered. Returns ``order`` with
    ``"actuator/position"``: those commands right after their sample, the others as in
    ``"actuator"``.
    """
    p_ord, c_ord = order.get("position"), order.get("actuator")
    act, pos = log.actuator, log.position
    if p_ord is None or c_ord is None or len(pos) < 2:
        return order
    by_file = np.argsort(p_ord, kind="stable")
    pos_f, p_sorted = pos[by_file], p_ord[by_file]
    latest = np.searchsorted(p_sorted, c_ord, side="right") - 1
    thrust = act[:, 4]
    use = np.flatnonzero((act[:, 0] > after_s) & (latest >= 0) & (thrust > 0) & (thrust < 1))
    if use.size < 20:
        return order
    def rows_back(b: np.ndarray | int) -> np.ndarray:
        i = np.clip(latest[use] - b, 0, None)
        return np.column_stack([np.ones(use.size), pos_f[i][:, [3, 6]]])

    coef = _robust_lstsq(rows_back(0), thrust[use])
    # many commands may answer an older sample: re-pick each one's best sample and refit
    cands = [rows_back(b) for b in range(8)]
    for _ in range(4):
        err = np.stack([np.abs(A @ coef - thrust[use]) for A in cands])
        pick = np.argmin(err, axis=0)
        coef = _robust_lstsq(np.stack(cands)[pick, np.arange(use.size)], thrust[use])
    c, Kc, Kd = coef
    res = np.min(np.stack([np.abs(A @ coef - thrust[use]) for A in cands]), axis=0)
    tol = 10 * float(np.median(res)) + 1e-6
    back = np.full(use.size, -1)
    for b in range(_BACK):
        if (back >= 0).all():
            break
        i = np.clip(latest[use] - b, 0, None)
        hit = (back < 0) & (latest[use] - b >= 0) & \
            (np.abs(c + pos_f[i][:, [3, 6]] @ np.array([Kc, Kd]) - thrust[use]) <= tol)
        back[hit] = b
    known = back >= 0
    out = dict(order)
    cmd = order["actuator"].copy()
    rows = use[known]
    cmd[rows] = p_sorted[latest[rows] - back[known]] + 1  # orders are doubled already
    out["actuator/position"] = cmd
    return out


def _setpoint_period(t: np.ndarray) -> float:
    """Nominal period of a setpoint stream: the median interval, as a whole rate in Hz."""
    d = np.diff(t)
    d = d[d > 0]
    if d.size == 0:
        return 0.0
    return 1.0 / max(1.0, round(1.0 / float(np.median(d))))


def _smoothed(t: np.ndarray, x: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Position through the live tune's complementary filter (same gain, same samples).

    ``x^_n = (1 - k) (x^_{n-1} + v_n dt_n) + k x_n`` from ``x^_0 = x_0``, as
    :class:`mrft_gcs.flight.noise.ComplementaryFilter` computes it sample by sample.
    """
    from scipy.signal import lfilter

    from mrft_gcs.flight.config import SequenceConfig

    if x.size == 0:
        return x
    k = SequenceConfig().side_filter_k
    w = (1 - k) * v[1:] * np.diff(t) + k * x[1:]
    out, _ = lfilter([1.0], [1.0, -(1 - k)], w, zi=[(1 - k) * x[0]])
    return np.concatenate([x[:1], out])


def _rpy(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    w, x, y, z = q.T
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1, 1))
    return roll, pitch


@dataclass(frozen=True)
class _Candidate:
    source: str
    t: np.ndarray
    u: np.ndarray
    y: np.ndarray
    gcs_period_s: float = 0.0
    age_s: np.ndarray | None = None  # see RelaySegment


def _position_signal(pos: np.ndarray, rows: np.ndarray, col: int, filtered: bool,
                     sign: float = 1.0) -> np.ndarray:
    """x (col 1), y (2) or altitude (3, sign -1) at ``rows``; filtered as the live tune does."""
    p = sign * pos[rows, col]
    if not filtered:
        return p
    return _smoothed(pos[rows, 0], p, sign * pos[rows, col + 3])


def _ages(cmd: np.ndarray, tab: np.ndarray, c: _Commands) -> np.ndarray | None:
    """How old each paired sample was when its command was logged (s), for a GCS's."""
    return cmd[c.cmd, 0] - tab[c.rows, 0] if c.gcs_period_s > 0 else None


def _candidates(log: TelemetryLog, order: dict[str, np.ndarray]) -> dict[Loop, list[_Candidate]]:
    """Per loop, the (source, t, u, y) signals worth searching for a relay."""
    out: dict[Loop, list[_Candidate]] = {lp: [] for lp in Loop}
    for name, tab in log.loops.items():
        out[Loop(name)].append(_Candidate("csv", tab[:, 0], tab[:, 1], tab[:, 2]))
    act, att, pos, atg = log.actuator, log.attitude, log.position, log.attitude_target
    if len(act):
        for loop, col, tab, name, ycol in ((Loop.ROLL, 1, att, "attitude", 1),
                                           (Loop.PITCH, 2, att, "attitude", 2),
                                           (Loop.ALTITUDE, 4, pos, "position", 3)):
            if not len(tab):
                continue
            c = _pair(tab, order.get(name), act[:, 0],
                      order.get(f"actuator/{name}", order.get("actuator")))
            if loop is Loop.ALTITUDE:
                y = _position_signal(tab, c.rows, 3, c.gcs_period_s > 0, -1.0)
            else:
                y = tab[c.rows, ycol]
            out[loop].append(_Candidate("actuator", tab[c.rows, 0], act[c.cmd, col], y,
                                        c.gcs_period_s, _ages(act, tab, c)))
    if len(atg) and len(pos):
        roll, pitch = _rpy(atg[:, 1:5])
        c = _pair(pos, order.get("position"), atg[:, 0], order.get("attitude_target"))
        t, filt = pos[c.rows, 0], c.gcs_period_s > 0
        out[Loop.X].append(_Candidate("attitude target", t, -pitch[c.cmd],
                                      _position_signal(pos, c.rows, 1, filt), c.gcs_period_s))
        out[Loop.Y].append(_Candidate("attitude target", t, roll[c.cmd],
                                      _position_signal(pos, c.rows, 2, filt), c.gcs_period_s))
        out[Loop.ALTITUDE].append(_Candidate("attitude target", t, atg[c.cmd, 5],
                                             _position_signal(pos, c.rows, 3, filt, -1.0),
                                             c.gcs_period_s, _ages(atg, pos, c)))
    return out


def _signature(log: TelemetryLog) -> dict[Loop, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Relay output reconstructed from telemetry alone: the sign of the angular acceleration."""
    out: dict[Loop, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    att = log.attitude
    if len(att) < 50:
        return out
    t = att[:, 0]
    dt = np.median(np.diff(t))
    if not dt > 0:
        return out
    k = max(1, int(round(0.01 / dt)))
    for loop, ang, rate in ((Loop.ROLL, 1, 4), (Loop.PITCH, 2, 5)):
        r = np.convolve(att[:, rate], np.ones(k) / k, mode="same")
        acc = np.gradient(r, t)
        scale = np.median(np.abs(acc))
        if not scale > 0:
            continue
        out[loop] = (t, np.sign(acc), att[:, ang])
    return out


def find_relay_segments(log: TelemetryLog, meta: dict[str, str] | None = None,
                        loops: tuple[Loop, ...] | None = None,
                        order: dict[str, np.ndarray] | None = None
                        ) -> tuple[list[RelaySegment], dict[str, str]]:
    """Relay tests in a log, and per loop searched without success, why not.

    Parameters
    ----------
    log : TelemetryLog
    meta : dict, optional
        Metadata (``beta``, ``h``, ``bias``; CSV comments) that overrides inference.
    loops : tuple of Loop, optional
        Only these loops.
    order : dict, optional
        ``DecodedLog.file_order`` of the log's tables (.tlog): pairs commands with the
        samples they answered.

    x and y behind the GCS attitude PDs (torque path) need the attitude identification:
    :func:`dry_run` finds them after roll and pitch.
    """
    return _find(log, meta or {}, loops or tuple(Loop), _answer_order(log, order or {}))


def _find(log: TelemetryLog, meta: dict[str, str], want: tuple[Loop, ...],
          order: dict[str, np.ndarray]) -> tuple[list[RelaySegment], dict[str, str]]:
    found: list[RelaySegment] = []
    why: dict[str, str] = {}
    sig = _signature(log)
    for loop, cands in _candidates(log, order).items():
        if loop not in want:
            continue
        reasons = []
        for c in cands:
            ok = np.isfinite(c.u) & np.isfinite(c.y)
            t, u, y = c.t[ok], c.u[ok], c.y[ok]
            a, b, reason = _relay_stretch(u)
            if reason:
                reasons.append(f"{c.source} command: {reason}")
                continue
            age = None if c.age_s is None else c.age_s[ok][a:b]
            found.append(_segment(loop, c.source, t[a:b], u[a:b], y[a:b], meta, c.gcs_period_s,
                                  age_s=age))
            break
        else:
            if loop in sig and "h" in meta:
                t, u, y = sig[loop]
                a, b, reason = _relay_stretch(u, regular=True)
                if not reason:
                    h = float(meta["h"])
                    found.append(_segment(loop, "telemetry", t[a:b], h * u[a:b], y[a:b], meta))
                    continue
                reasons.append("telemetry: no relay signature (the angular acceleration does "
                               "not switch between two levels)")
            elif loop in sig:
                t, u, _ = sig[loop]
                if not _relay_stretch(u, regular=True)[2]:
                    reasons.append("telemetry: an oscillation with a relay signature, but the "
                                   "relay output is not logged; give its amplitude h")
            if not cands and loop not in sig:
                reasons.append(_missing(loop, log))
            why[loop.value] = "; ".join(reasons) if reasons else _missing(loop, log)
    return found, why


def _missing(loop: Loop, log: TelemetryLog) -> str:
    need = {Loop.ROLL: "torque commands (actuator) and attitude",
            Loop.PITCH: "torque commands (actuator) and attitude",
            Loop.ALTITUDE: "thrust commands (actuator or attitude target) and position",
            Loop.X: "attitude set points, or torque commands with pitch identified, and "
                    "position",
            Loop.Y: "attitude set points, or torque commands with roll identified, and "
                    "position"}
    return f"no relay signal to look at (needs {need[loop]})"


def _segment(loop, source, t, u, y, meta, gcs_period_s: float = 0.0,
             inner: Identification | None = None, age_s: np.ndarray | None = None
             ) -> RelaySegment:
    lo, hi = float(u.min()), float(u.max())
    h = float(meta.get("h", 0.5 * (hi - lo)))
    bias = float(meta.get("bias", 0.5 * (hi + lo)))
    if loop is Loop.ALTITUDE and source != "csv" and "bias" not in meta:
        # Collective thrust: the loop input is the deviation from hover (the mid level).
        u, bias = u - 0.5 * (hi + lo), 0.0
    try:
        inf: RelayInference | None = infer_relay(u, y)
    except IdentificationError:
        if "beta" not in meta:
            raise
        inf = None
    if "beta" in meta:
        beta, frm = float(meta["beta"]), "metadata"
    else:
        assert inf is not None
        beta, frm = inf.beta, "switches"
        dom = _domain_beta(loop, inner)
        if dom is not None and abs(dom - beta) < 0.1:
            # A tune runs the domain's beta; the inferred value is that one, blurred by sampling.
            beta, frm = dom, "domain"
    sp, crossed = (inf.setpoint, inf.crossed) if inf is not None else (math.nan, math.nan)
    return RelaySegment(loop, t, u, y, beta, h, bias, source, frm, gcs_period_s, age_s=age_s,
                        setpoint=sp, crossed=crossed)


def _domain_beta(loop: Loop, inner: Identification | None = None) -> float | None:
    """The ``beta`` a live tune uses on this loop (None without bundled models).

    Side loops: that of the side classifier of the identified attitude loop (``inner``).
    """
    if loop.kind is LoopKind.SIDE and inner is None:
        return None
    try:
        from mrft_gcs.identify import relay_settings

        return float(relay_settings(loop.kind, inner).beta)
    except MrftError:
        return None


def _levels(u: np.ndarray, tol: float) -> np.ndarray:
    """+1 / -1 where ``u`` sits on the high / low level of its last two-level stretch
    (within ``tol`` of the span, found with that tolerance), 0 elsewhere."""
    a, b, reason = _relay_stretch(np.where(np.isfinite(u), u, 0.0), level_tol=tol)
    out = np.zeros(u.size)
    if reason:
        return out
    seg = u[a:b]
    mid = 0.5 * (np.nanmax(seg) + np.nanmin(seg))
    hi, lo = np.nanmedian(seg[seg > mid]), np.nanmedian(seg[seg <= mid])
    near = 0.2 * (hi - lo)
    out[a:b] = np.where(np.abs(seg - hi) < near, 1.0, np.where(np.abs(seg - lo) < near, -1.0, 0))
    return out


def _refit_pds(data: dict, first: dict[Loop, np.ndarray | None], d: np.ndarray
               ) -> dict[Loop, tuple[float, float, float]]:
    """The GCS attitude PDs fitted to the torques, given the relay levels of a first reading.

    Where the first reading puts ``ux`` and ``uy`` on their levels ``+-hx``, ``+-hy``,
    pitch torque ``= trim - Kc hx (cos d sx) - Kc hy (sin d sy) - Kc pitch - Kd q`` and
    roll torque ``= trim + Kc hy (cos d sy) - Kc hx (sin d sx) - Kc roll - Kd p`` are
    linear in ``trim, Kc hx, Kc hy, Kc, Kd``: a robust least-squares fit gives the gains
    a log flown by another version ran with. Returns ``{loop: (trim, Kc, Kd)}``.
    """
    fx, fy = first.get(Loop.X), first.get(Loop.Y)
    sx = None if fx is None else _levels(fx, 0.05)
    sy = None if fy is None else _levels(fy, 0.05)
    c, n = np.cos(d), np.sin(d)
    out = {}
    for lp, (ok, torque, angle, w) in data.items():
        s_own, s_other = (sx, sy) if lp is Loop.PITCH else (sy, sx)
        if s_own is None:
            continue
        use = ok & (s_own != 0)
        cols = [np.ones(torque.size), (-c if lp is Loop.PITCH else c) * s_own]
        if s_other is not None and np.any(n != 0):
            use &= s_other != 0
            cols.append(-n * s_other)
        cols += [-angle, -w]
        if use.sum() < 20:
            continue
        coef = _robust_lstsq(np.column_stack(cols)[use], torque[use])
        if coef[-2] > 0:
            out[lp] = (float(coef[0]), float(coef[-2]), float(coef[-1]))
    return out


def _side_segments(log: TelemetryLog, order: dict[str, np.ndarray],
                   inner: Mapping[Loop, LoopResult], want: tuple[Loop, ...],
                   meta: dict[str, str]) -> tuple[dict[Loop, RelaySegment], dict[str, str]]:
    """x and y relays behind the GCS attitude PDs (torque path), from the torques.

    The live tune turns its x/y relay outputs ``(ux, uy)`` into the set points of its
    roll and pitch PDs: ``roll_ref = uy``, ``pitch_ref = -ux``, or, where it rotates them
    by the heading's departure ``d`` from the take-off heading (``yaw_ref``, which the
    yaw hold keeps), ``roll_ref = cos d uy - sin d ux``, ``pitch_ref = -(cos d ux +
    sin d uy)``, with positions along the take-off heading's axes (while the other
    attitude loop still runs its relay, the other side output is taken as 0: the
    bounding relay's output near the take-off point). Both readings are tried, each with
    the identified and the PD gains fitted to the torques (:func:`_refit_pds`);
    the one whose relay output holds two exact levels longest is the one the log was
    flown with. The relays run without bias:
    their two levels are centred on zero.
    """
    act, att, pos = log.actuator, log.attitude, log.position
    found: dict[Loop, RelaySegment] = {}
    why: dict[str, str] = {}
    if not (len(act) and len(att) and len(pos)):
        return found, why
    a_ord, c_ord = order.get("attitude"), order.get("actuator")
    if a_ord is not None and c_ord is not None:
        by_file = np.argsort(a_ord, kind="stable")
        arow = by_file[np.clip(np.searchsorted(a_ord[by_file], c_ord, side="right") - 1, 0,
                               None)]
    else:
        arow = np.clip(np.searchsorted(att[:, 0], act[:, 0], side="right") - 1, 0, None)
    # per attitude loop: torque, angle and rate of the sample each command answered
    data: dict[Loop, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}
    pd: dict[Loop, tuple[float, float, float]] = {}
    for lp, (col, ang, rate) in ((Loop.PITCH, (2, 2, 5)), (Loop.ROLL, (1, 1, 4))):
        r = inner.get(lp)
        if r is None or r.identification is None or r.cycles is None:
            continue
        ok = (act[:, 0] > r.segment.t[-1]) & (np.abs(act[:, col]) < 1)
        data[lp] = (ok, act[:, col], att[arow, ang], att[arow, rate])
        pd[lp] = (float(np.mean(r.cycles[1])), r.identification.gains.Kc,
                  r.identification.gains.Kd)
    # the plain frame (no rotation) is the one with d = 0
    frames: list[tuple[str, np.ndarray, float]] = [("", np.zeros(act.shape[0]), 0.0)]
    if len(data) == 2 and "yaw_ref" in order:
        yaw_ref = float(order["yaw_ref"][0])
        frames.append(("heading", (att[arow, 3] - yaw_ref + np.pi) % (2 * np.pi) - np.pi,
                       yaw_ref))

    def set_points(d: np.ndarray, gains: dict) -> dict[Loop, np.ndarray | None]:
        ref = {}
        for lp, (ok, torque, angle, w) in data.items():
            trim, Kc, Kd = gains[lp]
            ref[lp] = np.where(ok, (torque - trim + Kd * w) / Kc + angle, np.nan)
        p, r = ref.get(Loop.PITCH), ref.get(Loop.ROLL)
        if p is None or r is None or not np.any(d):
            return {Loop.X: None if p is None else -p, Loop.Y: r}
        c, n = np.cos(d), np.sin(d)
        # while the other attitude loop still runs its relay, its side axis waits on the
        # bounding relay, which holds it at 0 within 1 m of the take-off point
        return {Loop.X: np.where(np.isfinite(r), -c * p - n * r, -p / c),
                Loop.Y: np.where(np.isfinite(p), -n * p + c * r, r / c)}

    readings: list[tuple[str, dict[Loop, np.ndarray | None], float]] = []
    for frame, d, yaw_ref in frames:
        first = set_points(d, pd)
        readings.append((frame, first, yaw_ref))
        refit = _refit_pds(data, first, d)
        if refit:
            readings.append((frame, set_points(d, {**pd, **refit}), yaw_ref))
    pair = _pair(pos, order.get("position"), act[:, 0],
                 order.get("actuator/position", order.get("actuator")))
    for lp in (Loop.X, Loop.Y):
        if lp not in want:
            continue
        name = f"tilt set point behind the {SIDE_INNER[lp].value} PD"
        best: tuple[int, str, np.ndarray, float] | None = None
        reason = "the torques do not follow a PD"
        for frame, cand, yaw_ref in readings:
            u_cmd = cand[lp]
            if u_cmd is None:
                continue
            u_cmd = _mend(u_cmd)
            a, b, reason = _relay_stretch(np.where(np.isfinite(u_cmd), u_cmd, 0.0),
                                          level_tol=_LEVEL_TOL)
            if reason:
                continue
            # the reading the log was flown with puts the relay levels back exactly
            seg = u_cmd[a:b]
            mid = 0.5 * (np.nanmax(seg) + np.nanmin(seg))
            hi, lo = np.nanmedian(seg[seg > mid]), np.nanmedian(seg[seg <= mid])
            exact = int(np.sum(np.minimum(np.abs(seg - hi), np.abs(seg - lo))
                               <= 1e-5 * (hi - lo)))
            if best is None or exact > best[0]:
                best = (exact, frame, u_cmd, yaw_ref)
        if best is None:
            why[lp.value] = f"{name}: {reason}"
            continue
        _, frame, u_cmd, yaw_ref = best
        u_cmd = _hold_levels(u_cmd)
        valid = np.isfinite(u_cmd[pair.cmd])
        rows = pair.rows[valid]
        xy = pos[pair.rows][:, [1, 2, 4, 5]]
        if frame:
            c0, n0 = np.cos(yaw_ref), np.sin(yaw_ref)
            xy = np.column_stack([c0 * xy[:, 0] + n0 * xy[:, 1], c0 * xy[:, 1] - n0 * xy[:, 0],
                                  c0 * xy[:, 2] + n0 * xy[:, 3], c0 * xy[:, 3] - n0 * xy[:, 2]])
        k = 0 if lp is Loop.X else 1
        p, v = xy[:, k], xy[:, k + 2]
        y = (_smoothed(pos[pair.rows, 0], p, v) if pair.gcs_period_s > 0 else p)[valid]
        u = u_cmd[pair.cmd][valid]
        a, b, reason = _relay_stretch(u)
        if reason:
            why[lp.value] = f"{name}: {reason}"
            continue
        lo, hi = float(u[a:b].min()), float(u[a:b].max())
        t = pos[rows, 0]
        side = _segment(lp, "attitude PD", t[a:b], u[a:b] - 0.5 * (lo + hi), y[a:b], meta,
                        pair.gcs_period_s, inner[SIDE_INNER[lp]].identification)
        found[lp] = replace(
            side, tilt=_axis_tilt(att, lp, yaw_ref if frame else None, t[a:b]))
    return found, why


def _axis_tilt(att: np.ndarray, loop: Loop, yaw_ref: float | None,
               t: np.ndarray) -> np.ndarray:
    """The measured tilt along side axis ``loop`` at the times ``t``, as the live tune
    takes it: roll and pitch rotated by the heading's departure from ``yaw_ref`` (none
    when the log was flown without that rotation; x: the forward tilt, ``-pitch``),
    interpolated between ATTITUDE samples."""
    d = (np.zeros(len(att)) if yaw_ref is None
         else (att[:, 3] - yaw_ref + np.pi) % (2 * np.pi) - np.pi)
    c, n = np.cos(d), np.sin(d)
    roll, pitch = att[:, 1], att[:, 2]
    tilt = c * -pitch - n * roll if loop is Loop.X else c * roll - n * pitch
    return np.interp(t, att[:, 0], tilt)


def _mend(u: np.ndarray) -> np.ndarray:
    """``u`` with each single value that stands apart from two equal neighbours (within
    ``_LEVEL_TOL`` of the span) set to theirs: a command whose sample could not be told
    in the middle of a held relay level."""
    span = float(np.nanmax(u) - np.nanmin(u)) if np.isfinite(u).any() else 0.0
    tol = _LEVEL_TOL * span
    out = u.copy()
    a, m, b = u[:-2], u[1:-1], u[2:]
    lone = (np.abs(a - b) <= tol) & (np.abs(m - a) > tol)
    out[1:-1][lone] = a[lone]
    return out


def _hold_levels(u: np.ndarray) -> np.ndarray:
    """The relay output behind a reconstructed set point: its two levels made exact.

    The set points come out of the PD to about 1e-4 of the level where the log tells
    everything, and to about 1e-2 where the other side output had to be assumed: within
    the last two-level stretch the levels are the medians of the values within 1e-5 of
    the span of them (the exact ones), and each value within ``_LEVEL_TOL`` of the span
    of a level takes it. A single value off both levels between two that are on one (a
    command whose sample could not be told) takes their level, or at a switch the nearer
    one: a relay holds each level for many samples.
    """
    a, b, reason = _relay_stretch(np.where(np.isfinite(u), u, 0.0), level_tol=_LEVEL_TOL)
    if reason:
        return u
    seg = u[a:b]
    span = np.nanmax(seg) - np.nanmin(seg)
    mid = 0.5 * (np.nanmax(seg) + np.nanmin(seg))
    levels = []
    for side in (seg[seg > mid], seg[seg <= mid]):
        level = float(np.nanmedian(side))
        exact = side[np.abs(side - level) <= 1e-5 * span]
        levels.append(float(np.median(exact)) if exact.size else level)
    lv = np.array(levels)
    out = u.copy()
    dist = np.abs(u[:, None] - lv[None, :])
    dist[~np.isfinite(dist)] = np.inf
    near = dist.min(axis=1) <= _LEVEL_TOL * span
    out[near] = lv[dist.argmin(axis=1)[near]]
    lone = ~near[1:-1] & near[:-2] & near[2:] & np.isfinite(u[1:-1])
    # between two of the same level: that level; at a switch: the nearer one
    out[1:-1][lone] = lv[np.argmin(dist[1:-1][lone], axis=1)]
    same = lone & (out[:-2] == out[2:])
    out[1:-1][same] = out[:-2][same]
    return out


# ------------------------------------------------------------------ per loop
def _watch(t: np.ndarray, u: np.ndarray, y: np.ndarray, rules: CycleRules
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One relay test through the live tune's cycle watcher, sample by sample.

    Returns the sample indices of the rising switches (cycle boundaries) and, for each,
    whether the watcher said "steady" there and whether it had the cycles to hand over
    (:meth:`CycleWatcher.cycles`), as the live sequence asks it after each sample.
    """
    watch = CycleWatcher(rules)
    rises: list[int] = []
    steady: list[bool] = []
    handed: list[bool] = []
    for k in range(t.size):
        watch.update(float(t[k]), float(u[k]), float(y[k]))
        if watch.rose:
            rises.append(k)
            steady.append(watch.steady)
            handed.append(watch.steady and watch.cycles() is not None)
    return (np.array(rises, dtype=int), np.array(steady, dtype=bool),
            np.array(handed, dtype=bool))


def _steady_rises(t: np.ndarray, u: np.ndarray, y: np.ndarray, n_periods: int,
                  period_tol: float, amplitude_tol: float = 0.08,
                  relax_after: int | None = None, relaxed_tol: tuple[float, float] = (0.08, 0.16)
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The cycle watcher's verdict at each rising switch under the given tolerances
    (:class:`CycleRules`): the sample indices of the rising switches and, for each, whether
    the watcher said "steady" there."""
    rules = CycleRules(n_periods=n_periods, period_tol=period_tol, amplitude_tol=amplitude_tol,
                       relax_after=relax_after, relaxed_tol=relaxed_tol)
    rises, steady, _ = _watch(t, u, y, rules)
    return rises, steady


_Cycles = tuple[np.ndarray, np.ndarray, np.ndarray]


def _live_cycles(seg: RelaySegment, inner: Identification | None
                 ) -> tuple[Identification | None, _Cycles, bool, list[str]]:
    """The cycles a live tune identifies, and their identification.

    The segment goes through the live tune's own cycle watcher
    (:class:`mrft_gcs.flight.cycles.CycleWatcher`, with the rules of
    :meth:`SequenceConfig.cycle_rules`) sample by sample; where it is steady, the tune
    identifies the cycles it hands over, then switches the loop to its PD a few
    milliseconds later, and an identification error restarts the watcher and waits for
    the next steady cycles. When that happens is up to the ground station's scheduling,
    but the relay stops right after: so the identified cycles are those that end at the
    last rising switch, before the relay stopped, at which the watcher handed cycles over.
    Where identification fails there, earlier steady cycles are tried (up to five, while
    the reason differs). Returns the identification (None when none succeeded), the
    cycles, whether they were steady, notes.
    """
    from mrft_gcs.flight.config import SequenceConfig

    rules = SequenceConfig().cycle_rules(seg.loop)
    m = rules.identify_cycles
    rises, _, handed = _watch(seg.t, seg.u, seg.y, rules)
    notes: list[str] = []
    windows = [(int(rises[i - m]), int(rises[i]) + 1)
               for i in np.flatnonzero(handed)[::-1][:5]]
    failed: set[str] = set()
    for a, b in windows:
        cyc = (seg.t[a:b], seg.u[a:b], seg.y[a:b])
        try:
            return identify(seg.loop.kind, *cyc, beta=seg.beta, h=seg.h, bias=seg.bias,
                            inner=inner, tilt=_tilt(seg, a, b)), cyc, True, notes
        except IdentificationError as err:
            if str(err) in failed:  # the same reason for every window: no point going on
                break
            failed.add(str(err))
            notes.append(f"the steady cycles up to t={seg.t[b - 1]:.2f} s were not "
                         f"identified ({err})")
        except MrftError as err:
            notes.append(f"not identified: {err}")
            break
    if windows:
        a, b = windows[0]
        return None, (seg.t[a:b], seg.u[a:b], seg.y[a:b]), True, notes
    if rises.size >= 2:
        a, b = int(rises[max(0, rises.size - 1 - m)]), int(rises[-1]) + 1
    else:
        a, b = 0, seg.t.size
    cyc = (seg.t[a:b], seg.u[a:b], seg.y[a:b])
    spread = (np.ptp(np.diff(seg.t[rises[-4:]])) / np.mean(np.diff(seg.t[rises[-4:]]))
              if rises.size >= 3 else np.inf)
    notes.append(f"the oscillation is not steady ({max(rises.size - 1, 0)} cycles, period "
                 f"spread {spread:.0%}); results are doubtful")
    try:
        return identify(seg.loop.kind, *cyc, beta=seg.beta, h=seg.h, bias=seg.bias,
                        inner=inner, tilt=_tilt(seg, a, b)), cyc, False, notes
    except MrftError as err:
        notes.append(f"not identified: {err}")
        return None, cyc, False, notes


def _tilt(seg: RelaySegment, a: int, b: int) -> np.ndarray | None:
    return None if seg.tilt is None else seg.tilt[a:b]


def _gcs_delay(seg: RelaySegment, t_cycles: np.ndarray) -> GcsDelay:
    """The GCS delay over the identified cycles, measured on the log as a live tune
    measures it (:func:`mrft_gcs.flight.onboard.measure_gcs_delay`)."""
    from mrft_gcs.flight.onboard import measure_gcs_delay

    t, ages = np.empty(0), np.empty(0)
    if seg.age_s is not None and len(t_cycles):
        m = (seg.t >= t_cycles[0]) & (seg.t <= t_cycles[-1])
        t, ages = seg.t[m], seg.age_s[m]
    return measure_gcs_delay(ages, seg.gcs_period_s, sample_t_s=t, clock=seg.clock)


def _retarget_delay(seg: RelaySegment, t_cycles: np.ndarray) -> tuple[float, bool]:
    """The GCS delay to re-target by over the identified cycles (s, before the robust
    check), and whether this log measured it plausibly (else half a setpoint period)."""
    g = _gcs_delay(seg, t_cycles)
    return g.estimate_s, g.measured


def analyse_segment(seg: RelaySegment, *, inner: Identification | None = None,
                    model: InnerModel | None = None, hover: float = 0.5,
                    structure: OnboardStructure | None = None,
                    position_hz: float = math.nan) -> LoopResult:
    """Cycle detector, identification and residual analysis of one relay test.

    The cycles identified are those a live tune identifies (:func:`_live_cycles`);
    when the oscillation never becomes steady, the last cycles are identified with a
    note. ``model`` replaces the identified model for the residual
    analysis (e.g. a known model while the classifiers are not bundled). ``structure``:
    how the autopilot closes the loop on written gains (:func:`log_structure`);
    ``position_hz``: the rate of its position loop (Hz, :func:`log_position_rate`; NaN: the
    slowest allowed for).
    """
    ident, cyc, steady, notes = _live_cycles(seg, inner)
    return _loop_result(seg, ident, cyc, steady, notes, model, hover, structure, position_hz)


def log_structure(decoded: DecodedLog, family: str = "") -> dict[Loop, OnboardStructure]:
    """Roll and pitch structures from the parameters a log holds, as a live tune reads them
    from the vehicle (:func:`~mrft_gcs.flight.structure.vehicle_structure`): the first logged
    value of each (what the vehicle had before any write). ``family`` ("" : an ArduPilot
    where the log holds ``ATC_*`` parameters) picks the default where the log does not say.
    """
    first: dict[str, float] = {}
    for e in decoded.events:
        if isinstance(e, ParamValue) and e.name not in first:
            first[e.name] = float(e.value)
    if not family and any(n.startswith("ATC_") for n in first):
        family = "ardupilot"
    return vehicle_structure(first.get, family)


def log_position_rate(decoded: DecodedLog, family: str = "") -> PositionLoopRate:
    """The position loop's rate from the parameters a log holds, as a live tune reads it
    (:func:`~mrft_gcs.flight.onboard.vehicle_position_rate`): the first logged values."""
    first: dict[str, float] = {}
    for e in decoded.events:
        if isinstance(e, ParamValue) and e.name not in first:
            first[e.name] = float(e.value)
    return vehicle_position_rate(first.get, family)


def _retarget(seg: RelaySegment, design: Identification, t_cycles: np.ndarray,
              structure: OnboardStructure | None, position_hz: float) -> Retarget:
    """The gains a tune writes for a loop whose relay ran on a ground station, designed on
    ``design`` (the identification, or roll/pitch with their fast lags pooled)."""
    rt = robust_onboard_gains(design, _gcs_delay(seg, t_cycles),
                              onboard_extra_s=onboard_extra_delay_s(seg.loop, position_hz))
    return structured_retarget(design, rt, structure) if structure is not None else rt


_RETARGET_NOTE = "gains re-targeted to the onboard loop"


def _retarget_note(rt: Retarget, ident: Identification) -> str:
    return (f"{_RETARGET_NOTE}, less delay than the ground-station relay by how old telemetry "
            f"was when the command answering it was logged ({rt.note()}), as a tune writes "
            f"them; identified Kc {ident.gains.Kc:.4g}, Kd {ident.gains.Kd:.4g}")


def _pool_roll_pitch(by_loop: dict[Loop, LoopResult],
                     structure: dict[Loop, OnboardStructure], position_hz: float) -> None:
    """Roll and pitch flown on the ground station's torque re-designed on their pooled fast
    lags, as a tune writes them (:func:`mrft_gcs.flight.onboard.pooled_attitude`)."""
    r, p = by_loop.get(Loop.ROLL), by_loop.get(Loop.PITCH)
    if (r is None or p is None or r.identification is None or p.identification is None
            or r.cycles is None or p.cycles is None
            or not all(x.segment.gcs_period_s > 0 and x.segment.source == "actuator"
                       for x in (r, p))):
        return
    pr, pp = pooled_attitude(r.identification, p.identification)
    if pr is r.identification:
        return
    note = pooled_note(r.identification, p.identification, pr)
    for res, design in ((r, pr), (p, pp)):
        assert res.identification is not None and res.cycles is not None
        rt = _retarget(res.segment, design, res.cycles[0], structure.get(res.loop),
                       position_hz)
        kept = tuple(n for n in res.notes if not n.startswith(_RETARGET_NOTE))
        by_loop[res.loop] = replace(res, gains=rt.gains, gcs_delay_s=rt.delay_s,
                                    rate_d_over_p_s=rt.d_over_p_s, notes=kept + (
                                        _retarget_note(rt, res.identification), note))


def _loop_result(seg: RelaySegment, ident: Identification | None, cyc: _Cycles, steady: bool,
                 notes: list[str], model: InnerModel | None, hover: float,
                 structure: OnboardStructure | None = None,
                 position_hz: float = math.nan) -> LoopResult:
    """The gains a tune writes from ``ident`` (re-targeted where the relay ran on a ground
    station, and designed on the autopilot's ``structure`` as a tune designs them) and the
    residual analysis over the identified cycles ``cyc``."""
    if seg.crossed < 0.9 and seg.beta_from == "switches":
        notes.insert(0, f"the oscillation does not cross the relay's set point every half cycle "
                        f"({100 * seg.crossed:.0f} % do): the relay lost its set point, so its "
                        f"beta cannot be read from the switches ({seg.beta:.2f}); give beta "
                        f"('--beta' or '# beta=...' in a CSV)")
    gains, delay, d_ratio = None, math.nan, 0.0
    if ident is not None:
        gains = ident.gains
        if seg.gcs_period_s > 0 and isinstance(ident.model, InnerModel):
            rt = _retarget(seg, ident, cyc[0], structure, position_hz)
            delay, gains, d_ratio = rt.delay_s, rt.gains, rt.d_over_p_s
            notes.append(_retarget_note(rt, ident))
    res = None
    use = ident.model if ident is not None else model
    if isinstance(use, InnerModel):
        kind = LoopKind.ALTITUDE if seg.loop is Loop.ALTITUDE else LoopKind.ATTITUDE
        t, u, y = cyc if steady else (seg.t, seg.u, seg.y)
        band = 4.0 * noise_std(y) if seg.gcs_period_s > 0 else 0.0
        try:
            res = analyse_residual(use, RelayTest(seg.beta, seg.h, seg.bias), t, u, y,
                                   kind=kind, hover=hover, band=band)
        except MrftError as err:
            notes.append(f"residual not analysed: {err}")
    elif isinstance(use, SideModel):
        notes.append("residual analysis covers roll, pitch and altitude only")
    return LoopResult(seg.loop, seg, steady, ident, res, tuple(notes), cyc, gains, delay,
                      d_ratio)


def dry_run(path: str | Path, *, loops: tuple[Loop, ...] | None = None, profile=None,
            models: dict[Loop, InnerModel] | None = None, meta: dict[str, str] | None = None
            ) -> DryRunResult:
    """Identify every relay test in a log; return models, residuals and would-be parameters.

    Parameters
    ----------
    path : str or Path
        A .tlog, .ulg, .bin or CSV log.
    loops : tuple of Loop, optional
        Only these loops.
    profile : AutopilotProfile, optional
        Maps the gains a tune would write to parameter values (``parameters``), clamped
        into its ``[param_ranges]`` as a tune writes them (a note on the loop per clamp).
    models : dict, optional
        Known models per loop, used for residual analysis where identification fails.
    meta : dict, optional
        ``beta``, ``h``, ``bias`` overriding what is inferred (CSV metadata is read too).

    Raises
    ------
    InputFileError
        The log cannot be read.
    """
    decoded = _before_write_back(decode_log(path).cleaned())
    log = to_telemetry_log(decoded)
    info: dict[str, str] = {}
    if Path(path).suffix.lower() == ".csv" or log.loops:
        try:
            info.update(read_csv_metadata(path))
        except MrftError:
            pass
    info.update(meta or {})
    want = loops or tuple(Loop)
    # x and y behind the GCS attitude PDs need the attitude loops (a heading rotation
    # mixes both), and altitude tells which position sample a command answered
    search = set(want)
    if set(want) & {Loop.X, Loop.Y}:
        search |= {Loop.ROLL, Loop.PITCH, Loop.ALTITUDE}
    order = _answer_order(log, decoded.file_order)
    segs, why = _find(log, info, tuple(lp for lp in Loop if lp in search), order)
    # the ages were counted on the log's clock fit: its slips and skew judge them
    segs = [replace(s, clock=decoded.clock) if s.age_s is not None else s for s in segs]
    hover = _hover(log, profile)
    hover_f = hover if hover is not None else 0.5
    structure = log_structure(decoded, profile.family.value if profile is not None else "")
    position_hz = log_position_rate(decoded, profile.family.value if profile is not None
                                    else "").hz
    by_loop: dict[Loop, LoopResult] = {}
    for seg in sorted(segs, key=lambda s: s.loop.kind is LoopKind.SIDE):
        inner = None
        if seg.loop.kind is LoopKind.SIDE:
            att = by_loop.get(SIDE_INNER[seg.loop])
            inner = att.identification if att else None
            if inner is not None and "beta" not in info:
                seg = _segment(seg.loop, seg.source, seg.t, seg.u, seg.y, info,
                               seg.gcs_period_s, inner)
        by_loop[seg.loop] = analyse_segment(seg, inner=inner, model=(models or {}).get(seg.loop),
                                            hover=hover_f, structure=structure.get(seg.loop),
                                            position_hz=position_hz)
    alt = by_loop.get(Loop.ALTITUDE)
    if alt is not None and alt.identification is not None and alt.segment.source == "actuator":
        order = _answer_position(log, order, float(alt.segment.t[-1]))
    todo = tuple(lp for lp in (Loop.X, Loop.Y) if lp in want and lp not in by_loop)
    attitude: dict[Loop, LoopResult] = {
        lp: r for lp, r in by_loop.items()
        if lp in (Loop.ROLL, Loop.PITCH) and r.segment.source == "actuator"}
    if todo and attitude:
        sides, reasons = _side_segments(log, order, attitude, todo, info)
        for lp, side in sides.items():
            why.pop(lp.value, None)
            by_loop[lp] = analyse_segment(side, inner=attitude[SIDE_INNER[lp]].identification,
                                          hover=hover_f)
        for k, reason in reasons.items():
            why[k] = f"{why.get(k, '')}; {reason}".lstrip("; ")
    if decoded.file_order:
        session = _replay_session(decoded, profile)
        if session is not None:
            cmds = decoded.actuator if len(decoded.actuator) else decoded.attitude_target
            _use_session(session, by_loop, why, want, models or {}, hover_f,
                         _setpoint_period(cmds[:, 0]), structure, position_hz)
    _pool_roll_pitch(by_loop, structure, position_hz)
    results = tuple(by_loop[lp] for lp in Loop if lp in by_loop and lp in want)
    why = {k: v for k, v in why.items() if Loop(k) in want}
    params: dict[str, float] = {}
    if profile is not None:
        from mrft_gcs.profiles import PDGains, params_in_range

        gains = {r.loop: PDGains(r.gains.Kc, r.gains.Kd) for r in results if r.gains is not None}
        if gains:
            ranged = params_in_range(profile, gains, hover_f)  # clamped as a tune writes them
            params = {**ranged.values, **rate_d_values(profile, ranged.gains, {
                r.loop: r.rate_d_over_p_s for r in results})}
            results = tuple(replace(r, notes=r.notes + tuple(
                n for c, n in zip(ranged.clamps, ranged.notes, strict=True) if r.loop in c.loops))
                for r in results)
    cut = log_truncation(path)
    return DryRunResult(str(path), summarize_log(log), results, why, params,
                        warnings=(cut,) if cut else ())


#: a session log of mrft-tune's own tune: the replayed sequence must reproduce at least this
#: share of the logged commands from take-off to the side tests (its own logs: all of them,
#: docs/pipeline.md), over at least this many ticks (1 s at 250 Hz)
_SESSION_MATCH = 0.95
_SESSION_MIN_TICKS = 250


class _NotSession(Exception):
    """The replayed sequence does not answer the log's states with its commands."""


#: beta, h and bias of the relay that flew
_Relay = tuple[float, float, float]


@dataclass(frozen=True)
class _SessionReplay:
    """The tune's sequence re-run over a session log (:func:`_replay_session`)."""

    loops: dict[Loop, tuple[Identification, _Cycles, np.ndarray | None, _Relay]]
    matched: int
    compared: int
    notes: dict[Loop, str]
    #: where the relay outputs were logged (``RelaySegment.source``): the commands, or x and
    #: y behind the ground station's attitude PDs (torque path)
    source: str


def _first_param(decoded: DecodedLog, names: list[str]) -> float | None:
    """The first logged value of the first of ``names`` in the log: what a tune read before
    take-off (it may write some of them afterwards)."""
    for n in names:
        for e in decoded.events:
            if isinstance(e, ParamValue) and e.name == n and 0 < e.value < 1:
                return float(e.value)
    return None


def _command_values(sp: object) -> tuple[float, ...] | None:
    """A torque or attitude command's values without its time (None: another kind)."""
    from mrft_gcs.telemetry import ActuatorTarget, AttitudeTarget

    if isinstance(sp, ActuatorTarget):
        return (sp.roll, sp.pitch, sp.yaw, sp.thrust)
    if isinstance(sp, AttitudeTarget):
        return (*sp.q_wxyz, sp.thrust)
    return None


def _replay_session(decoded: DecodedLog, profile) -> _SessionReplay | None:
    """Re-run the tune's own sequence over a session .tlog of mrft-tune, or None where the
    log is not one (or cannot be replayed).

    :class:`~mrft_gcs.flight.source.ReplayVehicle` plays the log tick by tick through
    :class:`~mrft_gcs.flight.driver.SequenceDriver` with the bundled identification and
    relay settings, the sequence configured as ``tune()`` configures it from what the log
    holds (the command kind, the hover thrust read before take-off, the profile's tilt
    limit). A log is taken for a session of this tool only where the replayed sequence
    answers the logged states with the logged commands, tick for tick, from take-off up to
    the side tests (:data:`_SESSION_MATCH`): another ground station's commands, a tune run
    with other relay settings or another take-off height do not.
    """
    from mrft_gcs.flight.config import SequenceConfig
    from mrft_gcs.flight.driver import SequenceDriver
    from mrft_gcs.flight.sequence import TuningSequence
    from mrft_gcs.flight.source import ReplayVehicle
    from mrft_gcs.identify import relay_settings
    from mrft_gcs.identify.live import bundled_identifier
    from mrft_gcs.profiles import Actuation, SafetyLimits

    fo = decoded.file_order
    kind = "actuator" if len(decoded.actuator) >= len(decoded.attitude_target) else (
        "attitude_target")
    if (not len(getattr(decoded, kind)) or not all(k in fo for k in ("attitude", "position",
                                                                      kind))):
        return None  # the session's own order of samples and commands is needed
    src = ReplayVehicle(decoded)
    takeoff = src.takeoff_tick()
    if takeoff is None:
        return None
    names = [profile.altitude.hover_thrust] if profile is not None else []
    hover = _first_param(decoded, names + ["MPC_THR_HOVER", "MOT_THST_HOVER"])
    lim = profile.safety if profile is not None else SafetyLimits()
    act = Actuation.TORQUE if kind == "actuator" else Actuation.ATTITUDE
    cfg = replace(SequenceConfig(), actuation=act, z_ref_m=1.0, hover_thrust_guess=hover,
                  max_tilt_cmd_rad=0.6 * math.radians(lim.max_tilt_deg))
    try:
        seq = TuningSequence(cfg, relay_settings(LoopKind.ATTITUDE),
                             relay_settings(LoopKind.ALTITUDE))
    except MrftError:
        return None  # no bundled classifiers: the relay tests are found in the log instead
    drv = SequenceDriver(seq, bundled_identifier)
    count = [0, 0]

    def compare(_s, sp) -> None:
        # the sequence alone drives the commands until the side tests start
        if any(seq.loops[lp].relay is not None for lp in (Loop.X, Loop.Y)):
            return
        got = src.applied()
        count[1] += 1
        a, b = _command_values(sp), _command_values(got)
        if type(sp) is type(got) and a is not None and b is not None:
            # float32 on the wire, and states decoded from it: the replay's commands agree
            # to ~1e-5 of full scale; another relay level or PD is off by 1e-2 or more
            count[0] += bool(np.allclose(a, b, rtol=0.0, atol=1e-4))
        if count[1] - count[0] > (1.0 - _SESSION_MATCH) * max(count[1], _SESSION_MIN_TICKS):
            raise _NotSession  # no need to fly another ground station's log to its end

    notes: dict[Loop, str] = {}
    try:
        drv.run(src, ground_ticks=takeoff, follow_applied=True, on_tick=compare)
    except (MrftError, _NotSession):
        return None
    matched, compared = count
    if compared < _SESSION_MIN_TICKS or matched < _SESSION_MATCH * compared:
        return None
    out = {}
    for lp, t in seq.loops.items():
        snap = t.snapshot
        if t.identification is None or snap is None:
            continue
        out[lp] = (t.identification, (snap.t_s, snap.u, snap.y), snap.tilt,
                   (snap.beta, snap.h, snap.bias))
        if t.note:
            notes[lp] = t.note
    return _SessionReplay(out, matched, compared, notes,
                          "actuator" if kind == "actuator" else "attitude target")


def _use_session(session: _SessionReplay, by_loop: dict[Loop, LoopResult],
                 why: dict[str, str], want: tuple[Loop, ...], models: dict[Loop, InnerModel],
                 hover: float, period_s: float,
                 structure: dict[Loop, OnboardStructure] | None = None,
                 position_hz: float = math.nan) -> None:
    """Each loop the replayed tune identified: its identification, on the cycles the
    sequence handed over, replaces what the relay-segment search found (whose segment,
    with the ages the written gains are re-targeted by, is kept where it found one)."""
    for lp, (ident, cyc, tilt, (beta, h, bias)) in session.loops.items():
        if lp not in want:
            continue
        old = by_loop.get(lp)
        if old is not None:
            seg = replace(old.segment, beta=beta, h=h, bias=bias, beta_from="session")
        else:
            source = ("attitude PD" if lp.kind is LoopKind.SIDE and session.source == "actuator"
                      else session.source)
            seg = RelaySegment(lp, cyc[0], cyc[1], cyc[2], beta, h, bias, source, "session",
                               gcs_period_s=period_s, tilt=tilt)
        notes = [f"identified by replaying the session through the tune's own sequence "
                 f"({session.matched} of {session.compared} logged commands reproduced "
                 f"before the side tests)"]
        if lp in session.notes:
            notes.append(session.notes[lp])
        why.pop(lp.value, None)
        by_loop[lp] = _loop_result(seg, ident, cyc, True, notes, models.get(lp), hover,
                                   (structure or {}).get(lp), position_hz)


def _before_write_back(decoded: DecodedLog) -> DecodedLog:
    """Attitude set points up to the gains' write-back only: a tune writes its gains after
    its relay tests, and what it sends after that (the in-air check's square wave on the
    attitude set point) is no relay test. The write-back is the first PARAM_VALUE logged
    after the first command."""
    atg = decoded.attitude_target
    cmds = [t[0, 0] for t in (decoded.actuator, atg) if len(t)]
    if not cmds or not len(atg):
        return decoded
    first = min(cmds)
    written = [e.t_s for e in decoded.events if isinstance(e, ParamValue) and e.t_s > first]
    if not written:
        return decoded
    keep = atg[:, 0] < min(written)
    order = dict(decoded.file_order)
    if "attitude_target" in order:
        order["attitude_target"] = order["attitude_target"][keep]
    return replace(decoded, attitude_target=atg[keep], file_order=order)


def _hover(log: TelemetryLog, profile) -> float | None:
    names = ["MPC_THR_HOVER", "MOT_THST_HOVER"]
    if profile is not None:
        names.insert(0, profile.altitude.hover_thrust)
    for n in names:
        v = log.params.get(n)
        if v is not None and 0 < v < 1:
            return float(v)
    return None
