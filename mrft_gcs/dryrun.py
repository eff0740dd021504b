"""Dry-run: the identification of a live tune, on logged telemetry; touches nothing.

:func:`dry_run` reads a log (:func:`mrft_gcs.logs.read_log`), finds the relay
tests in it (:func:`find_relay_segments`), and for each loop runs the same
pipeline as a live tune (:func:`analyse_segment`): the cycle detector, the
classifier with exact gain scaling (:func:`mrft_gcs.identify.identify`), then
residual analysis (:func:`mrft_gcs.residual.analyse_residual`). It returns a
:class:`DryRunResult` holding the identified models, residuals and the
parameter values a tune would write; it never opens a link.

Where relay tests come from
---------------------------
- **Explicit loop tables** (the documented CSV): ``u`` is the relay output.
- **Recorded setpoints**: torque commands (SET_ACTUATOR_CONTROL_TARGET roll and
  pitch, collective thrust for altitude) or attitude set points (x: -pitch,
  y: +roll, from SET_ATTITUDE_TARGET) that alternate between two levels. The
  measured output is the attitude, altitude (-z) or position, zero-order held at
  the set-point times.
- **Relay signature in telemetry alone**: a sustained oscillation of an angle
  whose rate has a square-wave derivative (the relay's torque). The relay levels
  are not in the log, so ``h`` must then be given (CSV metadata or ``h=``).

A relay stretch is a run of at least ``MIN_SWITCHES`` level changes, each level
held for two samples or more, alternating between two values. ``h`` is half
the level difference, the bias the mid level; ``beta`` comes from where the
switches happen relative to the error extremes (``e_switch = -beta e_max``),
unless metadata gives it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mrft_gcs.errors import IdentificationError, MrftError
from mrft_gcs.identify import CycleDetector, Identification, identify
from mrft_gcs.logs import read_csv_metadata, read_log, summarize_log
from mrft_gcs.logs.describe import LogSummary
from mrft_gcs.loops import Loop, LoopKind
from mrft_gcs.plant import InnerModel, SideModel
from mrft_gcs.residual import RelayTest, ResidualReport, analyse_residual
from mrft_gcs.telemetry import TelemetryLog

__all__ = ["RelaySegment", "LoopResult", "DryRunResult", "find_relay_segments", "infer_beta",
           "analyse_segment", "dry_run", "MIN_SWITCHES"]

#: Level changes a relay stretch needs (three full cycles).
MIN_SWITCHES = 6


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
        Where ``u`` came from (``"csv"``, ``"actuator"``, ``"attitude target"``, ``"telemetry"``).
    beta_from : str
        ``"metadata"``, ``"switches"`` or ``"domain"`` (inferred, within 0.1 of the beta a
        tune uses on that loop, and snapped to it).
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

    @property
    def duration_s(self) -> float:
        return float(self.t[-1] - self.t[0])


@dataclass(frozen=True)
class LoopResult:
    """What dry-run found for one loop: identification and residual, or why not."""

    loop: Loop
    segment: RelaySegment
    steady: bool
    identification: Identification | None = None
    residual: ResidualReport | None = None
    notes: tuple[str, ...] = ()

    def as_dict(self) -> dict:
        """The loop's entry of the tuning report (SPEC 4.3), as far as dry-run knows it."""
        ident = self.identification
        seg = self.segment
        out: dict = {"beta": seg.beta, "h": seg.h, "bias": seg.bias, "source": seg.source,
                     "steady": self.steady, "notes": list(self.notes)}
        if ident is not None:
            out.update(model=ident.model.as_dict(), **{"class": ident.class_index},
                       confidence=ident.confidence, period_s=ident.period_s,
                       amplitude=ident.amplitude,
                       gains={"Kc": ident.gains.Kc, "Kd": ident.gains.Kd})
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
    """

    source: str
    summary: LogSummary
    loops: tuple[LoopResult, ...]
    searched: dict[str, str] = field(default_factory=dict)
    parameters: dict[str, float] = field(default_factory=dict)

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


def _relay_stretch(u: np.ndarray, regular: bool = False) -> tuple[int, int, str]:
    """Longest stretch of ``u`` alternating between two levels: (start, stop, why-not).

    ``regular``: each level must also be held about as long as the last time (within
    35 %), as in a steady relay oscillation (used for signs reconstructed from telemetry).
    """
    if u.size < 2 * MIN_SWITCHES:
        return 0, 0, f"only {u.size} samples"
    span = float(np.ptp(u))
    if span <= 0:
        return 0, 0, "the command is constant"
    starts, lengths, vals = _runs(u, 1e-6 * max(span, 1e-9) + 1e-7)
    tol = 0.02 * span
    best = (0, 0, 0)  # (switches, first run, last run)
    i = 0
    m = 4 if regular else 2  # samples a level must be held
    while i < vals.size - 1:
        j = i
        a, b = vals[i], vals[i + 1]
        if abs(a - b) > 10 * tol and lengths[i] >= m:
            j = i + 1
            while (j + 1 < vals.size and lengths[j] >= m
                   and abs(vals[j + 1] - vals[j - 1]) <= tol
                   and (not regular or j < i + 2
                        or abs(lengths[j] - lengths[j - 2]) <= 0.35 * lengths[j - 2])):
                j += 1
            if lengths[j] < m:
                j -= 1
            if j - i > best[0]:
                best = (j - i, i, j)
        i = max(j, i + 1)
    n, i0, i1 = best
    if n < MIN_SWITCHES:
        distinct = np.unique(np.round(vals / max(tol, 1e-12))).size
        return 0, 0, (f"the command is not a two-level relay signal (longest two-level stretch "
                      f"has {n} switches, need {MIN_SWITCHES}; {distinct} distinct levels)")
    return int(starts[i0]), int(starts[i1] + lengths[i1]), ""


def infer_beta(u: np.ndarray, y: np.ndarray) -> float:
    """MRFT ``beta`` from where the relay switched relative to the error extremes.

    With ``e = r - y`` (``r``: the oscillation's centre), the relay leaves the high
    level when ``e <= -beta e_max`` (``e_max`` the largest error in that state), and the
    low level when ``e >= -beta e_min``; ``beta`` is the median of these ratios.
    """
    mid = 0.5 * (u.min() + u.max())
    high = u > mid
    e = -(y - 0.5 * (y.max() + y.min()))
    sw = np.flatnonzero(high[1:] != high[:-1]) + 1
    ratios = []
    for a, b in zip(sw[:-1], sw[1:], strict=False):
        seg = e[a:b]
        ext = seg.max() if high[a] else seg.min()
        if abs(ext) > 0 and b < e.size:
            # The threshold was crossed between the last two samples before the switch.
            ratios.append(-0.5 * (e[b] + e[b - 1]) / ext)
    if not ratios:
        raise IdentificationError("cannot infer the relay's beta: too few switches; give "
                                  "beta in the CSV metadata ('# beta=... h=...')")
    return float(np.clip(np.median(ratios), -0.95, 0.95))


def _held(t_out: np.ndarray, t_in: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Command in answer to each measurement: the first one sent at or after it.

    A ground station computes the relay output from a measurement and sends it after
    that measurement arrived, so the command paired with sample ``k`` is the next one
    (the last one, after the end of the commands).
    """
    idx = np.clip(np.searchsorted(t_in, t_out, side="left"), 0, t_in.size - 1)
    return v[idx]


def _rpy(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    w, x, y, z = q.T
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1, 1))
    return roll, pitch


def _candidates(log: TelemetryLog) -> dict[Loop, list]:
    """Per loop, the (source, t, u, y) pairs worth searching for a relay."""
    out: dict[Loop, list] = {lp: [] for lp in Loop}
    for name, tab in log.loops.items():
        out[Loop(name)].append(("csv", tab[:, 0], tab[:, 1], tab[:, 2]))
    act, att, pos, atg = log.actuator, log.attitude, log.position, log.attitude_target
    if len(act):
        for loop, col, tab, ycol in ((Loop.ROLL, 1, att, 1), (Loop.PITCH, 2, att, 2),
                                     (Loop.ALTITUDE, 4, pos, 3)):
            if len(tab):
                y = tab[:, ycol] * (-1 if loop is Loop.ALTITUDE else 1)
                out[loop].append(("actuator", tab[:, 0], _held(tab[:, 0], act[:, 0],
                                                               act[:, col]), y))
    if len(atg) and len(pos):
        roll, pitch = _rpy(atg[:, 1:5])
        t = pos[:, 0]
        out[Loop.X].append(("attitude target", t, _held(t, atg[:, 0], -pitch), pos[:, 1]))
        out[Loop.Y].append(("attitude target", t, _held(t, atg[:, 0], roll), pos[:, 2]))
        out[Loop.ALTITUDE].append(("attitude target", t, _held(t, atg[:, 0], atg[:, 5]),
                                   -pos[:, 3]))
    return out


def _signature(log: TelemetryLog) -> dict[Loop, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Relay output reconstructed from telemetry alone: the sign of the angular acceleration."""
    out = {}
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
                        loops: tuple[Loop, ...] | None = None
                        ) -> tuple[list[RelaySegment], dict[str, str]]:
    """Relay tests in a log, and per loop searched without success, why not.

    Parameters
    ----------
    log : TelemetryLog
    meta : dict, optional
        Metadata (``beta``, ``h``, ``bias``; CSV comments) that overrides inference.
    loops : tuple of Loop, optional
        Only these loops.
    """
    meta = meta or {}
    want = loops or tuple(Loop)
    found: list[RelaySegment] = []
    why: dict[str, str] = {}
    sig = _signature(log)
    for loop, cands in _candidates(log).items():
        if loop not in want:
            continue
        reasons = []
        for source, t, u, y in cands:
            ok = np.isfinite(u) & np.isfinite(y)
            t, u, y = t[ok], u[ok], y[ok]
            a, b, reason = _relay_stretch(u)
            if reason:
                reasons.append(f"{source} command: {reason}")
                continue
            found.append(_segment(loop, source, t[a:b], u[a:b], y[a:b], meta))
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
            Loop.X: "attitude set points and position", Loop.Y: "attitude set points and position"}
    return f"no relay signal to look at (needs {need[loop]})"


def _segment(loop, source, t, u, y, meta) -> RelaySegment:
    lo, hi = float(u.min()), float(u.max())
    h = float(meta.get("h", 0.5 * (hi - lo)))
    bias = float(meta.get("bias", 0.5 * (hi + lo)))
    if loop is Loop.ALTITUDE and source != "csv" and "bias" not in meta:
        # Collective thrust: the loop input is the deviation from hover (the mid level).
        u, bias = u - 0.5 * (hi + lo), 0.0
    if "beta" in meta:
        beta, frm = float(meta["beta"]), "metadata"
    else:
        beta, frm = infer_beta(u, y), "switches"
        dom = _domain_beta(loop)
        if dom is not None and abs(dom - beta) < 0.1:
            # A tune runs the domain's beta; the inferred value is that one, blurred by sampling.
            beta, frm = dom, "domain"
    return RelaySegment(loop, t, u, y, beta, h, bias, source, frm)


def _domain_beta(loop: Loop) -> float | None:
    """The ``beta`` a live tune uses on this loop (None without bundled models or for x/y)."""
    if loop.kind is LoopKind.SIDE:
        return None
    try:
        from mrft_gcs.identify import relay_settings

        return float(relay_settings(loop.kind).beta)
    except MrftError:
        return None


# ------------------------------------------------------------------ per loop
def analyse_segment(seg: RelaySegment, *, inner: Identification | None = None,
                    model: InnerModel | None = None, hover: float = 0.5) -> LoopResult:
    """Cycle detector, identification and residual analysis of one relay test.

    ``model`` replaces the identified model for the residual analysis (e.g. a known
    model while the classifiers are not bundled).
    """
    det = CycleDetector()
    # The detector only needs the last cycles: feed it about ten periods (a long test
    # would otherwise cost seconds of per-sample work for nothing).
    rises = np.flatnonzero(np.diff((seg.u > 0.5 * (seg.u.min() + seg.u.max())).astype(int)) > 0)
    period = float(np.median(np.diff(seg.t[rises]))) if rises.size > 2 else det.max_s
    keep = seg.t >= seg.t[-1] - min(0.9 * det.max_s, 10 * period)
    for ti, ui, yi in zip(seg.t[keep], seg.u[keep], seg.y[keep], strict=False):
        status = det.update(float(ti), float(ui), float(yi))
    notes = []
    steady = bool(status.steady)
    if not steady:
        notes.append(f"the oscillation is not steady ({status.cycles} cycles, period spread "
                     f"{status.spread:.0%}); results are doubtful")
    ident = None
    try:
        t, u, y = det.last_cycles(max(1, min(status.cycles, 4)))
        if t.size == 0:
            t, u, y = seg.t, seg.u, seg.y
        ident = identify(seg.loop.kind, t, u, y, beta=seg.beta, h=seg.h, bias=seg.bias,
                         inner=inner)
    except MrftError as err:
        notes.append(f"not identified: {err}")
    res = None
    use = ident.model if ident is not None else model
    if isinstance(use, InnerModel):
        kind = LoopKind.ALTITUDE if seg.loop is Loop.ALTITUDE else LoopKind.ATTITUDE
        try:
            res = analyse_residual(use, RelayTest(seg.beta, seg.h, seg.bias), seg.t, seg.u,
                                   seg.y, kind=kind, hover=hover)
        except MrftError as err:
            notes.append(f"residual not analysed: {err}")
    elif isinstance(use, SideModel):
        notes.append("residual analysis covers roll, pitch and altitude only")
    return LoopResult(seg.loop, seg, steady, ident, res, tuple(notes))


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
        Maps the identified gains to parameter values (``parameters``).
    models : dict, optional
        Known models per loop, used for residual analysis where identification fails.
    meta : dict, optional
        ``beta``, ``h``, ``bias`` overriding what is inferred (CSV metadata is read too).

    Raises
    ------
    InputFileError
        The log cannot be read.
    """
    log = read_log(path)
    info: dict[str, str] = {}
    if Path(path).suffix.lower() == ".csv" or log.loops:
        try:
            info.update(read_csv_metadata(path))
        except MrftError:
            pass
    info.update(meta or {})
    segs, why = find_relay_segments(log, info, loops)
    hover = _hover(log, profile)
    results: list[LoopResult] = []
    by_loop: dict[Loop, LoopResult] = {}
    for seg in sorted(segs, key=lambda s: s.loop.kind is LoopKind.SIDE):
        inner = None
        if seg.loop.kind is LoopKind.SIDE:
            att = by_loop.get(Loop.PITCH if seg.loop is Loop.X else Loop.ROLL)
            inner = att.identification if att else None
        r = analyse_segment(seg, inner=inner, model=(models or {}).get(seg.loop),
                            hover=hover if hover is not None else 0.5)
        results.append(r)
        by_loop[seg.loop] = r
    params: dict[str, float] = {}
    if profile is not None:
        from mrft_gcs.profiles import PDGains, gains_to_params

        gains = {r.loop: PDGains(r.identification.gains.Kc, r.identification.gains.Kd)
                 for r in results if r.identification is not None}
        if gains:
            params = gains_to_params(profile, gains, hover if hover is not None else 0.5)
    return DryRunResult(str(path), summarize_log(log), tuple(results), why, params)


def _hover(log: TelemetryLog, profile) -> float | None:
    names = ["MPC_THR_HOVER", "MOT_THST_HOVER"]
    if profile is not None:
        names.insert(0, profile.altitude.hover_thrust)
    for n in names:
        v = log.params.get(n)
        if v is not None and 0 < v < 1:
            return float(v)
    return None
