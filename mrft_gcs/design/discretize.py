"""Discretisation of the inner-loop domains into representative processes (paper section V).

Processes ``(T_prop, T1, tau)`` that differ only by a common time scale share
one *shape*: their optimal PDs, costs and MRFT cycles are time-scaled copies
of each other (time-scale property, tested in ``test_pd_design``). The
discretisation uses that in two steps, as the paper does:

1. **Shapes.** The chart ``(a, b) = (log T_prop/T1, log tau/T1)`` covers every
   shape reachable in the domain box. A fine grid of candidate shapes is made
   at unit scale (``T1 = 1``) and their optimal PDs designed. The distance
   between two shapes is their joint cost at the best relative time scale,
   ``d(s, s') = min_c max(J(s, c s'), J(c s', s))``. A greedy net picks
   representative shapes until every candidate lies within ``cover`` of one.
2. **Scales.** Along each representative shape, scales are spaced so that
   adjacent processes have joint cost ``J*`` (within the tolerance), over the
   range of scales at which the shapes it covers stay inside the box.

The representative processes are the shape x scale pairs; their count, the
adjacent joint costs and the shapes are returned in a :class:`Discretisation`.
At run time the scale is not restricted to these points: it is recovered
continuously from the measured period (see :mod:`mrft_gcs.identify`).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from scipy.optimize import brentq, minimize_scalar

from mrft_gcs.domains import Domain
from mrft_gcs.pd_design import PDDesign, ise, margins, optimal_pd
from mrft_gcs.plant import PD, inner_response

#: Joint cost (%) recorded for candidate/representative pairs too far apart to evaluate.
J_FAR = 200.0

__all__ = [
    "J_FAR",
    "Discretisation",
    "reachable_scales",
    "shape_grid",
    "design_shapes",
    "shape_distance",
    "greedy_net",
    "scale_ratio",
    "discretize_inner",
]


def reachable_scales(domain: Domain, a, b) -> tuple[np.ndarray, np.ndarray]:
    """Range ``[lo, hi]`` of ``T1`` for which shape ``(a, b)`` lies in the box.

    ``lo > hi``: no ``T1`` puts the shape in the box.
    """
    a, b = np.asarray(a, float), np.asarray(b, float)
    (tp_lo, t1_lo, tau_lo), (tp_hi, t1_hi, tau_hi) = domain.low, domain.high
    lo = np.maximum.reduce([np.full_like(a, t1_lo), tp_lo / np.exp(a), tau_lo / np.exp(b)])
    hi = np.minimum.reduce([np.full_like(a, t1_hi), tp_hi / np.exp(a), tau_hi / np.exp(b)])
    return lo, hi


def shape_grid(domain: Domain, n: int = 24) -> np.ndarray:
    """Reachable candidate shapes on an ``n x n`` grid of the chart, shape ``(m, 2)``.

    A chart cell is kept when some point of it is reachable (its centre, or a
    corner), so shapes at the edge of the box are covered too.
    """
    (tp_lo, t1_lo, tau_lo), (tp_hi, t1_hi, tau_hi) = domain.low, domain.high
    a = np.linspace(np.log(tp_lo / t1_hi), np.log(tp_hi / t1_lo), n)
    b = np.linspace(np.log(tau_lo / t1_hi), np.log(tau_hi / t1_lo), n)
    A, B = np.meshgrid(a, b, indexing="ij")
    lo, hi = reachable_scales(domain, A.ravel(), B.ravel())
    keep = lo <= hi * (1 + 1e-9)
    return np.column_stack([A.ravel()[keep], B.ravel()[keep]])


def _grid_for(shapes: np.ndarray, n: int = 700, spread: float = 4.0) -> np.ndarray:
    """One frequency grid wide enough for all given unit shapes scaled by up to ``spread``."""
    tp = np.exp(shapes[:, 0])
    tau = np.exp(shapes[:, 1])
    w_lo = 1e-3 / (spread * (1 + tp.max() + tau.max()))
    w_hi = 200 * spread / min(tp.min(), tau.min())
    return np.logspace(np.log10(w_lo), np.log10(w_hi), n)


def design_shapes(shapes: np.ndarray, w: np.ndarray, pool=None) -> list[PDDesign]:
    """Optimal PD of each unit shape on the common grid ``w`` (warm-started along the grid)."""
    designs: list[PDDesign] = []
    prev = None
    for a, b in shapes:
        G = inner_response(1.0, np.exp(a), 1.0, np.exp(b), w)[0]
        d = optimal_pd(G, w, x0=prev)
        designs.append(d)
        prev = (d.pd.Kc, d.pd.Kd)
    return designs


def _scaled_cost(Kc, Kd, shape: np.ndarray, c: float, w: np.ndarray) -> float:
    """ISE of PD ``(Kc, Kd)`` on unit shape ``shape`` stretched by ``c`` (inf if unstable)."""
    G = inner_response(1.0, c * shape[0], c * shape[1], c * shape[2], w)[0]
    m = margins((Kc + Kd * 1j * w) * G, w)
    return ise(Kc, Kd, G, w) if m.stable else np.inf


def _pair_cost(d1: PDDesign, p1: np.ndarray, d2: PDDesign, p2: np.ndarray, c: float,
               w: np.ndarray) -> float:
    """Joint cost (%) between unit process 1 and process 2 stretched by ``c``."""
    # Optimum of the stretched process 2 is its unit optimum with Kc / c, at cost c * ISE.
    q22 = c * d2.ise
    q12 = _scaled_cost(d1.pd.Kc, d1.pd.Kd, p2, c, w)
    q21 = _scaled_cost(d2.pd.Kc / c, d2.pd.Kd, p1, 1.0, w)
    return max((q12 - q22) / q22, (q21 - d1.ise) / d1.ise) * 100.0


def shape_distance(d1: PDDesign, p1: np.ndarray, d2: PDDesign, p2: np.ndarray,
                   w: np.ndarray) -> tuple[float, float]:
    """``(min_c joint cost %, argmin c)`` between two unit shapes."""
    # Start from the scale that lines up their optimal crossover frequencies.
    c0 = d1.margins.wc and d2.margins.wc and d2.margins.wc / d1.margins.wc
    c0 = float(c0) if c0 and np.isfinite(c0) else 1.0
    res = minimize_scalar(lambda lc: _pair_cost(d1, p1, d2, p2, float(np.exp(lc)), w),
                          bounds=(np.log(c0) - 1.0, np.log(c0) + 1.0), method="bounded",
                          options={"xatol": 1e-3})
    return float(res.fun), float(np.exp(res.x))


def greedy_net(n: int, neighbours: dict[int, dict[int, float]], cover: float) -> list[int]:
    """Indices of a greedy covering set: every point within ``cover`` of a chosen one.

    ``neighbours[i][j]`` is the distance between candidates ``i`` and ``j``
    (only pairs that were evaluated; absent pairs are treated as far).
    """
    uncovered = set(range(n))
    chosen: list[int] = []
    covers = {i: {j for j, d in neighbours[i].items() if d <= cover} | {i} for i in range(n)}
    while uncovered:
        best = max(range(n), key=lambda i: (len(covers[i] & uncovered), -i))
        chosen.append(best)
        uncovered -= covers[best]
    return sorted(chosen)


def scale_ratio(design: PDDesign, p: np.ndarray, w: np.ndarray, J_target: float) -> float:
    """Ratio ``rho > 1`` with joint cost ``J_target`` % between a shape at scale 1 and ``rho``."""

    def f(lr: float) -> float:
        return _pair_cost(design, p, design, p, float(np.exp(lr)), w) - J_target

    hi = 0.1
    while f(hi) < 0 and hi < 5:
        hi *= 2
    return float(np.exp(brentq(f, 1e-4, hi, xtol=1e-4)))


@dataclass(frozen=True)
class Discretisation:
    """Representative processes of an inner-loop domain.

    Attributes
    ----------
    domain : str
    J_target, tolerance, cover : float
        Target adjacent joint cost, its tolerance and the shape-net radius (%).
    shapes : array (S, 2)
        Chart coordinates ``(a, b)`` of the representative shapes.
    shape_pd : array (S, 2)
        Their unit-scale optimal ``(Kc, Kd)`` for ``K = 1``.
    shape_ise : array (S,)
    reps : array (N, 3)
        Representative processes ``(T_prop, T1, tau)``.
    rep_shape : array (N,)
        Shape index of each representative process.
    rep_pd : array (N, 2)
        Optimal ``(Kc, Kd)`` of each representative for ``K = 1``.
    adjacent_J : array (N,)
        Joint cost (%) of each representative to its nearest other one.
    candidates : int
        Candidate shapes evaluated.
    cand_shapes : array (m, 2)
        Chart coordinates of the candidates.
    cand_owner : array (m,)
        Representative shape whose region holds each candidate (its nearest in joint cost).
    cand_J : array (m, S)
        Joint cost (%) of each candidate to each representative shape (best relative
        scale); pairs too far apart to have been evaluated hold ``J_FAR``.
    seconds : float
        Wall time.
    """

    domain: str
    J_target: float
    tolerance: float
    cover: float
    shapes: np.ndarray
    shape_pd: np.ndarray
    shape_ise: np.ndarray
    reps: np.ndarray
    rep_shape: np.ndarray
    rep_pd: np.ndarray
    adjacent_J: np.ndarray
    candidates: int
    seconds: float
    cand_shapes: np.ndarray
    cand_owner: np.ndarray
    cand_J: np.ndarray

    def owner_of(self, params: np.ndarray) -> np.ndarray:
        """Representative shape index for processes ``(T_prop, T1, tau)`` of shape ``(n, 3)``."""
        p = np.atleast_2d(params)
        ab = np.column_stack([np.log(p[:, 0] / p[:, 1]), np.log(p[:, 2] / p[:, 1])])
        return self.cand_owner[self.nearest_candidate(ab)]

    def nearest_candidate(self, ab: np.ndarray) -> np.ndarray:
        scale = np.ptp(self.cand_shapes, axis=0)
        scale[scale == 0] = 1
        d = np.linalg.norm((ab[:, None, :] - self.cand_shapes[None]) / scale, axis=2)
        return np.argmin(d, axis=1)

    def to_json(self) -> dict:
        out = asdict(self)
        return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in out.items()}

    @classmethod
    def from_json(cls, data: dict) -> Discretisation:
        fields: dict[str, Any] = {k: (np.asarray(v) if isinstance(v, list) else v)
                                  for k, v in data.items()}
        return cls(**fields)


def discretize_inner(domain: Domain, J_target: float = 10.0, tolerance: float = 3.0,
                     cover: float | None = None, grid_n: int = 22,
                     progress=None) -> Discretisation:
    """Discretise an inner-loop domain (attitude or altitude) into representative processes.

    Parameters
    ----------
    domain : Domain
        ``D_ATT`` or ``D_ALT``.
    J_target, tolerance : float
        Adjacent joint cost and its tolerance, in % (paper Table III: 10 and 3).
    cover : float, optional
        Shape-net radius in %; defaults to ``J_target / 2`` so that neighbouring
        shapes end up about ``J_target`` apart.
    grid_n : int
        Chart grid size for candidate shapes.
    progress : callable, optional
        Called as ``progress(done, total, what)``.
    """
    t0 = time.perf_counter()
    cover = J_target / 2 if cover is None else cover
    cand = shape_grid(domain, grid_n)
    w = _grid_for(cand)
    params = np.column_stack([np.exp(cand[:, 0]), np.ones(len(cand)), np.exp(cand[:, 1])])
    designs = design_shapes(cand, w)
    if progress:
        progress(len(cand), len(cand), "shapes designed")
    # Distances between chart neighbours (cells within a radius of ~3 grid steps).
    step = np.array([np.ptp(cand[:, 0]) / (grid_n - 1), np.ptp(cand[:, 1]) / (grid_n - 1)])
    nb: dict[int, dict[int, float]] = {i: {} for i in range(len(cand))}
    pairs = [(i, j) for i in range(len(cand)) for j in range(i + 1, len(cand))
             if np.all(np.abs(cand[i] - cand[j]) <= 3.01 * step)]
    for k, (i, j) in enumerate(pairs):
        dist, _ = shape_distance(designs[i], params[i], designs[j], params[j], w)
        nb[i][j] = nb[j][i] = dist
        if progress and k % 200 == 0:
            progress(k, len(pairs), "shape distances")
    chosen = greedy_net(len(cand), nb, cover)
    # Scale range of each chosen shape: union of the ranges of the candidates it covers.
    owner = {}
    for i in range(len(cand)):
        near = [c for c in chosen if c == i or nb[i].get(c, np.inf) <= cover]
        owner[i] = min(near, key=lambda c: 0 if c == i else nb[i][c]) if near else i
    lo_all, hi_all = reachable_scales(domain, cand[:, 0], cand[:, 1])
    reps, rep_shape, rep_pd = [], [], []
    for s, c in enumerate(chosen):
        members = [i for i in range(len(cand)) if owner[i] == c]
        # the scales its region spans, limited to where this shape itself is in the box
        lo = max(lo_all[members].min(), lo_all[c])
        hi = min(hi_all[members].max(), hi_all[c])
        if lo > hi:
            lo, hi = lo_all[c], hi_all[c]
        rho = scale_ratio(designs[c], params[c], w, J_target)
        n = max(1, int(np.ceil(np.log(hi / lo) / np.log(rho) - 1e-9)) + 0)
        # n points spaced by about rho, centred in [lo, hi]
        span = np.log(hi / lo)
        scales = np.exp(np.log(lo) + (np.arange(n) + 0.5) * span / n) if n > 1 else \
            np.array([np.sqrt(lo * hi)])
        for sc in scales:
            reps.append(params[c] * sc)
            rep_shape.append(s)
            rep_pd.append((designs[c].pd.Kc / sc, designs[c].pd.Kd))
    reps_a = np.asarray(reps)
    adjacent = _adjacent_costs(reps_a, np.asarray(rep_pd), np.asarray(rep_shape), chosen, designs,
                               params, w)
    return Discretisation(
        domain=domain.name,
        J_target=J_target,
        tolerance=tolerance,
        cover=cover,
        shapes=cand[chosen],
        shape_pd=np.array([[designs[c].pd.Kc, designs[c].pd.Kd] for c in chosen]),
        shape_ise=np.array([designs[c].ise for c in chosen]),
        reps=reps_a,
        rep_shape=np.asarray(rep_shape),
        rep_pd=np.asarray(rep_pd),
        adjacent_J=adjacent,
        candidates=len(cand),
        seconds=time.perf_counter() - t0,
        cand_shapes=cand,
        cand_owner=np.array([chosen.index(owner[i]) for i in range(len(cand))]),
        cand_J=np.array([[0.0 if i == c else min(nb[i].get(c, J_FAR), J_FAR) for c in chosen]
                         for i in range(len(cand))]),
    )


def _adjacent_costs(reps, rep_pd, rep_shape, chosen, designs, params, w) -> np.ndarray:
    """Joint cost of each representative to its nearest neighbour (in log-parameter space)."""
    logp = np.log(reps)
    out = np.empty(len(reps))
    for i in range(len(reps)):
        d = np.linalg.norm(logp - logp[i], axis=1)
        d[i] = np.inf
        best = np.inf
        for j in np.argsort(d)[:4]:
            si, sj = chosen[rep_shape[i]], chosen[rep_shape[j]]
            ci = reps[i][1]
            cj = reps[j][1]
            best = min(best, _pair_cost(_scaled_design(designs[si], ci), params[si] * ci,
                                        _scaled_design(designs[sj], cj), params[sj] * cj, 1.0,
                                        w))
        out[i] = best
    return out


def _scaled_design(d: PDDesign, c: float) -> PDDesign:
    return PDDesign(PD(d.pd.Kc / c, d.pd.Kd), d.ise * c, d.margins, d.evaluations)
