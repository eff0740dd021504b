"""Measurement noise of the tuned signals, for the relays' noise bands.

The classifiers were trained on relay cycles simulated with white measurement
noise of standard deviation ``sigma`` and a relay noise band of ``4 sigma``
(:mod:`mrft_gcs.design.dataset`). The live relays are therefore given the same band,
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

__all__ = ["ComplementaryFilter", "NoiseEstimator", "detrended_std"]


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


class ComplementaryFilter:
    """Position smoothed with its own velocity: ``x^ += v dt + k (x - x^ - v dt)``.

    Where the position and velocity come from one estimator (LOCAL_POSITION_NED), the
    velocity carries the motion and the position only corrects the drift, so the output
    follows the motion without the phase lag of a low-pass filter while white position
    noise shrinks by ``sqrt(k / (2 - k))`` (0.16 at ``k = 0.05``). The side-motion relay
    needs this: with a 4-sigma band its cycles turn irregular once the noise exceeds
    about 1 % of the cycle amplitude.

    >>> f = ComplementaryFilter(0.05)
    >>> [round(f.update(0.004 * i, 0.01 * i, 2.5), 4) for i in range(3)]
    [0.0, 0.01, 0.02]
    """

    def __init__(self, k: float = 0.05) -> None:
        if not 0 < k <= 1:
            raise ValueError("the complementary filter gain must lie in (0, 1]")
        self.k = k
        self.reset()

    def reset(self) -> None:
        self.x: float | None = None
        self.t = float("nan")

    def update(self, t_s: float, x: float, v: float) -> float:
        """Add a sample (position, velocity at ``t_s``); returns the filtered position."""
        if self.x is None or not t_s > self.t:
            if self.x is None:
                self.x, self.t = x, t_s
            return self.x
        pred = self.x + v * (t_s - self.t)
        self.x = pred + self.k * (x - pred)
        self.t = t_s
        return self.x
