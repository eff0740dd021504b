"""The written gains proven in the autopilot's own hold mode: hold on them, hold on the values
they replaced, keep the set that holds at least as well.

After the hand-over (the vehicle in its position mode, LOITER / POSCTL, on the written
gains) :func:`compare_holds` records a hold of ``seconds`` on the written set, writes back
the value from before the tune of every parameter the tune changed (read back), records the
same hold on them, and judges the two (:func:`judge_holds`). Where the written set holds at
least as well it is written again (read back); otherwise the old values stay and the
comparison says which figure was worse. The safety limits stay active through both holds
(a violation or telemetry silent for 0.5 s lands the vehicle, :class:`SafetyAbort`).

The figures (:func:`hold_figures`) and the verdict (:func:`worse_in`, :func:`effort_in`) are
the ones ``benchmarks/tune_ardupilot.py`` judges its LOITER holds by:

- altitude spread (max - min) and standard deviation (m), largest |climb rate| (m/s),
  largest horizontal distance from where the hold began (m);
- largest tilt and the tilt's standard deviation about its mean lean (deg);
- roll/pitch against the autopilot's own target (ATTITUDE_TARGET): paired with the latest
  target, and against the target interpolated to each ATTITUDE's vehicle time, with its part
  above ~2 Hz (both judged); how fast the target moved (deg/s rms);
- throttle saturation: the share of VFR_HUD samples at 0 % or 100 %, and the throttle's
  standard deviation (%).

A hold is worse where altitude spread, its deviation, drift or saturation grew by more than
20 % (plus :data:`WORSE_SLACK`) and by more than the figure differs between the two halves of
one hold (the scatter of the same set, large in gusts), or roll/pitch followed their target
less closely; a stiffer position loop that spends more lean to hold position is reported
(:func:`effort_in`), not failed. A figure the telemetry cannot give (NaN on either side) is
not judged.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from mrft_gcs.errors import SafetyAbort
from mrft_gcs.flight.controllers import FlightState
from mrft_gcs.flight.safety import SafetyMonitor
from mrft_gcs.link import VehicleLink
from mrft_gcs.params import ParamChange, ParamClient
from mrft_gcs.telemetry import Attitude, AttitudeSetpoint, LocalPosition, ThrottleReport

__all__ = ["HoldFigures", "HoldVerdict", "HoldComparison", "HoldRecorder", "hold_figures",
           "synced_error", "worse_in", "noise_of", "effort_in", "judge_holds", "fly_hold",
           "compare_holds",
           "WORSE_SLACK", "FIGURE_TEXT", "SETTLE_S", "STREAM_HZ"]

#: what each judged hold figure may grow by on top of 20 % before it counts as worse
WORSE_SLACK = {"alt_spread_m": 0.005, "alt_std_m": 0.005, "max_drift_m": 0.005,
               "throttle_saturated": 0.0, "att_err_sync_rms_deg": 0.01,
               "att_err_hf_rms_deg": 0.01}
#: the judged figures in words (with their unit), for the reason of a revert
FIGURE_TEXT = {"alt_spread_m": ("altitude spread", "m"), "alt_std_m": ("altitude std", "m"),
               "max_drift_m": ("position drift", "m"),
               "throttle_saturated": ("throttle saturated share", ""),
               "att_err_sync_rms_deg": ("roll/pitch error against the target", "deg rms"),
               "att_err_hf_rms_deg": ("roll/pitch error against the target above 2 Hz",
                                      "deg rms")}
#: seconds on a parameter set before its hold is recorded (the loops settle on new gains)
SETTLE_S = 1.0
#: ATTITUDE_TARGET and VFR_HUD asked at this rate during the holds (Hz; the benchmark's)
STREAM_HZ = 25.0
#: the running mean taken off the synced error for its part above ~2 Hz (s)
HF_WINDOW_S = 0.52
ATTITUDE_TARGET_ID, VFR_HUD_ID = 83, 74


@dataclass(frozen=True)
class HoldFigures:
    """One hold's figures (module docstring: definitions); NaN where telemetry lacked."""

    alt_spread_m: float
    alt_std_m: float
    max_climb_m_s: float
    max_drift_m: float
    max_tilt_deg: float
    tilt_std_deg: float
    att_err_rms_deg: float
    att_err_sync_rms_deg: float
    att_err_hf_rms_deg: float
    target_rate_rms_deg_s: float
    throttle_saturated: float
    throttle_std_pct: float
    samples: int = 0  # ATTITUDE samples in the hold
    #: per judged figure, how far the figure of the hold's first half and that of its second
    #: half differ (same unit): the scatter of one set's holds, which a difference between two
    #: sets must exceed to count (:func:`worse_in`); empty where not measured
    noise: Mapping[str, float] = field(default_factory=dict, compare=False)

    def as_dict(self) -> dict[str, float]:
        out = asdict(self)
        del out["noise"]
        return out

    def line(self) -> str:
        return (f"alt spread {self.alt_spread_m:.3f} m (std {self.alt_std_m:.3f}), drift "
                f"{self.max_drift_m:.3f} m, tilt <= {self.max_tilt_deg:.1f} deg (std "
                f"{self.tilt_std_deg:.2f}), against the target "
                f"{self.att_err_sync_rms_deg:.3f} deg rms, throttle saturated "
                f"{100 * self.throttle_saturated:.0f} %")


def synced_error(att_t: np.ndarray, tgt_t: np.ndarray) -> np.ndarray:
    """Roll/pitch minus the target interpolated to each ATTITUDE's own vehicle time (rad,
    shape (n, 2)); ATTITUDE samples outside the target's time span are left out. Pairing each
    ATTITUDE with the latest ATTITUDE_TARGET instead counts the target's motion since that
    message as error: up to one stream period of it, more the faster the target moves.

    ``att_t`` and ``tgt_t``: rows ``(t_s, roll_rad, pitch_rad)`` on the vehicle clock."""
    if len(att_t) < 2 or len(tgt_t) < 2:
        return np.zeros((0, 2))
    order = np.argsort(tgt_t[:, 0], kind="stable")
    tt, tr, tp = tgt_t[order, 0], tgt_t[order, 1], tgt_t[order, 2]
    keep = (att_t[:, 0] >= tt[0]) & (att_t[:, 0] <= tt[-1])
    t = att_t[keep, 0]
    return np.column_stack((att_t[keep, 1] - np.interp(t, tt, tr),
                            att_t[keep, 2] - np.interp(t, tt, tp)))


def _rms_deg(x: np.ndarray) -> float:
    return float(np.degrees(np.sqrt(np.mean(np.sum(x**2, axis=1))))) if len(x) else math.nan


def _none(n: int) -> np.ndarray:
    return np.zeros((0, n))


def _halves(data: Mapping[str, np.ndarray]) -> tuple[dict[str, np.ndarray], ...]:
    """The rows of the hold's first and second half (each stream cut at its middle row)."""
    return tuple({k: (v[: len(v) // 2] if i == 0 else v[len(v) // 2:]) for k, v in data.items()}
                 for i in (0, 1))


def hold_figures(data: Mapping[str, np.ndarray], noise: bool = True) -> HoldFigures:
    """The figures of one hold from its recorded rows.

    Parameters
    ----------
    data : mapping of str to array
        ``pos`` (n, 4): x, y (m, NED), height up (m), climb rate up (m/s); ``att`` (n, 2):
        roll, pitch (rad); ``thr`` (n, 1): VFR_HUD throttle (%); ``err`` (n, 2): roll/pitch
        minus the latest target (rad); ``att_t`` / ``tgt_t`` (n, 3): vehicle time (s), roll,
        pitch (rad) of ATTITUDE / ATTITUDE_TARGET. ``thr``, ``err``, ``att_t`` and ``tgt_t``
        may be empty or absent (their figures are NaN).
    noise : bool
        Also the figures of each half of the hold, and how far apart they are
        (:attr:`HoldFigures.noise`; where each half has at least 4 position and attitude rows).
    """
    pos, att = data["pos"], data["att"]
    thr, err = data.get("thr", _none(1)), data.get("err", _none(2))
    z = pos[:, 2]
    tilt = np.degrees(np.arccos(np.cos(att[:, 0]) * np.cos(att[:, 1])))
    att_t, tgt = data.get("att_t", _none(3)), data.get("tgt_t", _none(3))
    sync = synced_error(att_t, tgt)
    rate = (np.diff(tgt[:, 1:], axis=0) / np.maximum(np.diff(tgt[:, 0]), 1e-3)[:, None]
            if len(tgt) > 2 else _none(2))
    # the running mean spans HF_WINDOW_S at the ATTITUDE rate (13 samples at 25 Hz)
    dt = float(np.median(np.diff(att_t[:, 0]))) if len(att_t) > 2 else 0.04
    n = max(3, int(round(HF_WINDOW_S / max(dt, 1e-3))) | 1)
    h = n // 2
    hf = (sync - np.column_stack([np.convolve(sync[:, k], np.ones(n) / n, mode="same")
                                  for k in range(2)]))[h:-h] if len(sync) > n else sync
    return HoldFigures(
        alt_spread_m=float(z.max() - z.min()), alt_std_m=float(z.std()),
        max_climb_m_s=float(np.abs(pos[:, 3]).max()),
        max_drift_m=float(np.hypot(pos[:, 0] - pos[0, 0], pos[:, 1] - pos[0, 1]).max()),
        max_tilt_deg=float(tilt.max()),
        # the rocking about the mean lean (a steady wind leans the vehicle by degrees)
        tilt_std_deg=float(np.degrees(np.hypot(att[:, 0].std(), att[:, 1].std()))),
        # roll/pitch against ATTITUDE_TARGET: what the attitude gains alone answer for
        att_err_rms_deg=_rms_deg(err),
        att_err_sync_rms_deg=_rms_deg(sync), att_err_hf_rms_deg=_rms_deg(hf),
        target_rate_rms_deg_s=_rms_deg(rate),
        throttle_saturated=float(np.mean((thr[:, 0] <= 0) | (thr[:, 0] >= 100)))
        if len(thr) else math.nan,
        throttle_std_pct=float(thr[:, 0].std()) if len(thr) else math.nan,
        samples=len(att), noise=_noise(data) if noise else {})


def _noise(data: Mapping[str, np.ndarray]) -> dict[str, float]:
    """|first half's figure - second half's| for each judged figure both halves give."""
    if min(len(data["pos"]), len(data["att"])) < 8:
        return {}
    h1, h2 = (hold_figures(h, noise=False).as_dict() for h in _halves(data))
    return {k: abs(h1[k] - h2[k]) for k in WORSE_SLACK
            if math.isfinite(h1[k]) and math.isfinite(h2[k])}


def worse_in(before: Mapping[str, float], after: Mapping[str, float],
             noise: Mapping[str, float] | None = None) -> list[str]:
    """The hold figures that grew by more than 20 % (and :data:`WORSE_SLACK`) from
    ``before`` to ``after``, and by more than ``noise`` (figure -> the scatter of one set's
    holds in that figure's unit, e.g. :func:`noise_of`; absent: 0).

    In gusts one set's holds scatter by more than 20 %: the same gains drift 0.3 m in one
    hold and 0.5 m in the next. A figure therefore counts only where the two sets differ by
    more than the halves of one hold differ (the larger of the two holds' scatter).

    A hold is judged on how far altitude and position wander, on throttle saturation and on
    how closely roll/pitch follow their target (at the same vehicle time). A stiffer loop
    answers gusts with faster, smaller corrections, so its climb-rate peaks are reported but
    not held against it; likewise the tilt: holding position in gusts takes lean, and a
    position loop that gives way less leans more (:func:`effort_in` says so).

    The tracking error, and its part above ~2 Hz, count only where they also grew per unit
    of the target's motion (``target_rate_rms_deg_s``, where both holds have it): a stiffer
    position loop moves the target faster, and the same attitude loop then lags it by more
    degrees but no more time (reported by :func:`effort_in`, not held against the tune).
    The part above 2 Hz is judged on its own because a ringing attitude loop shows there
    while a slow error (an integrator still settling after a swap) can hide it in the total.

    >>> worse_in({"alt_spread_m": 0.08}, {"alt_spread_m": 0.11})
    ['alt_spread_m']
    >>> b = {"att_err_sync_rms_deg": 0.03, "target_rate_rms_deg_s": 1.5}
    >>> worse_in(b, {"att_err_sync_rms_deg": 0.15, "target_rate_rms_deg_s": 7.8})
    []
    >>> worse_in(b, {"att_err_sync_rms_deg": 0.15, "target_rate_rms_deg_s": 1.5})
    ['att_err_sync_rms_deg']
    >>> worse_in({"max_drift_m": 0.3}, {"max_drift_m": 0.45}, {"max_drift_m": 0.2})
    []
    """
    noise = noise or {}
    out = [k for k, slack in WORSE_SLACK.items()
           if k in before and k in after and after[k] > 1.2 * before[k] + slack
           and not after[k] - before[k] <= noise.get(k, 0.0)]
    r = "target_rate_rms_deg_s"
    rb, ra = before.get(r, math.nan), after.get(r, math.nan)
    for k in ("att_err_sync_rms_deg", "att_err_hf_rms_deg"):
        if k in out and rb > 0 and ra > 0 and not after[k] / ra > 1.2 * before[k] / rb:
            out.remove(k)
    return out


def noise_of(before: HoldFigures, after: HoldFigures) -> dict[str, float]:
    """Per judged figure, the larger of the two holds' scatter (:attr:`HoldFigures.noise`)."""
    return {k: max(before.noise.get(k, 0.0), after.noise.get(k, 0.0))
            for k in WORSE_SLACK if k in before.noise or k in after.noise}


def effort_in(before: Mapping[str, float], after: Mapping[str, float]) -> str:
    """A line on the lean spent to hold position, where it grew by more than 20 %."""
    b, a = before.get("tilt_std_deg", math.nan), after.get("tilt_std_deg", math.nan)
    if not a > 1.2 * b:
        return ""
    return (f"more lean spent holding position: tilt std {b:.2f} -> {a:.2f} deg, the target "
            f"moving {before.get('target_rate_rms_deg_s', math.nan):.1f} -> "
            f"{after.get('target_rate_rms_deg_s', math.nan):.1f} deg/s rms, drift "
            f"{before['max_drift_m']:.2f} -> {after['max_drift_m']:.2f} m")


@dataclass(frozen=True)
class HoldVerdict:
    """The written set's hold (``after``) against the old set's (``before``)."""

    worse_in: tuple[str, ...]
    #: the judged figures that both holds gave (finite on both sides)
    judged: tuple[str, ...]
    effort: str = ""
    reason: str = ""

    @property
    def kept(self) -> bool:
        return not self.worse_in


def judge_holds(before: HoldFigures, after: HoldFigures) -> HoldVerdict:
    """:func:`worse_in` and :func:`effort_in` on two holds, with the reason in words.

    >>> f = dict.fromkeys(HoldFigures.__dataclass_fields__, 0.1) | {"noise": {}}
    >>> v = judge_holds(HoldFigures(**f), HoldFigures(**dict(f, max_drift_m=0.2)))
    >>> v.kept, v.reason
    (False, 'position drift 0.100 -> 0.200 m (worse by more than 20 % + 0.005)')
    """
    b, a = before.as_dict(), after.as_dict()
    judged = tuple(k for k in WORSE_SLACK if math.isfinite(b[k]) and math.isfinite(a[k]))
    noise = noise_of(before, after)
    worse = tuple(worse_in(b, a, noise))
    parts = []
    for k in worse:
        name, unit = FIGURE_TEXT[k]
        scatter = (f" and more than the {noise[k]:.3f} the halves of one hold differ"
                   if noise.get(k, 0.0) > 0 else "")
        parts.append(f"{name} {b[k]:.3f} -> {a[k]:.3f}{' ' + unit if unit else ''} (worse by "
                     f"more than 20 % + {WORSE_SLACK[k]:g}{scatter})")
    return HoldVerdict(worse, judged, effort_in(b, a), "; ".join(parts))


@dataclass(frozen=True)
class HoldComparison:
    """What :func:`compare_holds` flew and decided (the report's ``hold_compare``)."""

    mode: str
    seconds: float
    #: the hold on the written gains, and on the values from before the tune
    after: HoldFigures
    before: HoldFigures
    verdict: HoldVerdict
    #: ``kept`` (the written set written again, read back) or ``reverted`` (old values stay)
    outcome: str
    #: the parameters set back to their old value for the hold before (name -> old, new)
    swapped: dict[str, tuple[float, float]] = field(default_factory=dict)
    load_avg_1min: float = math.nan
    #: seconds the comparison flew, settling and parameter swaps included
    duration_s: float = math.nan
    #: the swapped parameters' values on the vehicle at the end, as read back (name -> value):
    #: the written ones where kept, the old ones where reverted
    on_vehicle: dict[str, float] = field(default_factory=dict)

    def as_dict(self) -> dict[str, object]:
        def num(x: float) -> float | None:
            return x if math.isfinite(x) else None

        return {"mode": self.mode, "seconds": self.seconds, "outcome": self.outcome,
                "before": {k: num(v) for k, v in self.before.as_dict().items()},
                "after": {k: num(v) for k, v in self.after.as_dict().items()},
                "worse_in": list(self.verdict.worse_in), "judged": list(self.verdict.judged),
                "reason": self.verdict.reason or None, "effort": self.verdict.effort or None,
                "parameters": sorted(self.swapped), "load_avg_1min": num(self.load_avg_1min),
                "duration_s": num(self.duration_s),
                # the scatter each figure had to exceed (the larger of the two holds')
                "noise": {k: num(v) for k, v in noise_of(self.before, self.after).items()},
                "on_vehicle": {k: num(v) for k, v in sorted(self.on_vehicle.items())}}

    def line(self) -> str:
        head = (f"hold comparison in {self.mode}, {self.seconds:g} s each ({self.duration_s:.1f} "
                f"s in all): before the tune "
                f"{self.before.line()}; written {self.after.line()}; ")
        if self.outcome == "kept":
            tail = "the written gains hold at least as well: kept"
        else:
            tail = f"the written gains hold worse ({self.verdict.reason}): old values put back"
        return head + tail + (f"; {self.verdict.effort}" if self.verdict.effort else "")


class HoldRecorder:
    """The rows :func:`hold_figures` takes, from the link's typed events in arrival order."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.rows: dict[str, list[tuple[float, ...]]] = {
            "pos": [], "att": [], "thr": [], "err": [], "att_t": [], "tgt_t": []}
        self._target: tuple[float, float] | None = None

    def update(self, event: object) -> None:
        r = self.rows
        if isinstance(event, LocalPosition):
            r["pos"].append((event.x_m, event.y_m, -event.z_m, -event.vz_m_s))
        elif isinstance(event, AttitudeSetpoint):
            self._target = (event.roll_rad, event.pitch_rad)
            r["tgt_t"].append((event.t_s, event.roll_rad, event.pitch_rad))
        elif isinstance(event, Attitude):
            r["att"].append((event.roll_rad, event.pitch_rad))
            r["att_t"].append((event.t_s, event.roll_rad, event.pitch_rad))
            if self._target is not None:  # the attitude loop's own error, against its target
                r["err"].append((event.roll_rad - self._target[0],
                                 event.pitch_rad - self._target[1]))
        elif isinstance(event, ThrottleReport):
            r["thr"].append((event.throttle_pct,))

    def arrays(self) -> dict[str, np.ndarray]:
        width = {"pos": 4, "att": 2, "thr": 1, "err": 2, "att_t": 3, "tgt_t": 3}
        return {k: np.asarray(v, float).reshape(-1, width[k]) for k, v in self.rows.items()}


def _state(att: Attitude, pos: LocalPosition) -> FlightState:
    return FlightState(att.t_s, att.roll_rad, att.pitch_rad, att.yaw_rad, att.rollspeed_rad_s,
                       att.pitchspeed_rad_s, att.yawspeed_rad_s, pos.t_s, pos.x_m, pos.y_m,
                       -pos.z_m, pos.vx_m_s, pos.vy_m_s, -pos.vz_m_s)


def fly_hold(link: VehicleLink, seconds: float, monitor: SafetyMonitor, where: str
             ) -> HoldFigures:
    """Record ``seconds`` of the vehicle holding in the mode it is in, with the safety limits
    checked on every sample (as the hover check does): a limit or telemetry silent for 0.5 s
    commands a landing and raises :class:`SafetyAbort` naming ``where``."""
    rec = HoldRecorder()
    att: Attitude | None = None
    pos: LocalPosition | None = None
    with link.subscribe(Attitude, LocalPosition, AttitudeSetpoint, ThrottleReport) as sub:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            link.drain()  # nobody else reads the sample queue now
            if link.telemetry_age_s() > 0.5:
                link.land(wait_ack=False)
                raise SafetyAbort(f"telemetry lost in {where}; landing commanded")
            ev = sub.get(0.05)
            if ev is None:
                continue
            rec.update(ev)
            if isinstance(ev, Attitude):
                att = ev
            elif isinstance(ev, LocalPosition):
                pos = ev
            else:
                continue
            if att is not None and pos is not None:
                reason = monitor.violation(_state(att, pos), duration=False)
                if reason is not None:
                    link.land(wait_ack=False)
                    raise SafetyAbort(f"{where}: {reason}; landing commanded")
    data = rec.arrays()
    if len(data["pos"]) < 2 or len(data["att"]) < 2:
        link.land(wait_ack=False)
        raise SafetyAbort(f"{where}: no ATTITUDE and LOCAL_POSITION_NED in {seconds:g} s; "
                          f"landing commanded")
    return hold_figures(data)


def compare_holds(link: VehicleLink, changes: tuple[ParamChange, ...], seconds: float,
                  monitor: SafetyMonitor, mode: str, backup_dir: str | Path,
                  judge: Callable[[HoldFigures, HoldFigures], HoldVerdict] = judge_holds,
                  log: Callable[[str], None] | None = None) -> HoldComparison:
    """Hold on the written set, then on the values it replaced; keep the better-holding set.

    Parameters
    ----------
    link : VehicleLink
        The vehicle, in its position mode ``mode`` on the written gains.
    changes : tuple of ParamChange
        Every parameter the tune changed (``old``: before the tune, ``new``: written).
    seconds : float
        Length of each hold (s).
    monitor : SafetyMonitor
        The tune's limits (origin: the take-off point).
    backup_dir : path
        Where each swap's backup goes (``params-hold-old-*``, ``params-hold-new-*``).
    judge : callable
        ``judge(before, after) -> HoldVerdict`` (:func:`judge_holds`).

    Returns
    -------
    HoldComparison
        ``outcome`` ``kept`` (the written values are on the vehicle again, read back) or
        ``reverted`` (the old values are, read back).

    Raises
    ------
    SafetyAbort
        A limit in either hold (landing commanded; the parameters as they were then: the
        message says which set).
    ParameterError
        A swap that did not stick (rolled back by :meth:`ParamClient.write`).
    """
    swapped = {c.name: (c.old, c.new) for c in changes
               if not math.isclose(c.old, c.new, rel_tol=1e-6, abs_tol=1e-9)}
    client = ParamClient(link)
    t0 = time.monotonic()
    for rate_id in (ATTITUDE_TARGET_ID, VFR_HUD_ID):
        link.ask_message_interval(rate_id, STREAM_HZ)
    try:
        # each set gets SETTLE_S before its hold, watched like the hold itself
        fly_hold(link, SETTLE_S, monitor, f"the hold on the written gains in {mode}")
        after = fly_hold(link, seconds, monitor, f"the hold on the written gains in {mode}")
        if log:
            log(f"hold on the written gains: {after.line()}")
        old = client.write({n: o for n, (o, _) in swapped.items()}, backup_dir, label="hold-old")
        # read back: what the vehicle holds now (the written set's write below replaces it)
        on_vehicle = {c.name: c.new for c in old.changes}
        where = f"the hold on the values from before the tune in {mode} (they stay written)"
        fly_hold(link, SETTLE_S, monitor, where)
        before = fly_hold(link, seconds, monitor, where)
        if log:
            log(f"hold on the values from before: {before.line()}")
        verdict = judge(before, after)
        if verdict.kept:
            new = client.write({n: w for n, (_, w) in swapped.items()}, backup_dir,
                               label="hold-new")
            on_vehicle = {c.name: c.new for c in new.changes}
    finally:
        for rate_id in (ATTITUDE_TARGET_ID, VFR_HUD_ID):
            link.ask_message_interval(rate_id, 0.0)
    return HoldComparison(mode, seconds, after, before, verdict,
                          "kept" if verdict.kept else "reverted", swapped,
                          os.getloadavg()[0], time.monotonic() - t0, on_vehicle)
