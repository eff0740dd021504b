"""Per-loop cycle watching: when a relay loop's cycles are steady, and which to identify.

One :class:`CycleWatcher` per relay loop, fed one sample per telemetry sample its relay
answered. It wraps :class:`~mrft_gcs.identify.CycleDetector` with the rules of a tune
(:class:`CycleRules`, from :meth:`mrft_gcs.flight.config.SequenceConfig.cycle_rules`):

- the period tolerance widens to ``sample_intervals`` mean telemetry intervals over the
  last period when that is more (a switch is seen on a telemetry sample, so a short
  period is known only to about one interval either way);
- from ``relax_after`` cycles on, periods and amplitudes may spread by ``relaxed_tol``
  (a relay kicked now and then by a late ground-station tick may never give cycles
  within the strict tolerances);
- once steady, :meth:`CycleWatcher.cycles` hands over the last ``identify_cycles``
  cycles.

The live sequence (:class:`mrft_gcs.flight.sequence.TuningSequence`) and the log replay
(:func:`mrft_gcs.dryrun.dry_run`) both run this code, so a replay sees the verdicts a
live tune saw.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mrft_gcs.identify import CycleDetector, CycleStatus

__all__ = ["CycleRules", "CycleWatcher", "Cycles", "MIN_CYCLE_SAMPLES"]

#: (t_s, u, y) of whole relay cycles, arrays of shape (m,)
Cycles = tuple[np.ndarray, np.ndarray, np.ndarray]
#: fewer samples than this over the cycles handed over are too few to identify
MIN_CYCLE_SAMPLES = 8


def _no_cycle() -> CycleStatus:
    return CycleStatus(0, False, math.nan, math.nan, math.inf)


@dataclass(frozen=True)
class CycleRules:
    """When one loop's relay cycles count as steady, and how many are identified.

    Attributes
    ----------
    n_periods : int
        Periods (and amplitudes) that must agree.
    identify_cycles : int
        Cycles handed to identification once steady.
    period_tol, amplitude_tol : float
        Relative spread allowed among them.
    relax_after : int or None
        From this many complete cycles on, the tolerances are at least ``relaxed_tol``
        (period, amplitude); None: never.
    relaxed_tol : tuple of float
    sample_intervals : float
        The period tolerance is at least this many mean telemetry intervals over the last
        period.
    """

    n_periods: int = 3
    identify_cycles: int = 4
    period_tol: float = 0.05
    amplitude_tol: float = 0.08
    relax_after: int | None = None
    relaxed_tol: tuple[float, float] = (0.08, 0.16)
    sample_intervals: float = 2.5


class CycleWatcher:
    """Streams one relay loop's (t, u, y) and says when its cycles are steady.

    Parameters
    ----------
    rules : CycleRules

    Attributes
    ----------
    status : CycleStatus
        What the detector has seen since the last restart.
    rose : bool
        The last sample was a rising relay switch: a cycle boundary, the only place
        where the verdict changes.
    dt_s : float
        Mean telemetry interval (s; NaN until a period is known).

    Examples
    --------
    >>> w = CycleWatcher(CycleRules(n_periods=2, identify_cycles=2))
    >>> for k in range(300):  # a 0.2 s relay cycle, 4 ms samples
    ...     _ = w.update(0.004 * k, 1.0 if k % 50 < 25 else -1.0, math.sin(2 * math.pi * k / 50))
    >>> w.steady, round(w.status.period_s, 3)
    (True, 0.2)
    >>> t, u, y = w.cycles()
    >>> round(float(t[-1] - t[0]), 3)  # two cycles
    0.4
    """

    def __init__(self, rules: CycleRules) -> None:
        self.rules = rules
        self.detector = CycleDetector(n_periods=rules.n_periods, period_tol=rules.period_tol,
                                      amplitude_tol=rules.amplitude_tol,
                                      relax_after=rules.relax_after,
                                      relaxed_tol=rules.relaxed_tol)
        self.reset()

    def reset(self) -> None:
        """Forget everything, the telemetry interval included."""
        self.dt_s = math.nan
        self.restart()

    def restart(self) -> None:
        """Forget the cycles seen so far (the relay starts over); the telemetry interval
        is kept, the link's rate has not changed."""
        self.detector.reset()
        self.status = _no_cycle()
        self.rose = False

    def update(self, t_s: float, u: float, y: float) -> CycleStatus:
        """Add one telemetry sample: time (s), relay output and measured output."""
        det, per = self.detector, self.status.period_s
        last = det.rises[-1] if det.rises else None
        if det.t and math.isfinite(per) and per > 0:
            dt = t_s - det.t[-1]
            self.dt_s = dt if not math.isfinite(self.dt_s) else 0.99 * self.dt_s + 0.01 * dt
            det.period_tol = max(self.rules.period_tol,
                                 self.rules.sample_intervals * self.dt_s / per)
        self.status = det.update(t_s, u, y)
        self.rose = bool(det.rises) and det.rises[-1] != last
        return self.status

    @property
    def steady(self) -> bool:
        """The last ``n_periods`` periods and amplitudes agree."""
        return self.status.steady

    def last_cycles(self, n: int) -> Cycles:
        """``(t, u, y)`` of the last ``n`` complete cycles (empty arrays if fewer)."""
        return self.detector.last_cycles(n)

    def cycles(self) -> Cycles | None:
        """The last ``identify_cycles`` cycles, the ones to identify; None if too few
        samples (whether they are steady is :attr:`steady`)."""
        t, u, y = self.detector.last_cycles(self.rules.identify_cycles)
        return None if t.size < MIN_CYCLE_SAMPLES else (t, u, y)
