"""The streaming cycle detector: says when a relay loop's oscillation is steady."""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

__all__ = ["CycleDetector", "CycleStatus"]

#: Two relay levels closer than this (relative) are one: a relay output read back from a
#: log (float32, or recovered by inverting a controller) wobbles at ~1e-7 before it switches.
_LEVEL_SPLIT = 1e-4


@dataclass(frozen=True)
class CycleStatus:
    """What the cycle detector has seen so far.

    Attributes
    ----------
    cycles : int
        Complete relay cycles seen (rising switch to rising switch).
    steady : bool
        The last ``n_periods`` periods and amplitudes agree within tolerance.
    period_s, amplitude : float
        Of the last complete cycle (NaN before the first one).
    spread : float
        Relative spread of the last periods (steadiness measure).
    """

    cycles: int
    steady: bool
    period_s: float
    amplitude: float
    spread: float


class CycleDetector:
    """Watches a relay loop sample by sample and says when its oscillation is steady.

    Parameters
    ----------
    n_periods : int
        Periods that must agree (default 3).
    period_tol, amplitude_tol : float
        Relative spread allowed among them (default 3 % and 8 %).
    max_s : float
        Seconds of history kept.
    relax_after : int, optional
        From this many complete cycles on, the tolerances are widened to
        ``relaxed_tol`` (period, amplitude; each at least the strict one). A relay
        kicked every cycle or two (a ground station whose ticks come late now and then
        holds a switch for a tick) may never give three cycles within the strict
        tolerances; after ``relax_after`` cycles the detector accepts a wider spread
        instead of waiting on. None (default): never.

    Cycles are delimited by the relay output's rising switches; the relay's two
    levels are learnt from the data, so bias and amplitude need not be given.
    """

    def __init__(self, n_periods: int = 3, period_tol: float = 0.03, amplitude_tol: float = 0.08,
                 max_s: float = 30.0, relax_after: int | None = None,
                 relaxed_tol: tuple[float, float] = (0.08, 0.16)) -> None:
        self.n_periods, self.period_tol, self.amplitude_tol = n_periods, period_tol, amplitude_tol
        self.max_s = max_s
        self.relax_after, self.relaxed_tol = relax_after, relaxed_tol
        self.reset()

    def tolerances(self, cycles: int) -> tuple[float, float]:
        """(period, amplitude) tolerances in force once ``cycles`` cycles are complete."""
        if self.relax_after is not None and cycles >= self.relax_after:
            return (max(self.period_tol, self.relaxed_tol[0]),
                    max(self.amplitude_tol, self.relaxed_tol[1]))
        return self.period_tol, self.amplitude_tol

    def reset(self) -> None:
        self.t: deque[float] = deque()
        self.u: deque[float] = deque()
        self.y: deque[float] = deque()
        self.rises: deque[int] = deque()  # absolute sample numbers of rising switches
        self.rise_t: deque[float] = deque(maxlen=64)  # their times (status() reads only these)
        self.k0 = 0  # absolute sample number of self.t[0]
        self.k = 0
        self.lo = np.inf
        self.hi = -np.inf
        self.prev_high: bool | None = None
        self.cyc_lo, self.cyc_hi = np.inf, -np.inf  # extremes of y since the last rising switch
        self._cached: CycleStatus | None = None
        self.amps: deque[float] = deque(maxlen=self.n_periods)

    def update(self, t_s: float, u: float, y: float) -> CycleStatus:
        """Add one sample; returns the current status."""
        if not (math.isfinite(t_s) and math.isfinite(u) and math.isfinite(y)):
            return self.status()
        self.t.append(t_s)
        self.u.append(u)
        self.y.append(y)
        self.lo, self.hi = min(self.lo, u), max(self.hi, u)
        if self.hi - self.lo > _LEVEL_SPLIT * max(abs(self.hi), abs(self.lo)):
            high = bool(u > 0.5 * (self.lo + self.hi))  # a numpy bool is never `is False`
            if self.prev_high is False and high:
                self._cached = None
                self.rises.append(self.k)
                self.rise_t.append(t_s)
                if len(self.rises) >= 2 and self.cyc_hi > self.cyc_lo:
                    self.amps.append(0.5 * (self.cyc_hi - self.cyc_lo))
                self.cyc_lo, self.cyc_hi = np.inf, -np.inf
            self.prev_high = high
        self.cyc_lo, self.cyc_hi = min(self.cyc_lo, y), max(self.cyc_hi, y)
        self.k += 1
        while self.t and self.t[-1] - self.t[0] > self.max_s:
            self.t.popleft()
            self.u.popleft()
            self.y.popleft()
            self.k0 += 1
        while self.rises and self.rises[0] < self.k0:
            self.rises.popleft()
        return self.status()

    def _periods(self) -> np.ndarray:
        return np.diff(np.fromiter(self.rise_t, float)) if len(self.rise_t) >= 2 else np.empty(0)

    def status(self) -> CycleStatus:
        """Current status; recomputed only when a new cycle has completed."""
        if self._cached is None:
            self._cached = self._status()
        return self._cached

    def _status(self) -> CycleStatus:
        all_periods = self._periods()
        periods = all_periods[-self.n_periods:]
        n = len(periods)
        if n == 0:
            return CycleStatus(0, False, np.nan, np.nan, np.inf)
        spread = float(np.ptp(periods) / periods.mean()) if n > 1 else np.inf
        amps = np.asarray(self.amps)
        aspread = float(np.ptp(amps) / amps.mean()) if len(amps) > 1 and amps.mean() > 0 else np.inf
        tol_p, tol_a = self.tolerances(len(all_periods))
        steady = (n >= self.n_periods and spread <= tol_p
                  and len(amps) >= self.n_periods and aspread <= tol_a)
        return CycleStatus(len(all_periods), steady, float(periods[-1]),
                           float(amps[-1]) if len(amps) else np.nan, spread)

    def last_cycles(self, n: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(t, u, y)`` of the last ``n`` complete cycles (empty arrays if fewer exist)."""
        if len(self.rises) < n + 1:
            return np.empty(0), np.empty(0), np.empty(0)
        a, b = self.rises[-n - 1] - self.k0, self.rises[-1] - self.k0
        t, u, y = (np.asarray(list(d)[a:b + 1]) for d in (self.t, self.u, self.y))
        return t, u, y
