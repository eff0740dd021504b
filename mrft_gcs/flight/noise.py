"""Measurement noise of the tuned signals, for the relays' noise bands.

The classifiers were trained on relay cycles simulated with white measurement
noise of standard deviation ``sigma`` and a relay noise band of ``4 sigma``
(:mod:`mrft_gcs.dataset`). The live relays are therefore given the same band,
``4 sigma`` of each signal as measured before the test: on the ground (motors
idle or spinning up), where the vehicle does not move, each signal's samples
are detrended (least-squares line per signal, so a slow drift or the start of
the lift-off does not count as noise) and their standard deviation taken.

:class:`NoiseEstimator` is streaming: ``reset()``, ``update(t_s, values)`` with
one sample per telemetry message, ``sigma()`` per signal.
"""

from __future__ import annotations

from collections import deque

import numpy as np

__all__ = ["NoiseEstimator", "detrended_std"]


def detrended_std(t_s: np.ndarray, y: np.ndarray) -> float:
    """Standard deviation of ``y`` about its least-squares line in ``t_s`` (NaN if < 8 samples).

    >>> t = np.arange(100) * 0.004
    >>> round(detrended_std(t, 3.0 * t + np.where(np.arange(100) % 2, 0.01, -0.01)), 3)
    0.01
    """
    t, y = np.asarray(t_s, float), np.asarray(y, float)
    if t.size < 8 or np.ptp(t) <= 0:
        return float("nan")
    A = np.column_stack([t - t.mean(), np.ones_like(t)])
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    return float(np.std(y - A @ coef, ddof=2))


class NoiseEstimator:
    """Noise of ``n`` signals from their last ``max_samples`` samples.

    Parameters
    ----------
    n : int
        Number of signals.
    max_samples : int
        Window (samples); 250 is one second of 250 Hz telemetry.
    """

    def __init__(self, n: int, max_samples: int = 250) -> None:
        self.n = n
        self.max_samples = max_samples
        self.reset()

    def reset(self) -> None:
        self.t: deque[float] = deque(maxlen=self.max_samples)
        self.v: deque[tuple[float, ...]] = deque(maxlen=self.max_samples)

    def update(self, t_s: float, values: tuple[float, ...]) -> None:
        """Add one sample (``values``: one per signal); repeated or non-finite ones are dropped."""
        if self.t and t_s <= self.t[-1]:
            return
        if not (np.isfinite(t_s) and all(np.isfinite(values))):
            return
        self.t.append(t_s)
        self.v.append(tuple(values))

    @property
    def samples(self) -> int:
        return len(self.t)

    def sigma(self) -> np.ndarray:
        """Detrended standard deviation per signal, shape (n,); NaN with fewer than 8 samples."""
        if len(self.t) < 8:
            return np.full(self.n, np.nan)
        t = np.asarray(self.t)
        v = np.asarray(self.v)
        return np.array([detrended_std(t, v[:, i]) for i in range(self.n)])
