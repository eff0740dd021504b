"""The vehicle's clock against the ground station's receive clock.

A telemetry sample carries the vehicle's time ``vt`` (``time_boot_ms``); the ground
station stamps when it received it (``rx``). ``rx - vt`` is the clocks' offset plus the
link's latency: its lower envelope (the least-delayed samples, the min filter of NTP-like
offset estimation) is the offset a sample sent at ``vt`` would show on a link with no
delay beyond its smallest. That envelope is not a constant: the two clocks drift (skew,
tens to hundreds of ppm), and a simulated vehicle whose loop falls behind real time on a
busy host *slips*: its time stops while real time goes on, and the envelope steps up by
the stall (5-20 ms at a time, several per minute on a loaded machine). A constant offset
taken once (the session's smallest ``rx - vt``) then makes every later sample look older
by the slips so far: measured ages saturate.

The model: the smallest ``rx - vt`` per bin of vehicle time (:data:`BIN_S`; bins keyed on
the vehicle's clock, so a live session and a replay of its log bin alike), split into
segments at steps of the envelope (a slip: the smallest of the next
:data:`SLIP_PERSIST_BINS` bins differs from the smallest of the last ones by over
:data:`SLIP_S`), one skew for the session (median of the bin minima's slopes within
segments), and per bin the envelope: the smallest skew-corrected minimum within
:data:`WINDOW_BINS` bins either side in its segment. :class:`ClockModel` keeps the bins
while samples arrive (live); :func:`clock_bins` builds the same from arrays (a log);
:func:`fit_clock` fits either, so live and replay measure the same.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["BIN_S", "ClockBins", "ClockFit", "ClockModel", "Slip", "clock_bins", "fit_clock"]

#: width of a bin of vehicle time (s): 125 samples at 250 Hz, enough for one least-delayed
BIN_S = 0.5
#: the envelope at a bin is the smallest within this many bins either side (same segment)
WINDOW_BINS = 4
#: a step of the envelope larger than this (s) is a slip (1000 ppm of drift over the
#: persistence below moves it 1 ms)
SLIP_S = 0.002
#: a step must hold for this many bins (a shorter rise is the link's lateness, not a slip)
SLIP_PERSIST_BINS = 2
#: the skew is the median slope over pairs of bins up to this many apart
SKEW_LAGS = 20


@dataclass(frozen=True)
class ClockBins:
    """Per bin of vehicle time, the least-delayed sample. Arrays of shape ``(n,)``.

    Attributes
    ----------
    key : int array
        ``floor(vt / BIN_S)``, increasing.
    vt_s : array
        Vehicle time of the bin's least-delayed sample (s).
    offset_s : array
        Its receive-minus-vehicle time (s).
    count : int array
        Samples in the bin.
    """

    key: np.ndarray
    vt_s: np.ndarray
    offset_s: np.ndarray
    count: np.ndarray


@dataclass(frozen=True)
class Slip:
    """A step of the envelope between vehicle times ``t0_s`` and ``t1_s`` of ``step_s``
    (positive: the vehicle's clock fell behind)."""

    t0_s: float
    t1_s: float
    step_s: float


@dataclass(frozen=True)
class ClockFit:
    """The offset between receive and vehicle clocks over a session.

    Attributes
    ----------
    knot_s, knot_offset_s : arrays (n,)
        Vehicle times (s) and the envelope there (receive minus vehicle time, s).
    knot_segment : int array (n,)
        The segment (between slips) of each knot.
    slips : tuple of Slip
    skew_ppm : float
        Drift of the receive clock against the vehicle's (ppm; NaN: too short to tell).
    spread_s : float
        Median height of the bin minima above the envelope (s): how well the least-delayed
        samples pin it.
    resolution_s : float
        The vehicle stamps' resolution: 1e-3 when every least-delayed sample sits on a
        whole millisecond (``time_boot_ms``), else 0.
    """

    knot_s: np.ndarray
    knot_offset_s: np.ndarray
    knot_segment: np.ndarray
    slips: tuple[Slip, ...]
    skew_ppm: float
    spread_s: float
    resolution_s: float

    @property
    def empty(self) -> bool:
        return not len(self.knot_s)

    def _skew(self) -> float:
        return 0.0 if math.isnan(self.skew_ppm) else self.skew_ppm * 1e-6

    def _segment_of(self, vt: np.ndarray) -> np.ndarray:
        # a sample belongs to the segment of the last knot at or before it: one between a
        # slip's two knots stays with the earlier (see Slip: it may have slipped already)
        first = np.flatnonzero(np.diff(self.knot_segment, prepend=-1) != 0)
        i = np.searchsorted(self.knot_s[first], vt, side="right") - 1
        return self.knot_segment[first[np.clip(i, 0, None)]]

    def offset_at(self, vt_s) -> np.ndarray:
        """Receive-minus-vehicle offset of the least-delayed sample stamped ``vt_s`` (s)."""
        vt = np.atleast_1d(np.asarray(vt_s, dtype=float))
        out = np.full(vt.shape, np.nan)
        if self.empty:
            return out
        seg, s = self._segment_of(vt), self._skew()
        for j in np.unique(seg):
            k = self.knot_segment == j
            x, e = self.knot_s[k], self.knot_offset_s[k]
            m = seg == j
            v = vt[m]
            # inside: between knots; outside: the end knot carried on by the skew
            out[m] = np.where(v < x[0], e[0] + s * (v - x[0]),
                              np.where(v > x[-1], e[-1] + s * (v - x[-1]), np.interp(v, x, e)))
        return out

    def to_vehicle(self, rx_s) -> np.ndarray:
        """Vehicle time of receive times ``rx_s`` (s): the inverse of ``vt + offset_at(vt)``
        (within a slip, its start)."""
        rx = np.atleast_1d(np.asarray(rx_s, dtype=float))
        if self.empty:
            return np.full(rx.shape, np.nan)
        s, far = self._skew(), 1e6
        x = np.concatenate([[self.knot_s[0] - far], self.knot_s, [self.knot_s[-1] + far]])
        e = np.concatenate([[self.knot_offset_s[0] - s * far], self.knot_offset_s,
                            [self.knot_offset_s[-1] + s * far]])
        r = np.maximum.accumulate(x + e)  # a step down of the envelope: the later wins
        return np.interp(rx, r, x)

    def slips_between(self, t0_s: float, t1_s: float) -> tuple[Slip, ...]:
        """The slips that may have happened between vehicle times ``t0_s`` and ``t1_s``."""
        return tuple(sl for sl in self.slips if sl.t0_s < t1_s and sl.t1_s > t0_s)


def clock_bins(rx_s, vt_s, bin_s: float = BIN_S) -> ClockBins:
    """Bins of a log's samples (receive times ``rx_s``, vehicle times ``vt_s``, s, in the
    order received): what :class:`ClockModel` holds after the same updates.

    >>> b = clock_bins([10.0, 10.1, 10.9], [0.0, 0.1, 0.6])
    >>> b.key.tolist(), b.offset_s.tolist(), b.count.tolist()
    ([0, 1], [10.0, 10.3], [2, 1])
    """
    rx = np.asarray(rx_s, dtype=float)
    vt = np.asarray(vt_s, dtype=float)
    ok = np.isfinite(rx) & np.isfinite(vt)
    rx, vt = rx[ok], vt[ok]
    if not len(vt):
        e = np.empty(0)
        return ClockBins(np.empty(0, dtype=np.int64), e, e, np.empty(0, dtype=np.int64))
    key = np.floor(vt / bin_s).astype(np.int64)
    d = rx - vt
    order = np.lexsort((np.arange(len(d)), d, key))  # per key: smallest, first received
    k = key[order]
    first = np.flatnonzero(np.diff(k, prepend=k[0] - 1) != 0)
    pick = order[first]
    count = np.diff(np.append(first, len(k)))
    return ClockBins(key[pick], vt[pick], d[pick], count.astype(np.int64))


def _slips(key: np.ndarray, x: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, list[Slip]]:
    """Segment index per bin and the slips between segments."""
    h = SLIP_PERSIST_BINS
    seg = np.zeros(len(m), dtype=np.int64)
    slips: list[Slip] = []
    start = 0
    for k in range(1, len(m) - h + 1):
        if k - start < 1:
            continue
        left = m[max(start, k - h):k].min()
        right = m[k:k + h].min()
        if abs(right - left) > SLIP_S:
            slips.append(Slip(float(x[k - 1]), float(x[k]), float(right - left)))
            start = k
        seg[k] = len(slips)
    seg[max(1, len(m) - h + 1):] = len(slips)
    return seg, slips


def _skew(x: np.ndarray, m: np.ndarray, seg: np.ndarray) -> float:
    """Median slope of the bin minima over pairs up to :data:`SKEW_LAGS` apart (s/s)."""
    slopes = []
    for lag in range(1, min(SKEW_LAGS, len(m) - 1) + 1):
        same = seg[lag:] == seg[:-lag]
        dx = x[lag:] - x[:-lag]
        ok = same & (dx > 0)
        slopes.append((m[lag:] - m[:-lag])[ok] / dx[ok])
    s = np.concatenate(slopes) if slopes else np.empty(0)
    return float(np.median(s)) if len(s) else math.nan


def fit_clock(bins: ClockBins) -> ClockFit:
    """Fit the envelope, its slips and skew to ``bins`` (see the module notes).

    >>> vt = np.arange(0.0, 20.0, 0.004)
    >>> rx = 100.0 + vt * (1 + 200e-6) + 0.015 * (vt > 10.2)  # 200 ppm, a 15 ms slip
    >>> fit = fit_clock(clock_bins(rx, vt))
    >>> round(fit.skew_ppm), [round(s.step_s, 3) for s in fit.slips]
    (200, [0.015])
    >>> float(np.round(fit.offset_at(15.0)[0] - 100.0, 4))  # 0.015 + 15 s * 200 ppm
    0.018
    """
    key, x, m = bins.key, bins.vt_s, bins.offset_s
    if not len(key):
        e = np.empty(0)
        return ClockFit(e, e, np.empty(0, dtype=np.int64), (), math.nan, math.nan, 0.0)
    seg, slips = _slips(key, x, m)
    skew = _skew(x, m, seg)
    s = 0.0 if math.isnan(skew) else skew
    r = m - s * x
    env = np.empty(len(m))
    for k in range(len(m)):
        lo, hi = max(0, k - WINDOW_BINS), min(len(m), k + WINDOW_BINS + 1)
        same = seg[lo:hi] == seg[k]
        env[k] = r[lo:hi][same].min() + s * x[k]
    ms = x * 1e3
    resolution = 1e-3 if np.all(np.abs(ms - np.round(ms)) < 1e-6) else 0.0
    return ClockFit(x.copy(), env, seg, tuple(slips),
                    skew * 1e6 if not math.isnan(skew) else math.nan,
                    float(np.median(m - env)), resolution)


class ClockModel:
    """The bins of :func:`clock_bins`, kept while samples arrive (one ``update`` per
    ATTITUDE / LOCAL_POSITION_NED, from the link's reader thread); :meth:`fit` at any time.

    >>> c = ClockModel()
    >>> for i in range(2000):
    ...     c.update(50.0 + i * 0.004 + (0.0003 if i % 3 else 0.0), i * 0.004)
    >>> round(c.offset_s, 6), len(c.fit().slips)
    (50.0, 0)
    """

    def __init__(self, bin_s: float = BIN_S) -> None:
        self.bin_s = bin_s
        self.reset()

    def reset(self) -> None:
        """Forget every sample (a new session, or the vehicle rebooted)."""
        # key: (offset, vt, count), replaced whole so that a reader never sees half an update
        self._bins: dict[int, tuple[float, float, int]] = {}
        self._last_vt = -math.inf

    def update(self, rx_s: float, vt_s: float) -> None:
        """One sample: received at ``rx_s`` (s, the ground station's clock), stamped ``vt_s``
        by the vehicle (s). Vehicle time going back over a second (a reboot) resets."""
        if not (math.isfinite(rx_s) and math.isfinite(vt_s)):
            return
        if vt_s < self._last_vt - 1.0:
            self.reset()
        self._last_vt = max(self._last_vt, vt_s)
        k = math.floor(vt_s / self.bin_s)
        d = rx_s - vt_s
        b = self._bins.get(k)
        if b is None:
            self._bins[k] = (d, vt_s, 1)
        elif d < b[0]:
            self._bins[k] = (d, vt_s, b[2] + 1)
        else:
            self._bins[k] = (b[0], b[1], b[2] + 1)

    @property
    def offset_s(self) -> float:
        """The envelope now: the smallest offset over the last :data:`WINDOW_BINS` bins (s;
        NaN before the first sample)."""
        keys = sorted(dict(self._bins))[-WINDOW_BINS:]
        return min((self._bins[k][0] for k in keys), default=math.nan)

    def bins(self) -> ClockBins:
        """The bins so far (a copy: safe while updates go on in another thread)."""
        snap = sorted((k, v[1], v[0], v[2]) for k, v in dict(self._bins).items())
        if not snap:
            return clock_bins([], [])
        key, vt, off, n = map(np.asarray, zip(*snap, strict=True))
        return ClockBins(key.astype(np.int64), vt.astype(float), off.astype(float),
                         n.astype(np.int64))

    def fit(self) -> ClockFit:
        """:func:`fit_clock` of the bins so far."""
        return fit_clock(self.bins())
