"""Classifier input representation, shared by dataset generation and runtime identification.

The paper feeds the network one steady cycle resampled at 1 ms and
zero-padded to the slowest process. Here each cycle is instead resampled per
*half-cycle*: the relay-high half and the relay-low half are each stretched to
``N_POINTS / 2`` points. That makes the input independent of the time scale
and of the telemetry rate (the time scale is recovered from the period,
exactly, by the time-scale property) and removes most of the distortion a
relay bias causes, since each half is a step response of its own duration.
The last ``n_cycles`` complete cycles are averaged, which cuts measurement
noise (measured: with 1 % noise, class accuracy 42 % -> 50 %; with bias up to
``h/2``, 36 % -> 44 %, against whole-cycle resampling of two cycles).

Feature vector (length ``N_POINTS + 2``): ``y`` over the two halves, minus
its mean, over its half peak-to-peak; then the duty cycle minus 0.5 and the
log of the high/low duration ratio.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mrft_gcs.errors import IdentificationError, SetpointNotCrossed

__all__ = ["N_POINTS", "CycleFeatures", "cycle_features", "crosses_setpoint", "rising_switches"]

#: Points per cycle in the time-normalised representation.
N_POINTS = 64


@dataclass(frozen=True)
class CycleFeatures:
    """A measured steady cycle reduced to the classifier input and its scale figures.

    Attributes
    ----------
    x : array (N_POINTS + 2,)
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


def crosses_setpoint(e: np.ndarray, rise: int, fall: int, next_rise: int) -> bool:
    """Whether the error ``e`` crosses the set point in both halves of one relay cycle.

    ``rise``, ``fall`` and ``next_rise`` are the sample indices of the cycle's switches
    (:func:`rising_switches`): a proper MRFT cycle has a positive error during its high
    half and a negative one during its low half before each switch.
    """
    return bool(e[rise:fall].max() > 0 and e[fall:next_rise].min() < 0)


def cycle_features(t: np.ndarray, u: np.ndarray, y: np.ndarray, n_cycles: int = 4,
                   setpoint=None) -> CycleFeatures:
    """Features of the last ``n_cycles`` complete relay cycles of a record.

    Parameters
    ----------
    t, u, y : arrays (m,)
        Sample times (s, increasing, any rate), relay output, measured variable.
    n_cycles : int
        Complete cycles to average (fewer are used if fewer exist).
    setpoint : float or array (m,), optional
        The relay's set point. When given, each cycle used must be a proper MRFT
        cycle: the error crosses the set point in every half-cycle before the relay
        switches. A cycle that does not (too much relay bias for the test's phase
        lead, or noise) is not the oscillation the classifier knows and is refused.

    Raises
    ------
    IdentificationError
        Fewer than one complete (proper) cycle, or too few samples per cycle.
    """
    t, u, y = (np.asarray(a, float) for a in (t, u, y))
    if not (t.size == u.size == y.size) or t.size < 8:
        raise IdentificationError("too few samples to find a relay cycle")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(u)) and np.all(np.isfinite(y))):
        raise IdentificationError("the relay record holds NaN or infinite values; drop them first")
    rises = rising_switches(u)
    if rises.size < 2:
        raise IdentificationError("no complete relay cycle in the record (need two rising "
                                  "switches)")
    high = u > 0.5 * (u.max() + u.min())
    falls = np.flatnonzero(high[:-1] & ~high[1:]) + 1
    k = min(n_cycles, rises.size - 1)
    half = N_POINTS // 2
    grid = (np.arange(half) + 0.5) / half
    e = None if setpoint is None else np.broadcast_to(np.asarray(setpoint, float), y.shape) - y
    ys, fracs = [], []
    improper = 0
    for a, b in zip(rises[-k - 1:-1], rises[-k:], strict=True):
        f = falls[(falls > a) & (falls < b)]
        if f.size != 1 or min(f[0] - a, b - f[0]) < 3:
            continue
        if e is not None and not crosses_setpoint(e, a, f[0], b):
            improper += 1
            continue
        # Switch instants are placed midway between the samples that straddle them.
        ta, tf, tb = (0.5 * (t[i - 1] + t[i]) for i in (a, f[0], b))
        ts, ys_ = t[a - 1:b + 1], y[a - 1:b + 1]  # this cycle's samples only
        ys.append(np.concatenate([np.interp(ta + grid * (tf - ta), ts, ys_),
                                  np.interp(tf + grid * (tb - tf), ts, ys_)]))
        fracs.append((tf - ta) / (tb - ta))
    if not ys:
        if improper:
            raise SetpointNotCrossed(
                "the relay cycles do not cross the set point every half-cycle: the relay bias is "
                "too large for this test; re-centre the relay on the hover command and retry")
        raise IdentificationError(
            "no clean relay cycle (too few samples per half-cycle: telemetry too slow for this "
            "loop?)")
    yc = np.mean(ys, axis=0)
    offset = float(yc.mean())
    amp = 0.5 * float(yc.max() - yc.min())
    if not amp > 0:
        raise IdentificationError("the measured variable does not oscillate")
    duty = float(np.mean(fracs))
    x = np.concatenate([(yc - offset) / amp, [duty - 0.5, np.log(duty / (1 - duty))]])
    lo, hi = u.min(), u.max()
    periods = np.diff(t[rises])[-k:]
    return CycleFeatures(x=x.astype(np.float32), period_s=float(periods.mean()), amplitude=amp,
                         offset=offset, duty=duty, h=float(0.5 * (hi - lo)),
                         bias=float(0.5 * (hi + lo)), cycles=len(ys))
