"""Steady relay cycles as waveforms: the measured average cycle and its metrics.

A relay record is cut at the relay's rising switches (low to high level); the
last complete cycles whose periods agree are averaged sample by sample, aligned
at their rising switch, into one :class:`CycleWave` with the mean removed. The
same function cuts the simulated records, so measured and simulated cycles are
compared on exactly the same footing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mrft_gcs.errors import IdentificationError

__all__ = ["CycleWave", "uniform", "rising_switches", "cycle_wave", "noise_std", "harmonics"]


@dataclass(frozen=True)
class CycleWave:
    """The average steady cycle of a relay record.

    Attributes
    ----------
    dt : float
        Sample time (s).
    y : array (N,)
        Output over one cycle from the rising switch, mean removed (output units).
    period_s, amplitude, duty : float
        Mean period (s), half peak-to-peak of ``y``, fraction of the cycle at the high level.
    cycles : int
        Cycles averaged.
    spread : float
        Relative spread (max - min) / mean of their periods.
    """

    dt: float
    y: np.ndarray
    period_s: float
    amplitude: float
    duty: float
    cycles: int
    spread: float

    @property
    def thd(self) -> float:
        """Harmonic distortion of ``y``: RMS of harmonics 2..5 over the fundamental."""
        return float(np.sqrt(np.sum(harmonics(self.y)[1:] ** 2)))


def harmonics(y: np.ndarray, k_max: int = 5) -> np.ndarray:
    """Magnitudes of harmonics 1..k_max of one period of ``y``, relative to the first."""
    c = np.abs(np.fft.rfft(y - y.mean()))[1:k_max + 1]
    return c / c[0] if c.size and c[0] > 0 else np.full(k_max, np.nan)


def uniform(t: np.ndarray, u: np.ndarray, y: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Resample ``(t, u, y)`` onto a uniform grid at the median sample time.

    ``u`` (a relay output) is held (previous sample), ``y`` interpolated linearly.
    """
    t, u, y = (np.asarray(a, dtype=float) for a in (t, u, y))
    ok = np.isfinite(t) & np.isfinite(u) & np.isfinite(y)
    t, u, y = t[ok], u[ok], y[ok]
    if t.size < 8:
        raise IdentificationError("too few samples for a relay cycle (need a few complete "
                                  "cycles of the relay test)")
    order = np.argsort(t, kind="stable")
    t, u, y = t[order], u[order], y[order]
    dt = float(np.median(np.diff(t)))
    if not dt > 0:
        raise IdentificationError("time stamps do not increase; check the log's clock")
    if np.allclose(np.diff(t), dt, rtol=0.02, atol=0):
        return dt, u, y
    grid = np.arange(t[0], t[-1] + 0.5 * dt, dt)
    idx = np.clip(np.searchsorted(t, grid, side="right") - 1, 0, t.size - 1)
    return dt, u[idx], np.interp(grid, t, y)


def rising_switches(u: np.ndarray) -> np.ndarray:
    """Sample indices where ``u`` goes from its low to its high level."""
    lo, hi = float(np.min(u)), float(np.max(u))
    if not hi > lo:
        return np.empty(0, dtype=np.int64)
    high = u > 0.5 * (lo + hi)
    return np.flatnonzero(~high[:-1] & high[1:]) + 1


def cycle_wave(u: np.ndarray, y: np.ndarray, dt: float, max_cycles: int = 6,
               tol: float = 0.1) -> CycleWave | None:
    """Average of the last steady cycles of one record, or ``None`` if there is no full cycle.

    Cycles whose period is more than ``tol`` (relative) from the last one's are
    left out, and so is everything before them (the transient).
    """
    r = rising_switches(u)
    if r.size < 2:
        return None
    periods = np.diff(r)
    last = periods[-1]
    keep = 1
    while (keep < min(max_cycles, periods.size)
           and abs(periods[-keep - 1] - last) <= tol * last):
        keep += 1
    starts, lengths = r[-keep - 1:-1], periods[-keep:]
    n = int(lengths.min())
    seg = np.stack([y[s:s + n] for s in starts])
    hi = u > 0.5 * (u.min() + u.max())
    wave = seg.mean(axis=0)
    wave = wave - wave.mean()
    duty = float(np.mean([hi[s:s + m].mean() for s, m in zip(starts, lengths, strict=False)]))
    p = lengths * dt
    return CycleWave(dt=dt, y=wave, period_s=float(p.mean()),
                     amplitude=float(0.5 * np.ptp(wave)), duty=duty, cycles=int(keep),
                     spread=float(np.ptp(p) / p.mean()))


def noise_std(y: np.ndarray) -> float:
    """Robust estimate of white measurement noise from second differences (output units)."""
    d2 = np.diff(np.asarray(y, dtype=float), 2)
    if d2.size < 4:
        return 0.0
    mad = float(np.median(np.abs(d2 - np.median(d2))))
    return mad / 0.6745 / np.sqrt(6.0)
