"""Score tuned gains against the optimal PD of a simulated airframe's true linear models.

Used by the benchmark, the end-to-end tests and the demo: the bundled SITL knows
its own small-signal models (:meth:`mrft_gcs.sitl.Airframe.linear_models`), so
the deterioration ``J`` (SPEC 2, eq. 17) of the gains a tune wrote can be
computed exactly. For x and y the process is the true cascade: the closed
attitude loop under the attitude gains *actually in use*, then the side part.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from mrft_gcs.loops import Loop
from mrft_gcs.pd_design import deterioration, frequency_grid, margins, optimal_pd
from mrft_gcs.plant import PD, closed_inner_response, inner_response, side_response

__all__ = ["LoopScore", "true_response", "score_gains"]

_SIDE_INNER = {Loop.X: Loop.PITCH, Loop.Y: Loop.ROLL}


@dataclass(frozen=True)
class LoopScore:
    """``J_pct`` of ``gains`` against ``optimal`` on the true process; phase margin in deg."""

    loop: Loop
    gains: PD
    optimal: PD
    J_pct: float
    pm_deg: float
    stable: bool


def true_response(models: Mapping[str, Mapping[str, float]], loop: Loop,
                  inner_gains: PD | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(G(jw), w)`` of the true process of ``loop`` (side loops need the inner gains)."""
    if loop in _SIDE_INNER:
        mi = models[_SIDE_INNER[loop].value]
        ms = models[loop.value]
        w = frequency_grid(mi["T_prop"], mi["T1"], mi["tau"], extra_T=(ms["T2"], ms["tau"]))
        if inner_gains is None:
            raise ValueError(f"{loop.value}: the true side process needs the attitude gains")
        gi = inner_response(mi["K"], mi["T_prop"], mi["T1"], mi["tau"], w)
        g = closed_inner_response(inner_gains.Kc, inner_gains.Kd, gi, w) * \
            side_response(ms["K"], ms["T2"], ms["tau"], w)
        return g[0], w
    m = models[loop.value]
    w = frequency_grid(m["T_prop"], m["T1"], m["tau"])
    return inner_response(m["K"], m["T_prop"], m["T1"], m["tau"], w)[0], w


def score_gains(models: Mapping[str, Mapping[str, float]],
                gains: Mapping[Loop, PD]) -> dict[Loop, LoopScore]:
    """J (%) and phase margin of each loop's gains on the true process.

    For x and y the attitude gains in ``gains`` (pitch for x, roll for y) define the
    true cascade; without them that side loop is skipped.
    """
    out: dict[Loop, LoopScore] = {}
    for loop, pd in gains.items():
        inner = gains.get(_SIDE_INNER.get(loop, loop)) if loop in _SIDE_INNER else None
        if loop in _SIDE_INNER and inner is None:
            continue
        G, w = true_response(models, loop, inner)
        best = optimal_pd(G, w)
        J = deterioration(pd, G, w, best.ise)
        m = margins((pd.Kc + pd.Kd * 1j * w) * G, w)
        out[loop] = LoopScore(loop, pd, best.pd, J, float(m.pm_deg), bool(m.stable))
    return out
