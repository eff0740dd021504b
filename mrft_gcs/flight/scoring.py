"""Score tuned gains against the optimal PD of a simulated airframe's true linear models.

Used by the benchmark, the end-to-end tests and the demo: the bundled SITL knows
its own small-signal models (:meth:`mrft_gcs.sitl.Airframe.linear_models`), so
the deterioration ``J`` (SPEC 2, eq. 17) of the gains a tune wrote can be
computed exactly. For x and y the process is the true cascade: the closed
attitude loop under the attitude gains *actually in use*, then the side part. On
the attitude path that closed loop is the autopilot's own cascade under its own
parameters (:func:`onboard_attitude_response`, the SITL's PX4-style structure).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from mrft_gcs.loops import Loop
from mrft_gcs.pd_design import deterioration, frequency_grid, margins, optimal_pd
from mrft_gcs.plant import PD, closed_inner_response, inner_response, side_response

__all__ = ["LoopScore", "StepFigures", "true_response", "score_gains", "step_figures",
           "onboard_attitude_response"]

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


#: The SITL's rate-D low-pass (``IMU_DGYRO_CUTOFF``, Hz), see :mod:`mrft_gcs.sitl.onboard`.
_DGYRO_CUTOFF_HZ = 30.0


def onboard_attitude_response(model: Mapping[str, float], params: Mapping[str, float],
                              axis: str, w: np.ndarray) -> np.ndarray:
    """Closed attitude loop (set point to measured angle) of the SITL's onboard cascade.

    The structure of :mod:`mrft_gcs.sitl.onboard` (PX4's): ``rate_sp = P_angle e``,
    ``u = K_rate (P (rate_sp - rate) + I/s (rate_sp - rate) - D s F(s) rate) + FF rate_sp``
    with ``F`` the 30 Hz low-pass of the rate derivative, on the true model ``model``
    (``K, T_prop, T1, tau``) of that axis. ``axis`` is ``"ROLL"`` or ``"PITCH"``; ``params``
    the vehicle's ``MC_*`` values. Small-signal (no rate or integrator limits); the
    1 kHz loop is taken as continuous.
    """
    s = 1j * np.asarray(w, float)
    G = inner_response(model["K"], model["T_prop"], model["T1"], model["tau"], w)[0]
    pa = params[f"MC_{axis}_P"]
    pre = f"MC_{axis}RATE"
    kr, p, i, d = (params[f"{pre}_{k}"] for k in ("K", "P", "I", "D"))
    ff = params.get(f"{pre}_FF", 0.0)
    F = 1.0 / (1.0 + s / (2 * np.pi * _DGYRO_CUTOFF_HZ))
    c = kr * (p + i / s)  # on the rate error
    # u = (c + ff) pa (r - y) - c s y - kr d s^2 F y,  y = G u
    return G * (c + ff) * pa / (1.0 + G * ((c + ff) * pa + c * s + kr * d * s * s * F))


def true_response(models: Mapping[str, Mapping[str, float]], loop: Loop,
                  inner_gains: PD | None = None,
                  attitude_params: Mapping[str, float] | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """``(G(jw), w)`` of the true process of ``loop``.

    Side loops need the attitude loop in use: ``inner_gains`` (the deployed PD on the
    attitude axis, torque path) or ``attitude_params`` (the autopilot's own ``MC_*``
    parameters, attitude path: :func:`onboard_attitude_response`).
    """
    if loop in _SIDE_INNER:
        mi = models[_SIDE_INNER[loop].value]
        ms = models[loop.value]
        w = frequency_grid(mi["T_prop"], mi["T1"], mi["tau"], extra_T=(ms["T2"], ms["tau"]))
        if attitude_params is not None:
            t_att = onboard_attitude_response(mi, attitude_params,
                                              _SIDE_INNER[loop].value.upper(), w)
        elif inner_gains is not None:
            gi = inner_response(mi["K"], mi["T_prop"], mi["T1"], mi["tau"], w)
            t_att = closed_inner_response(inner_gains.Kc, inner_gains.Kd, gi, w)[0]
        else:
            raise ValueError(f"{loop.value}: the true side process needs the attitude gains")
        g = t_att * side_response(ms["K"], ms["T2"], ms["tau"], w)[0]
        return g, w
    m = models[loop.value]
    w = frequency_grid(m["T_prop"], m["T1"], m["tau"])
    return inner_response(m["K"], m["T_prop"], m["T1"], m["tau"], w)[0], w


def score_gains(models: Mapping[str, Mapping[str, float]],
                gains: Mapping[Loop, PD],
                attitude_params: Mapping[str, float] | None = None) -> dict[Loop, LoopScore]:
    """J (%) and phase margin of each loop's gains on the true process.

    For x and y the attitude gains in ``gains`` (pitch for x, roll for y) define the
    true cascade; without them that side loop is skipped. With ``attitude_params``
    (the attitude path: the autopilot flies its own attitude loop) the cascade is the
    onboard one under those parameters instead.
    """
    out: dict[Loop, LoopScore] = {}
    for loop, pd in gains.items():
        if pd is None:
            continue
        inner = gains.get(_SIDE_INNER.get(loop, loop)) if loop in _SIDE_INNER else None
        if loop in _SIDE_INNER and inner is None and attitude_params is None:
            continue
        G, w = true_response(models, loop, inner, attitude_params)
        best = optimal_pd(G, w)
        J = deterioration(pd, G, w, best.ise)
        m = margins((pd.Kc + pd.Kd * 1j * w) * G, w)
        out[loop] = LoopScore(loop, pd, best.pd, J, float(m.pm_deg), bool(m.stable))
    return out


@dataclass(frozen=True)
class StepFigures:
    """Step-response figures: times in s, overshoot in % of the step, error in m."""

    rise_time_s: float
    overshoot_pct: float
    settling_time_s: float
    steady_error_m: float


def step_figures(t_s: np.ndarray, y: np.ndarray, y0: float, y1: float,
                 band: float = 0.05, tail_s: float = 1.0) -> StepFigures:
    """Rise time (10-90 %), overshoot, settling time (within ``band`` of the step for good)
    and steady error (mean over the last ``tail_s``) of a step from ``y0`` to ``y1``.

    >>> t = np.linspace(0, 5, 501)
    >>> f = step_figures(t, 1 - np.exp(-t / 0.5), 0.0, 1.0)
    >>> round(f.rise_time_s, 2), round(f.overshoot_pct, 1)
    (1.1, 0.0)
    """
    t = np.asarray(t_s, float) - float(t_s[0])
    r = (np.asarray(y, float) - y0) / (y1 - y0)
    i10 = int(np.argmax(r >= 0.1)) if np.any(r >= 0.1) else None
    i90 = int(np.argmax(r >= 0.9)) if np.any(r >= 0.9) else None
    rise = float(t[i90] - t[i10]) if i10 is not None and i90 is not None else float("nan")
    over = float(max(0.0, r.max() - 1.0) * 100.0)
    outside = np.nonzero(np.abs(r - 1.0) > band)[0]
    settle = float(t[outside[-1] + 1]) if outside.size and outside[-1] + 1 < t.size else \
        (0.0 if not outside.size else float("nan"))
    tail = t >= t[-1] - tail_s
    steady = float(np.mean(np.asarray(y, float)[tail]) - y1)
    return StepFigures(rise, over, settle, steady)
