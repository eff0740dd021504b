"""Optimal PD design (docs/method.md, paper Table III) and the performance deterioration J.

The deployed controller is ``u = Kc e - Kd dy/dt`` (derivative on the
measurement). For a unit set-point step the error is::

    E(s) = (1 + Kd s G) / (s (1 + (Kc + Kd s) G))

and the cost is its integral square error, computed in the frequency domain
by Parseval's theorem, ``ISE = (1/pi) int_0^inf |E(jw)|^2 dw``, on a
logarithmic grid with the analytic tails added (``|E|^2 -> 1/w^2`` above the
grid, ``|E(0)|^2`` below). Stability (Nyquist, counting crossings of the
negative real axis left of -1), phase margin and gain margin are those of
``L = (Kc + Kd s) G``.

The optimum minimises the ISE subject to a phase margin of at least 20 deg
(Nelder-Mead on ``log Kc, log Kd`` with a penalty, then a final exact pull
onto the feasible set). Designs are made for the gain-normalised plant
(``K = 1``); for gain ``K`` divide both gains by ``K``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from mrft_gcs.plant import PD

__all__ = [
    "Margins",
    "PDDesign",
    "frequency_grid",
    "ise",
    "margins",
    "optimal_pd",
    "deterioration",
    "joint_cost",
    "PM_MIN_DEG",
]

#: Minimum phase margin of the designs (paper Table III), degrees.
PM_MIN_DEG = 20.0


def frequency_grid(T_prop, T1, tau, n: int = 1200, extra_T=()) -> np.ndarray:
    """Log-spaced frequencies (rad/s) covering a plant's dynamics, shape ``(n,)``.

    From ``1e-3 / (T_prop + T1 + tau + ...)`` to ``200 / min(T_prop, tau, ...)``.
    """
    Ts = [float(T_prop), float(T1), float(tau), *map(float, extra_T)]
    pos = [t for t in Ts if t > 0]
    return np.logspace(np.log10(1e-3 / sum(pos)), np.log10(200.0 / min(pos)), n)


def _error_sq(Kc, Kd, G, w) -> np.ndarray:
    s = 1j * w
    L = (Kc + Kd * s) * G
    E = (1 + Kd * s * G) / (s * (1 + L))
    return np.abs(E) ** 2


def ise(Kc: float, Kd: float, G: np.ndarray, w: np.ndarray) -> float:
    """Infinite-horizon ISE of the unit-step error (stability is *not* checked here).

    ``G`` is the plant's frequency response on the grid ``w`` (1-D arrays).
    """
    e2 = _error_sq(Kc, Kd, G, w)
    lw = np.log(w)
    body = np.trapezoid(e2 * w, lw)
    return float((body + e2[0] * w[0] + 1.0 / w[-1]) / np.pi)


@dataclass(frozen=True)
class Margins:
    """Stability and margins of an open loop ``L(jw)``.

    Attributes
    ----------
    stable : bool
        Closed loop stable (Nyquist, no net encirclement of -1).
    pm_deg : float
        Smallest phase margin over all gain crossovers (deg); ``inf`` if none.
    gm : float
        Smallest gain margin (ratio) over phase crossovers with ``|L| < 1``; ``inf`` if none.
    wc : float
        Gain crossover frequency of the smallest phase margin (rad/s).
    """

    stable: bool
    pm_deg: float
    gm: float
    wc: float


def margins(L: np.ndarray, w: np.ndarray) -> Margins:
    """Margins of the open loop ``L`` sampled on ``w`` (type-1 plant: phase starts near -90 deg)."""
    lmag = np.log(np.abs(L))
    ph = np.unwrap(np.angle(L))
    ph = ph - 2 * np.pi * np.round(ph[0] / (2 * np.pi))
    # Nyquist: signed crossings of the lines -180 - 360 k deg; those with |L| > 1 encircle -1.
    band = np.floor((ph + np.pi) / (2 * np.pi))
    i = np.flatnonzero(band[1:] != band[:-1])
    level = -np.pi + 2 * np.pi * np.maximum(band[i], band[i + 1])
    frac = np.clip((level - ph[i]) / (ph[i + 1] - ph[i]), 0.0, 1.0)
    lm = lmag[i] + frac * (lmag[i + 1] - lmag[i])
    enc = int(np.sum(np.sign(band[i + 1] - band[i])[lm > 0]))
    gm = float(np.exp(-lm[lm <= 0].max())) if np.any(lm <= 0) else np.inf
    # Gain crossovers.
    j = np.flatnonzero((lmag[1:] > 0) != (lmag[:-1] > 0))
    if j.size:
        f = -lmag[j] / (lmag[j + 1] - lmag[j])
        p = ph[j] + f * (ph[j + 1] - ph[j])
        pm_all = np.degrees(np.mod(p + np.pi + np.pi, 2 * np.pi) - np.pi)
        k = int(np.argmin(pm_all))
        pm = float(pm_all[k])
        wc = float(np.exp(np.log(w[j[k]]) + f[k] * np.log(w[j[k] + 1] / w[j[k]])))
    else:
        pm, wc = np.inf, np.nan
    return Margins(stable=enc == 0 and bool(lmag[-1] < 0), pm_deg=pm, gm=gm, wc=wc)


@dataclass(frozen=True)
class PDDesign:
    """An optimal PD for one gain-normalised plant.

    Attributes
    ----------
    pd : PD
        Gains for ``K = 1`` (divide by ``K`` for the real plant).
    ise : float
        Its ISE on the plant (s).
    margins : Margins
        Its stability margins on the plant.
    evaluations : int
        Cost evaluations spent.
    """

    pd: PD
    ise: float
    margins: Margins
    evaluations: int

    def as_dict(self) -> dict[str, float | bool]:
        return {
            "Kc": self.pd.Kc,
            "Kd": self.pd.Kd,
            "ise": self.ise,
            "pm_deg": self.margins.pm_deg,
            "gm": self.margins.gm,
            "gm_db": (float(20 * np.log10(self.margins.gm)) if np.isfinite(self.margins.gm)
                      else np.inf),
            "wc_rad_s": self.margins.wc,
            "stable": self.margins.stable,
        }


def _evaluate(Kc: float, Kd: float, G: np.ndarray, w: np.ndarray) -> tuple[float, Margins]:
    m = margins((Kc + Kd * 1j * w) * G, w)
    if not m.stable:
        return np.inf, m
    return ise(Kc, Kd, G, w), m


def _initial_guess(G: np.ndarray, w: np.ndarray) -> tuple[float, float]:
    # Place the PD zero where the plant's phase is -135 deg and aim for a 45 deg
    # margin there: a robust, always-stable starting point.
    ph = np.unwrap(np.angle(G[0] if G.ndim > 1 else G))
    g = G[0] if G.ndim > 1 else G
    i = int(np.argmin(np.abs(ph + np.radians(225))))
    w1 = w[i]
    Kd = 0.5 / (abs(g[i]) * w1)
    return Kd * w1 * 0.5, Kd


def optimal_pd(G: np.ndarray, w: np.ndarray, pm_min_deg: float = PM_MIN_DEG,
               x0: tuple[float, float] | None = None) -> PDDesign:
    """ISE-optimal PD with phase margin >= ``pm_min_deg`` for the plant response ``G`` on ``w``.

    Parameters
    ----------
    G : array (m,)
        Frequency response of the gain-normalised plant on the grid ``w``.
    w : array (m,)
        Frequencies (rad/s), log-spaced, wide enough to hold the dynamics
        (see :func:`frequency_grid`).
    x0 : (Kc, Kd), optional
        Starting point (e.g. a neighbour's optimum).

    Examples
    --------
    >>> from mrft_gcs.plant import inner_response
    >>> w = frequency_grid(0.05, 0.5, 0.01)
    >>> d = optimal_pd(inner_response(1, 0.05, 0.5, 0.01, w)[0], w)
    >>> d.margins.pm_deg >= 20 - 1e-6
    True
    """
    evals = 0

    def cost(x: np.ndarray) -> float:
        nonlocal evals
        evals += 1
        Kc, Kd = np.exp(x)
        q, m = _evaluate(Kc, Kd, G, w)
        if not np.isfinite(q):
            return 1e12
        short = max(0.0, pm_min_deg - m.pm_deg)
        return q * (1.0 + 0.05 * short + 0.02 * short**2)

    starts = [x0] if x0 is not None else []
    starts.append(_initial_guess(G, w))
    best = None
    for s in starts:
        res = minimize(cost, np.log(s), method="Nelder-Mead",
                       options={"xatol": 1e-4, "fatol": 1e-9, "maxiter": 600})
        if best is None or res.fun < best.fun:
            best = res
    assert best is not None
    Kc, Kd = np.exp(best.x)
    Kc, Kd = _pull_feasible(Kc, Kd, G, w, pm_min_deg)
    q, m = _evaluate(Kc, Kd, G, w)
    return PDDesign(PD(float(Kc), float(Kd)), float(q), m, evals)


def _pull_feasible(Kc: float, Kd: float, G, w, pm_min_deg: float) -> tuple[float, float]:
    """Scale both gains down (a pure gain change) until the margin constraint holds exactly."""
    m = margins((Kc + Kd * 1j * w) * G, w)
    if m.stable and m.pm_deg >= pm_min_deg:
        return Kc, Kd
    lo, hi = 0.0, 1.0  # lo feasible scale (log-space bisection on the multiplier)
    for _ in range(40):
        mid = 0.5 * (lo + hi) if lo > 0 else hi * 0.5
        mm = margins((Kc + Kd * 1j * w) * mid * G, w)
        if mm.stable and mm.pm_deg >= pm_min_deg:
            lo = mid
            if hi - lo < 1e-6:
                break
        else:
            hi = mid
        if lo > 0 and hi - lo < 1e-6:
            break
    return Kc * lo, Kd * lo


def deterioration(pd_i: PD, G_j: np.ndarray, w: np.ndarray, q_opt_j: float) -> float:
    """``J_ij`` (eq. 17) in %: relative ISE increase when ``pd_i`` replaces the optimum of ``G_j``.

    ``inf`` when ``pd_i`` destabilises ``G_j``.
    """
    q, _ = _evaluate(pd_i.Kc, pd_i.Kd, G_j, w)
    return float((q - q_opt_j) / q_opt_j * 100.0)


def joint_cost(d_i: PDDesign, G_i: np.ndarray, d_j: PDDesign, G_j: np.ndarray,
               w: np.ndarray) -> float:
    """``max(J_ij, J_ji)`` in % for two designed plants on a common grid ``w``."""
    return max(deterioration(d_i.pd, G_j, w, d_j.ise), deterioration(d_j.pd, G_i, w, d_i.ise))
