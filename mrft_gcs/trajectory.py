"""Minimum-snap periodic trajectories, and the figure-eight of the paper's benchmark.

A closed path through waypoints ``w_0 .. w_{N-1}`` visited at fixed times is built from
``N`` polynomial segments of degree 7 (local time ``tau`` in ``[0, h_i]``,
``p_i(tau) = sum_j c_ij tau^j``) that minimise the snap integral over one period::

    J = sum_i int_0^{h_i} |p_i''''(tau)|^2 dtau

subject to ``p_i(0) = w_i``, ``p_i(h_i) = w_{i+1 mod N}`` and continuity of the
derivatives 1..``continuity`` at every junction, the last segment joining the first
(periodic). This is the equality-constrained QP of Mellinger & Kumar (2011) and Richter et al.
(2016), solved exactly through its KKT system. Only continuity up to jerk (3) is needed for
``J`` to be finite; the optimality conditions then make derivatives 4..6 continuous too (the
minimiser is the periodic interpolating spline of degree 7, the classical variational result
for ``int (f'''')^2``), which :func:`continuity_gaps` lets tests check.

:func:`figure_eight` samples the lemniscate of Gerono at ``N`` equal time steps, runs the QP
and scales the result to exactly ``W x H`` (the QP is linear in the waypoints, so a scaled
solution is the solution for scaled waypoints). :func:`ramp_in` time-warps a path so that it
starts from rest at ``p(0)``, for flying it from a hover.

Axes are those of the waypoints (for the figure-eight: ``x`` along ``W``, ``y`` along ``H``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mrft_gcs.errors import UsageError

__all__ = [
    "PiecewisePoly",
    "TrajectorySample",
    "min_snap_periodic",
    "evaluate",
    "sample",
    "snap_cost",
    "continuity_gaps",
    "figure_eight",
    "ramp_in",
]

DEGREE = 7
_NC = DEGREE + 1  # coefficients per segment and axis


@dataclass(frozen=True)
class PiecewisePoly:
    """A closed periodic path of degree-7 segments.

    Attributes
    ----------
    breaks_s : array (N + 1,)
        Segment start times, ``breaks_s[0] = 0``, ``breaks_s[-1]`` = period (s).
    coeffs : array (N, 8, d)
        Ascending-power coefficients in each segment's local time (s), per axis (m).
    waypoints_m : array (N, d)
        The points the path passes through at ``breaks_s[:-1]``.
    """

    breaks_s: np.ndarray
    coeffs: np.ndarray
    waypoints_m: np.ndarray

    @property
    def period_s(self) -> float:
        return float(self.breaks_s[-1])

    @property
    def n_segments(self) -> int:
        return int(self.coeffs.shape[0])

    @property
    def dim(self) -> int:
        return int(self.coeffs.shape[2])


@dataclass(frozen=True)
class TrajectorySample:
    """A path sampled at times ``t_s`` (shape ``(n,)``); every other array is ``(n, d)``."""

    t_s: np.ndarray
    pos_m: np.ndarray
    vel_m_s: np.ndarray
    acc_m_s2: np.ndarray
    jerk_m_s3: np.ndarray
    snap_m_s4: np.ndarray


def _falling(j: int, k: int) -> float:
    """j! / (j - k)! (0 when k > j)."""
    return float(math.perm(j, k)) if k <= j else 0.0


def _row(h: float, k: int) -> np.ndarray:
    """Row vector r with r . c = p^(k)(h) for one segment's coefficients c."""
    return np.array([_falling(j, k) * h ** (j - k) if j >= k else 0.0 for j in range(_NC)])


def _snap_gram(h: float) -> np.ndarray:
    """Q with c^T Q c = int_0^h (p'''')^2 for one segment."""
    q = np.zeros((_NC, _NC))
    for i in range(4, _NC):
        for j in range(4, _NC):
            p = i + j - 7
            q[i, j] = _falling(i, 4) * _falling(j, 4) * h**p / p
    return q


def min_snap_periodic(waypoints_m: np.ndarray, period_s: float,
                      segment_s: np.ndarray | None = None, continuity: int = 4) -> PiecewisePoly:
    """The closed minimum-snap path through ``waypoints_m`` (KKT solution of the QP).

    Parameters
    ----------
    waypoints_m : array (N, d)
        Points visited in order; the path returns to the first after the last. N >= 2.
    period_s : float
        Time of one closed lap (s).
    segment_s : array (N,), optional
        Time of each segment (s), scaled to sum to ``period_s``; equal times by default.
    continuity : int
        Highest derivative forced continuous at junctions, 3 to 6. The optimum is C^6 whatever
        the value (see module docstring); 4 keeps the snap reference continuous by construction.

    Raises
    ------
    UsageError
        Fewer than 2 waypoints, non-finite values, non-positive times.

    Examples
    --------
    >>> pp = min_snap_periodic(np.array([[0.0], [1.0]]), 2.0)
    >>> round(float(evaluate(pp, np.array([0.5]))[0, 0]), 9)  # halfway up, by symmetry
    0.5
    """
    w = np.asarray(waypoints_m, dtype=float)
    if w.ndim == 1:
        w = w[:, None]
    n, d = w.shape
    if n < 2 or not np.all(np.isfinite(w)):
        raise UsageError("a closed path needs at least 2 finite waypoints")
    if not (math.isfinite(period_s) and period_s > 0):
        raise UsageError(f"period must be positive, got {period_s} s")
    if not 3 <= continuity <= 6:
        raise UsageError(f"continuity must be 3 to 6 (derivatives), got {continuity}")
    h = np.full(n, period_s / n) if segment_s is None else np.asarray(segment_s, dtype=float)
    if h.shape != (n,) or not np.all(h > 0):
        raise UsageError("segment times: one positive value per waypoint")
    h = h * (period_s / h.sum())

    nv = n * _NC
    rows: list[np.ndarray] = []
    rhs: list[np.ndarray] = []
    for i in range(n):
        j = (i + 1) % n
        for tau, target in ((0.0, w[i]), (h[i], w[j])):
            r = np.zeros(nv)
            r[i * _NC:(i + 1) * _NC] = _row(tau, 0)
            rows.append(r)
            rhs.append(target)
        for k in range(1, continuity + 1):
            r = np.zeros(nv)
            r[i * _NC:(i + 1) * _NC] = _row(h[i], k)
            r[j * _NC:(j + 1) * _NC] -= _row(0.0, k)
            rows.append(r)
            rhs.append(np.zeros(d))
    A, b = np.array(rows), np.array(rhs)
    Q = np.zeros((nv, nv))
    for i in range(n):
        Q[i * _NC:(i + 1) * _NC, i * _NC:(i + 1) * _NC] = _snap_gram(h[i])
    m = A.shape[0]
    kkt = np.block([[2 * Q, A.T], [A, np.zeros((m, m))]])
    sol = np.linalg.lstsq(kkt, np.vstack([np.zeros((nv, d)), b]), rcond=None)[0]
    coeffs = sol[:nv].reshape(n, _NC, d)
    breaks = np.concatenate([[0.0], np.cumsum(h)])
    breaks[-1] = period_s
    return PiecewisePoly(breaks_s=breaks, coeffs=coeffs, waypoints_m=w.copy())


def evaluate(pp: PiecewisePoly, t_s: np.ndarray, order: int = 0) -> np.ndarray:
    """The ``order``-th time derivative at times ``t_s`` (any real, wrapped by the period).

    Returns an array ``(n, d)`` (m, m/s, m/s^2, ...).
    """
    t = np.mod(np.atleast_1d(np.asarray(t_s, dtype=float)), pp.period_s)
    seg = np.clip(np.searchsorted(pp.breaks_s, t, side="right") - 1, 0, pp.n_segments - 1)
    tau = t - pp.breaks_s[seg]
    out = np.zeros((len(t), pp.dim))
    for j in range(order, _NC):
        out += (_falling(j, order) * tau ** (j - order))[:, None] * pp.coeffs[seg, j, :]
    return out


def sample(pp: PiecewisePoly, t_s: np.ndarray) -> TrajectorySample:
    """Position, velocity, acceleration, jerk and snap at times ``t_s`` (s)."""
    t = np.atleast_1d(np.asarray(t_s, dtype=float))
    return TrajectorySample(t, *(evaluate(pp, t, k) for k in range(5)))


def snap_cost(pp: PiecewisePoly) -> float:
    """``int_0^T |p''''|^2 dt`` over one lap, summed over axes (m^2/s^7), exact."""
    h = np.diff(pp.breaks_s)
    return float(sum(np.einsum("jd,jk,kd->", pp.coeffs[i], _snap_gram(h[i]), pp.coeffs[i])
                     for i in range(pp.n_segments)))


def continuity_gaps(pp: PiecewisePoly, max_order: int = 6) -> np.ndarray:
    """Largest jump of each derivative 0..``max_order`` over all junctions (wrap included).

    Returns an array ``(max_order + 1,)``; a C^k path has entries 0..k at rounding level.
    """
    h = np.diff(pp.breaks_s)
    gaps = np.zeros(max_order + 1)
    for i in range(pp.n_segments):
        j = (i + 1) % pp.n_segments
        for k in range(max_order + 1):
            end = _row(h[i], k) @ pp.coeffs[i]
            start = _row(0.0, k) @ pp.coeffs[j]
            gaps[k] = max(gaps[k], float(np.max(np.abs(end - start))))
    return gaps


def figure_eight(size_m: tuple[float, float] = (2.0, 1.0), period_s: float = 5.5,
                 n_waypoints: int = 8) -> PiecewisePoly:
    """The minimum-snap figure-eight of ``W x H`` metres and one lap per ``period_s``.

    Waypoints are the lemniscate of Gerono ``(sin wt, sin 2wt)`` at ``n_waypoints`` equal time
    steps (a multiple of 4 keeps the extremes among them); the path starts at the centre
    crossing, heading +x then +y, and is scaled to span exactly ``W`` along x and ``H`` along y.

    Examples
    --------
    >>> pp = figure_eight((2.0, 1.0), 5.5)
    >>> p = sample(pp, np.linspace(0, 5.5, 20001)).pos_m
    >>> [round(float(np.ptp(p[:, k])), 4) for k in (0, 1)]
    [2.0, 1.0]
    """
    W, H = (float(v) for v in size_m)
    if not (W > 0 and H > 0 and math.isfinite(W) and math.isfinite(H)):
        raise UsageError(f"figure-eight size must be positive, got {W} x {H} m")
    if n_waypoints < 8 or n_waypoints % 4:
        raise UsageError(f"n_waypoints must be a multiple of 4, at least 8; got {n_waypoints}")
    phase = 2 * np.pi * np.arange(n_waypoints) / n_waypoints
    unit = min_snap_periodic(np.stack([np.sin(phase), np.sin(2 * phase)], axis=1), period_s)
    dense = evaluate(unit, np.linspace(0.0, period_s, 200_001))  # extent to ~1e-9 m
    scale = np.array([W, H]) / np.ptp(dense, axis=0)
    return PiecewisePoly(unit.breaks_s, unit.coeffs * scale, unit.waypoints_m * scale)


def _smooth_speed(u: np.ndarray, k: int) -> np.ndarray:
    """k-th derivative in u of s(u) = 35u^4 - 84u^5 + 70u^6 - 20u^7 (k = -1: its integral)."""
    c = {4: 35.0, 5: -84.0, 6: 70.0, 7: -20.0}
    out = np.zeros_like(u)
    for p, a in c.items():
        if k == -1:
            out += a * u ** (p + 1) / (p + 1)
        elif k <= p:
            out += a * _falling(p, k) * u ** (p - k)
    return out


def ramp_in(pp: PiecewisePoly, t_s: np.ndarray, lead_s: float) -> TrajectorySample:
    """The path started from rest: at rest at ``p(0)`` for ``t < 0``, then sped up smoothly.

    The path parameter ``sigma(t)`` has rate ``sigma' = s(t/lead_s)`` rising from 0 to 1 over
    ``lead_s`` seconds with zero slope, curvature and jerk at both ends (a degree-7 smooth step),
    so velocity, acceleration and jerk stay continuous; after ``lead_s`` the path runs at full
    speed, ``sigma = t - lead_s/2``. Derivatives follow by the chain rule.
    """
    if not lead_s > 0:
        raise UsageError(f"ramp-in time must be positive, got {lead_s} s")
    t = np.atleast_1d(np.asarray(t_s, dtype=float))
    u = np.clip(t / lead_s, 0.0, 1.0)
    sig = np.where(t <= lead_s, lead_s * _smooth_speed(u, -1), t - lead_s / 2)
    inside = (t > 0) & (t < lead_s)
    s1 = np.where(t <= 0, 0.0, np.where(t >= lead_s, 1.0, _smooth_speed(u, 0)))
    s2, s3, s4 = (np.where(inside, _smooth_speed(u, k) / lead_s**k, 0.0) for k in (1, 2, 3))
    p0, p1, p2, p3, p4 = (evaluate(pp, sig, k) for k in range(5))
    a, b, c, e = s1[:, None], s2[:, None], s3[:, None], s4[:, None]
    vel = p1 * a
    acc = p2 * a**2 + p1 * b
    jerk = p3 * a**3 + 3 * p2 * a * b + p1 * c
    snap = p4 * a**4 + 6 * p3 * a**2 * b + 3 * p2 * b**2 + 4 * p2 * a * c + p1 * e
    return TrajectorySample(t, p0, vel, acc, jerk, snap)
