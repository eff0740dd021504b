"""Side-motion design (paper Algorithm 3): one set of side classes per attitude shape.

The side plant is the closed attitude loop (the attitude shape ``k`` under its
optimal PD) in cascade with ``K e^{-tau s}/((T2 s + 1) s)``. The whole cascade
can be stretched in time, so for an attitude process of shape ``k`` at scale
``c`` the side problem equals the unit-scale one with side parameters
``(T2 / c, tau / c)``. Each attitude shape therefore gets one side
discretisation over the *normalised* box ``D_side / [c_lo, c_hi]`` (its
attitude scale range), one distinguishing phase, one zeta table and one
classifier; at run time the attitude identification supplies ``k`` and ``c``.

Functions here reuse the inner-loop machinery: the greedy net
(:func:`mrft_gcs.design.discretize.greedy_net`), optimal PD design, the non-parametric
tuning rules of Algorithm 1 and the simulator. The side features and the side plant's
response, which the runtime needs too, live in :mod:`mrft_gcs.identify.side`.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mrft_gcs.design.dataset import BIAS_MAX, NOISE_MAX, Dataset
from mrft_gcs.design.discretize import J_FAR, greedy_net, reachable_scales
from mrft_gcs.design.phase import rule_cost
from mrft_gcs.domains import D_ATT, D_SIDE
from mrft_gcs.features import N_POINTS
from mrft_gcs.identify.runtime import identify, load_bundle
from mrft_gcs.identify.side import SIDE_H, side_features, side_plant_response
from mrft_gcs.loops import LoopKind
from mrft_gcs.pd_design import PDDesign, ise, margins, optimal_pd
from mrft_gcs.simulate import find_cycle, simulate_mrft, simulate_side_mrft

__all__ = ["SideClasses", "side_plant_response", "design_side_for_shape", "side_dataset",
           "SIDE_BETAS", "SIDE_H", "side_features"]

SIDE_BETAS = np.round(np.arange(-0.7, 0.21, 0.1), 3)  # see phase.BETA_GRID


@dataclass(frozen=True)
class SideClasses:
    """Side classes of one attitude shape (normalised to unit attitude scale)."""

    att_shape: int
    att_params: np.ndarray
    att_pd: np.ndarray
    box_lo: np.ndarray
    box_hi: np.ndarray
    cand: np.ndarray  # (m, 2) log T2', log tau'
    cand_owner: np.ndarray
    cand_J: np.ndarray
    params: np.ndarray  # (S, 2) T2', tau'
    pd: np.ndarray  # (S, 2) unit optimal (Kc, Kd)
    ise: np.ndarray
    beta: float
    worst_J: float
    unit_period: np.ndarray
    unit_amplitude: np.ndarray
    zeta: np.ndarray
    rule_cost: np.ndarray
    seconds: float

    def owner_of(self, T2n, taun) -> np.ndarray:
        ab = np.column_stack([np.log(T2n), np.log(taun)])
        scale = np.ptp(self.cand, axis=0)
        scale[scale == 0] = 1
        d = np.linalg.norm((ab[:, None, :] - self.cand[None]) / scale, axis=2)
        return np.argmin(d, axis=1)

    def to_json(self) -> dict:
        return {k: (v.tolist() if isinstance(v, np.ndarray) else v)
                for k, v in self.__dict__.items()}

    @classmethod
    def from_json(cls, d: dict) -> SideClasses:
        fields: dict[str, Any] = {k: (np.asarray(v) if isinstance(v, list) else v)
                                  for k, v in d.items()}
        return cls(**fields)


def _cost(Kc, Kd, P, w) -> float:
    m = margins((Kc + Kd * 1j * w) * P, w)
    return ise(Kc, Kd, P, w) if m.stable else np.inf


def _unit_side_cycles(att, att_pd, params, betas, cycles=12, dt_frac=2e-4):
    """Simulated side MRFT cycles (K = 1, h = 1, unit attitude scale) for each beta."""
    w = np.logspace(-3, 5, 3000)
    n = len(params)
    P = np.empty((n, len(betas)))
    A = np.empty((n, len(betas)))
    for k, beta in enumerate(betas):
        resp = side_plant_response(att, att_pd, params[:, 0], params[:, 1], w)
        ph = np.unwrap(np.angle(resp), axis=1)
        T_hb = 2 * np.pi / w[np.argmax(ph <= -np.pi + np.arcsin(beta), axis=1)]
        c = 1.0 / T_hb  # stretch the whole cascade so the cycle lasts about a second
        inner = (1.0 / c, att[0] * c, att[1] * c, att[2] * c)
        run = simulate_side_mrft(inner, (att_pd[0], att_pd[1] * c), (1.0 / c, params[:, 0] * c,
                                 params[:, 1] * c), beta=beta, h=1.0, duration_s=float(cycles),
                                 dt=dt_frac, keep_s=3.0)
        for i in range(n):
            cyc = find_cycle(run.u[i], run.y[i], run.dt)
            P[i, k] = cyc.period_s / c[i] if cyc else np.nan
            A[i, k] = cyc.amplitude if cyc else np.nan
    return P, A


def design_side_for_shape(k: int, att: np.ndarray, att_pd: np.ndarray, scale_lo: float,
                          scale_hi: float, J_target: float = 10.0, grid_n: int = 7) -> SideClasses:
    """Algorithm 3 for one attitude shape: discretise, distinguishing phase, zeta."""
    t0 = time.perf_counter()
    (T2_lo, tau_lo), (T2_hi, tau_hi) = D_SIDE.low, D_SIDE.high
    lo = np.array([T2_lo / scale_hi, tau_lo / scale_hi])
    hi = np.array([T2_hi / scale_lo, tau_hi / scale_lo])
    A, B = np.meshgrid(*(np.linspace(np.log(lo[i]), np.log(hi[i]), grid_n) for i in range(2)),
                       indexing="ij")
    cand = np.column_stack([A.ravel(), B.ravel()])
    params = np.exp(cand)
    w = np.logspace(np.log10(1e-3 / (hi[0] + hi[1] + 1)), np.log10(200 / min(att[0], att[2])), 900)
    P = side_plant_response(att, tuple(att_pd), params[:, 0], params[:, 1], w)
    designs: list[PDDesign] = []
    prev = None
    for i in range(len(cand)):
        d = optimal_pd(P[i], w, x0=prev)
        designs.append(d)
        prev = (d.pd.Kc, d.pd.Kd)
    step = np.ptp(cand, axis=0) / (grid_n - 1)
    nb: dict[int, dict[int, float]] = {i: {} for i in range(len(cand))}
    for i in range(len(cand)):
        for j in range(i + 1, len(cand)):
            if np.all(np.abs(cand[i] - cand[j]) <= 2.01 * step):
                qij = _cost(designs[i].pd.Kc, designs[i].pd.Kd, P[j], w)
                qji = _cost(designs[j].pd.Kc, designs[j].pd.Kd, P[i], w)
                dist = max((qij - designs[j].ise) / designs[j].ise,
                           (qji - designs[i].ise) / designs[i].ise) * 100
                nb[i][j] = nb[j][i] = dist
    cover = J_target / 2
    chosen = greedy_net(len(cand), nb, cover)
    owner = np.array([min((c for c in chosen if c == i or nb[i].get(c, np.inf) <= cover),
                          key=lambda c: 0 if c == i else nb[i][c]) for i in range(len(cand))])
    cand_J = np.array([[0.0 if i == c else min(nb[i].get(c, J_FAR), J_FAR) for c in chosen]
                       for i in range(len(cand))])
    sp = params[chosen]
    spd = np.array([[designs[c].pd.Kc, designs[c].pd.Kd] for c in chosen])
    sise = np.array([designs[c].ise for c in chosen])
    # Distinguishing phase over the side classes (Algorithm 1 with feasible rules).
    Pc, Ac = _unit_side_cycles(att, tuple(att_pd), sp, SIDE_BETAS)
    Pch = P[chosen]
    best = (np.inf, 0)
    for b in range(len(SIDE_BETAS)):
        T, a = Pc[:, b], Ac[:, b]
        if not np.all(np.isfinite(T) & np.isfinite(a)):
            continue
        c1 = spd[:, 0] * a
        c2 = spd[:, 1] * 2 * np.pi / (spd[:, 0] * T)
        for i in range(len(sp)):
            worst = 0.0
            for j in range(len(sp)):
                Kc = c1[i] / a[j]
                Kd = c2[i] * Kc * T[j] / (2 * np.pi)
                worst = max(worst, rule_cost(Kc, Kd, Pch[j], w, sise[j]))
                if worst >= best[0]:
                    break
            if worst < best[0]:
                best = (worst, b)
    beta = float(SIDE_BETAS[best[1]])
    up, ua = _unit_side_cycles(att, tuple(att_pd), sp, [beta], cycles=16, dt_frac=1e-4)
    gabs = np.array([abs(side_plant_response(att, tuple(att_pd), T2, ta, [2 * np.pi / T])[0, 0])
                     for (T2, ta), T in zip(sp, up[:, 0], strict=True)])
    T, a = up[:, 0], ua[:, 0]
    c1 = spd[:, 0] * a
    c2 = spd[:, 1] * 2 * np.pi / (spd[:, 0] * T)
    cost = np.array([[rule_cost(c1[i] / a[j], c2[i] * c1[i] / a[j] * T[j] / (2 * np.pi), Pch[j], w,
                                sise[j]) for j in range(len(sp))] for i in range(len(sp))])
    return SideClasses(att_shape=k, att_params=np.asarray(att), att_pd=np.asarray(att_pd),
                       box_lo=lo, box_hi=hi, cand=cand,
                       cand_owner=np.array([chosen.index(o) for o in owner]), cand_J=cand_J,
                       params=sp, pd=spd, ise=sise, beta=beta, worst_J=float(best[0]),
                       unit_period=up[:, 0], unit_amplitude=ua[:, 0], zeta=ua[:, 0] / gabs,
                       rule_cost=np.where(np.isfinite(cost), cost, 1e6),
                       seconds=time.perf_counter() - t0)


def _fill_rows(run, idx, att_scale, rows, per, amp, ok) -> None:
    """Features of each simulated record ``run.*[r]`` into row ``idx[r]`` (no cycle: skipped)."""
    for r, i in enumerate(idx):
        try:
            f, x = side_features(run.t, run.u[r], run.y[r], att_scale[i], setpoint=0.0)
        except Exception:  # noqa: BLE001 - a run without two proper cycles is dropped
            continue
        rows[i], per[i], amp[i], ok[i] = x, f.period_s, f.amplitude, True


def side_dataset(sc: SideClasses, scale_lo: float, scale_hi: float, n: int, seed: int,
                 dt: float = 1e-3) -> Dataset:
    """Labelled side MRFT cycles for one attitude shape (real time units, random attitude scale)."""
    rng = np.random.default_rng(seed)
    c = np.exp(rng.uniform(np.log(scale_lo), np.log(scale_hi), n))
    side = D_SIDE.sample_log_uniform(n, rng)
    cand = sc.owner_of(side[:, 0] / c, side[:, 1] / c)
    label = sc.cand_owner[cand]
    J = sc.cand_J[cand]
    bias = rng.uniform(-BIAS_MAX, BIAS_MAX, n)
    T_est = 1.3 / (1 - np.abs(bias)) * sc.unit_period[label] * c
    A_est = sc.unit_amplitude[label] * c
    noise = rng.uniform(0, NOISE_MAX, n) * A_est
    att = sc.att_params
    rows = np.zeros((n, N_POINTS + 3), np.float32)
    per, amp = np.full(n, np.nan), np.full(n, np.nan)
    ok = np.zeros(n, bool)
    order = np.argsort(T_est)
    for s in range(0, n, 400):
        idx = order[s:s + 400]
        Tmax = float(T_est[idx].max())
        dur = 2.0 + 12 * Tmax
        run = simulate_side_mrft((1.0, att[0] * c[idx], att[1] * c[idx], att[2] * c[idx]),
                                 (sc.att_pd[0] / c[idx], sc.att_pd[1]),
                                 (1.0, side[idx, 0], side[idx, 1]), beta=sc.beta, h=1.0,
                                 bias=bias[idx], noise_std=noise[idx], band=4 * noise[idx],
                                 duration_s=dur, dt=dt, keep_s=5.5 * Tmax,
                                 seed=int(rng.integers(2**31)))
        _fill_rows(run, idx, c, rows, per, amp, ok)
    params = np.column_stack([side, c])
    return Dataset(rows[ok], label[ok], J[ok], params[ok], per[ok], amp[ok], noise[ok], bias[ok])


def save(path: Path, sc: SideClasses) -> None:
    path.write_text(json.dumps(sc.to_json()))


def side_dataset_realistic(sc: SideClasses, disc, n: int, seed: int, dt: float = 1e-3) -> Dataset:
    """Side rows made the way flight makes them: real attitude processes, identified gains.

    Attitude processes are drawn around attitude shape ``k`` (its chart region, random
    scale and gain), their MRFT is simulated and identified with the bundled attitude
    classifier; those whose identification picks shape ``k`` keep the gains and scale it
    returned, and the side test then runs on the real cascade. Labels are the side
    regions of ``(T2 / c, tau / c)`` as in :func:`side_dataset`.
    """
    rng = np.random.default_rng(seed)
    ab = load_bundle(LoopKind.ATTITUDE)
    k = sc.att_shape
    own = np.flatnonzero(disc.cand_owner == k)
    m = 4 * n
    pick = rng.choice(own, m) if own.size else np.full(m, 0)
    step = np.ptp(disc.cand_shapes, axis=0) / 15
    chart = disc.cand_shapes[pick] + rng.uniform(-0.5, 0.5, (m, 2)) * step
    lo, hi = reachable_scales(D_ATT, chart[:, 0], chart[:, 1])
    ok = lo <= hi
    chart, lo, hi = chart[ok], lo[ok], hi[ok]
    T1 = np.exp(rng.uniform(np.log(lo), np.log(np.maximum(hi, lo))))
    att = np.column_stack([np.exp(chart[:, 0]) * T1, T1, np.exp(chart[:, 1]) * T1])
    Ka = np.exp(rng.uniform(np.log(0.5), np.log(50.0), len(att)))
    run = simulate_mrft(Ka, att[:, 0], att[:, 1], att[:, 2], beta=ab.beta, h=ab.h,
                        duration_s=1.0 + 14 * att[:, 1].max(), keep_s=5.0,
                        seed=int(rng.integers(2**31)))
    keep = []
    for i in range(len(att)):
        try:
            a = identify(LoopKind.ATTITUDE, run.t, run.u[i], run.y[i], beta=ab.beta, h=ab.h,
                         setpoint=0.0)
        except Exception:  # noqa: BLE001
            continue
        if a.diagnostics.shape == k:
            keep.append((i, a.gains.Kc, a.gains.Kd, a.diagnostics.scale))
        if len(keep) >= n:
            break
    idx = np.array([r[0] for r in keep], int)
    if idx.size == 0:
        return side_dataset(sc, float(lo.min()), float(hi.max()), n, seed, dt)
    Kc = np.array([r[1] for r in keep])
    Kd = np.array([r[2] for r in keep])
    c = np.array([r[3] for r in keep])
    q = len(idx)
    side = D_SIDE.sample_log_uniform(q, rng)
    cand = sc.owner_of(side[:, 0] / c, side[:, 1] / c)
    label = sc.cand_owner[cand]
    J = sc.cand_J[cand]
    bias = rng.uniform(-BIAS_MAX, BIAS_MAX, q)
    T_est = 1.3 / (1 - np.abs(bias)) * sc.unit_period[label] * c
    noise = rng.uniform(0, NOISE_MAX, q) * sc.unit_amplitude[label] * c * 9.81 * side[:, 0]
    Ks = 9.81 * side[:, 0]
    rows = np.zeros((q, N_POINTS + 3), np.float32)
    per, amp = np.full(q, np.nan), np.full(q, np.nan)
    good = np.zeros(q, bool)
    order = np.argsort(T_est)
    for s in range(0, q, 400):
        j = order[s:s + 400]
        Tmax = float(T_est[j].max())
        ii = idx[j]
        srun = simulate_side_mrft((Ka[ii], *att[ii].T), (Kc[j], Kd[j]), (Ks[j], side[j, 0],
                                  side[j, 1]), beta=sc.beta, h=1.0, bias=bias[j],
                                  noise_std=noise[j], band=4 * noise[j],
                                  duration_s=2.0 + 12 * Tmax, dt=dt, keep_s=5.5 * Tmax,
                                  seed=int(rng.integers(2**31)))
        _fill_rows(srun, j, c, rows, per, amp, good)
    params = np.column_stack([side, c])
    return Dataset(rows[good], label[good], J[good], params[good], per[good], amp[good],
                   noise[good], bias[good])
