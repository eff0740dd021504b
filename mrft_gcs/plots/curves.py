"""What the plots of a loop show: the open loop of the written gains and their step response.

Pure numerics on the identified model and the written PD (``u = Kc e - Kd dy/dt``): the
open loop ``L = (Kc + Kd s) G`` with its margins (:func:`mrft_gcs.pd_design.margins`),
and the unit set-point step simulated on the delayed model
(:mod:`mrft_gcs.simulate`). For x and y, ``G`` is the side part behind the closed
attitude loop under the attitude loop's identified model and the gains its side design
assumed (as :mod:`mrft_gcs.identify.runtime` designs them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from mrft_gcs.loops import Loop, LoopKind
from mrft_gcs.pd_design import Margins, frequency_grid, margins
from mrft_gcs.plant import (
    PD,
    InnerModel,
    SideModel,
    closed_inner_response,
    inner_response,
    side_response,
)
from mrft_gcs.simulate import inner_plant, side_plant

__all__ = ["LoopCurves", "loop_curves"]


@dataclass(frozen=True)
class LoopCurves:
    """Open-loop frequency response and closed-loop step of one loop's written gains.

    Attributes
    ----------
    loop : Loop
    gains : PD
        The gains the curves are for (the written ones), SI units of the loop.
    w : ndarray, shape (n,)
        Frequencies (rad/s).
    L : ndarray, shape (n,), complex
        Open loop ``(Kc + Kd jw) G(jw)``.
    margins : Margins
        Phase margin (deg), gain margin (ratio), crossover (rad/s), stability.
    w_pc : float
        Phase crossover (-180 deg) where the gain margin is read (rad/s; NaN: none).
    t_s, y : ndarray, shape (m,)
        Unit set-point step response on the model (s; output per unit set point).
    """

    loop: Loop
    gains: PD
    w: np.ndarray
    L: np.ndarray
    margins: Margins
    w_pc: float
    t_s: np.ndarray
    y: np.ndarray

    @property
    def magnitude_db(self) -> np.ndarray:
        return 20.0 * np.log10(np.abs(self.L))

    @property
    def phase_deg(self) -> np.ndarray:
        ph = np.unwrap(np.angle(self.L))
        return np.degrees(ph - 2 * np.pi * np.round(ph[0] / (2 * np.pi)))


def _phase_crossover(L: np.ndarray, w: np.ndarray) -> float:
    ph = np.unwrap(np.angle(L))
    ph = ph - 2 * np.pi * np.round(ph[0] / (2 * np.pi))
    i = np.flatnonzero((ph[1:] + np.pi < 0) != (ph[:-1] + np.pi < 0))
    i = i[np.abs(L[i]) < 1.0] if i.size else i
    if not i.size:
        return math.nan
    k = int(i[0])
    f = (-np.pi - ph[k]) / (ph[k + 1] - ph[k])
    return float(np.exp(np.log(w[k]) + f * np.log(w[k + 1] / w[k])))


def _duration(m: Margins, slowest_s: float) -> float:
    """Long enough to settle: many crossover periods, at least a few plant time constants."""
    base = 15.0 / m.wc if math.isfinite(m.wc) and m.wc > 0 else 0.0
    return float(min(max(base, 4.0 * slowest_s, 0.5), 60.0))


def loop_curves(loop: Loop, model: InnerModel | SideModel, gains: PD, *,
                inner: tuple[InnerModel, PD] | None = None, less_delay_s: float = 0.0,
                n_w: int = 800, n_t: int = 3000) -> LoopCurves | None:
    """Curves of ``gains`` on ``model``; None where they cannot be drawn.

    Parameters
    ----------
    loop : Loop
    model : InnerModel or SideModel
        The identified model (SI units of the loop).
    gains : PD
        The written gains.
    inner : (InnerModel, PD), optional
        x and y only: the attitude loop behind them (model and PD). Without it a side
        loop has no curves (None).
    less_delay_s : float
        Inner loops whose relay ran on the ground station: the delay (s) the written
        gains were re-targeted for, taken off the model's ``tau`` (the onboard loop).
    n_w, n_t : int
        Frequency and time samples.
    """
    if not (math.isfinite(gains.Kc) and math.isfinite(gains.Kd)):
        return None
    if isinstance(model, InnerModel) and math.isfinite(less_delay_s) and less_delay_s > 0:
        model = replace(model, tau=max(model.tau - less_delay_s, 0.0))
    if isinstance(model, InnerModel) and loop.kind is not LoopKind.SIDE:
        w = frequency_grid(model.T_prop, model.T1, model.tau, n=n_w)
        G = inner_response(model.K, model.T_prop, model.T1, model.tau, w)[0]
        slowest = model.T_prop + model.T1 + model.tau
    elif isinstance(model, SideModel) and inner is not None:
        mi, gi = inner
        w = frequency_grid(mi.T_prop, mi.T1, mi.tau, n=n_w, extra_T=(model.T2, model.tau))
        t_att = closed_inner_response(gi.Kc, gi.Kd,
                                      inner_response(mi.K, mi.T_prop, mi.T1, mi.tau, w), w)[0]
        G = t_att * side_response(model.K, model.T2, model.tau, w)[0]
        slowest = model.T2 + model.tau + mi.T_prop + mi.T1 + mi.tau
    else:
        return None
    L = (gains.Kc + gains.Kd * 1j * w) * G
    m = margins(L, w)
    duration = _duration(m, slowest)
    dt = duration / n_t
    t = np.arange(n_t) * dt
    y = _step(model, gains, inner, n_t, dt)
    return LoopCurves(loop, gains, w, L, m, _phase_crossover(L, w), t, y)


def _step(model: InnerModel | SideModel, gains: PD, inner: tuple[InnerModel, PD] | None,
          n: int, dt: float) -> np.ndarray:
    """Unit set-point step under the PD (derivative on the measurement), as flown."""
    y = np.empty(n)
    if isinstance(model, InnerModel):
        p = inner_plant(model.K, model.T_prop, model.T1, model.tau, dt)
        for k in range(n):
            y[k] = p.output()[0]
            p.step(gains.Kc * (1.0 - p.output()) - gains.Kd * p.derivative())
        return y
    assert inner is not None
    mi, gi = inner
    att = inner_plant(mi.K, mi.T_prop, mi.T1, mi.tau, dt)
    pos = side_plant(model.K, model.T2, model.tau, dt)
    for k in range(n):
        x = pos.output()
        y[k] = x[0]
        tilt_sp = gains.Kc * (1.0 - x) - gains.Kd * pos.derivative()
        theta = att.output()
        pos.step(theta)
        att.step(gi.Kc * (tilt_sp - theta) - gi.Kd * att.derivative())
    return y
