"""Classifier input representation, shared by dataset generation and runtime identification.

The paper feeds the network one steady cycle resampled at 1 ms and
zero-padded to the slowest process. Here the cycle is instead resampled to a
fixed number of points *per cycle* (time-normalised), which makes the input
independent of the time scale and of the telemetry rate; the time scale itself
is recovered from the measured period (exact under the time-scale property).
The last ``n_cycles`` complete cycles are phase-aligned and averaged, which
cuts measurement noise.

Feature vector (length ``2 * N_POINTS + 2``):

- ``y`` over one cycle, minus its mean, divided by its half peak-to-peak;
- the relay output over the same cycle mapped to -1 / +1;
- the duty cycle minus 0.5 (the relay bias shows here);
- the log of the mean-to-amplitude ratio's magnitude is *not* used: the
  offset is set by the bias, already present in the duty cycle; instead the
  last entry is the skew of the waveform (mean of the cubed normalised ``y``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mrft_gcs.errors import IdentificationError

__all__ = ["N_POINTS", "CycleFeatures", "cycle_features", "rising_switches"]

#: Points per cycle in the time-normalised representation.
N_POINTS = 64


@dataclass(frozen=True)
class CycleFeatures:
    """A measured steady cycle reduced to the classifier input and its scale figures.

    Attributes
    ----------
    x : array (2 * N_POINTS + 2,)
        Classifier input.
    period_s : float
        Mean period of the cycles used.
    amplitude : float
        Half peak-to-peak of ``y`` over the averaged cycle.
    offset : float
        Mean of ``y`` over the cycle.
    duty : float
        Fraction of the cycle the relay was high.
    h, bias : float
        Relay half-difference and mid-level measured from ``u``.
    cycles : int
        Cycles averaged.
    """

    x: np.ndarray
    period_s: float
    amplitude: float
    offset: float
    duty: float
    h: float
    bias: float
    cycles: int


def rising_switches(u: np.ndarray) -> np.ndarray:
    """Sample indices where the relay output goes from its low to its high level."""
    u = np.asarray(u, float)
    mid = 0.5 * (u.max() + u.min())
    high = u > mid
    return np.flatnonzero(~high[:-1] & high[1:]) + 1


def cycle_features(t: np.ndarray, u: np.ndarray, y: np.ndarray, n_cycles: int = 2) -> CycleFeatures:
    """Features of the last ``n_cycles`` complete relay cycles of a record.

    Parameters
    ----------
    t, u, y : arrays (m,)
        Sample times (s, increasing, any rate), relay output, measured variable.
    n_cycles : int
        Complete cycles to average (fewer are used if fewer exist).

    Raises
    ------
    IdentificationError
        Fewer than one complete cycle, or too few samples per cycle.
    """
    t, u, y = (np.asarray(a, float) for a in (t, u, y))
    if not (t.size == u.size == y.size) or t.size < 8:
        raise IdentificationError("too few samples to find a relay cycle")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(u)) and np.all(np.isfinite(y))):
        raise IdentificationError("the relay record holds NaN or infinite values; drop them first")
    rises = rising_switches(u)
    if rises.size < 2:
        raise IdentificationError("no complete relay cycle in the record (need two rising switches)")
    k = min(n_cycles, rises.size - 1)
    starts, stops = rises[-k - 1:-1], rises[-k:]
    if np.min(stops - starts) < 8:
        raise IdentificationError(
            "fewer than 8 samples per relay cycle: telemetry is too slow for this loop")
    grid = (np.arange(N_POINTS) + 0.5) / N_POINTS
    ys, us = [], []
    for a, b in zip(starts, stops):
        # Switch instants are placed midway between the samples that straddle them.
        ta = 0.5 * (t[a - 1] + t[a]) if a > 0 else t[a]
        tb = 0.5 * (t[b - 1] + t[b])
        tt = ta + grid * (tb - ta)
        ys.append(np.interp(tt, t, y))
        idx = np.clip(np.searchsorted(t, tt, side="right") - 1, 0, len(t) - 1)
        us.append(u[idx])
    yc = np.mean(ys, axis=0)
    uc = np.mean(us, axis=0)
    lo, hi = u.min(), u.max()
    h = 0.5 * (hi - lo)
    bias = 0.5 * (hi + lo)
    offset = float(yc.mean())
    amp = 0.5 * float(yc.max() - yc.min())
    if not amp > 0:
        raise IdentificationError("the measured variable does not oscillate")
    yn = (yc - offset) / amp
    un = (uc - bias) / h
    duty = float(np.mean(un > 0))
    x = np.concatenate([yn, un, [duty - 0.5, float(np.mean(yn**3))]]).astype(np.float32)
    periods = np.diff(t[rises])[-k:]
    return CycleFeatures(x=x, period_s=float(periods.mean()), amplitude=amp, offset=offset,
                         duty=duty, h=float(h), bias=float(bias), cycles=int(k))
