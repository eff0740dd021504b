"""Score tuned gains against the optimal PD of a simulated airframe's true linear models.

Used by the benchmark, the end-to-end tests and the demo: the bundled SITL knows
its own small-signal models (:meth:`mrft_gcs.sitl.Airframe.linear_models`), so
the deterioration ``J`` (docs/method.md, eq. 17) of the gains a tune wrote can be
computed exactly. For x and y the process is the true cascade: the closed
attitude loop under the attitude gains *actually in use*, then the side part. On
the attitude path that closed loop is the autopilot's own cascade under its own
parameters (:func:`onboard_attitude_response`, the SITL's PX4-style structure).

:func:`score_written` scores what a tune *wrote*: the parameter set on the loop the
autopilot closes with it (its onboard delays, its loop rates as a sample-and-hold, its
controller structure: PX4's rate K and D-on-measurement low-pass, or ArduPilot's square-root
angle controller linearised, rate target filter and D on the error), per vehicle
(:class:`mrft_gcs.sitl.OnboardSpec`), beside the ground-station-side figures of the gains
identified there. The general controller ``u = Cr r - Cy y`` is scored as a PD is: the
ISE of the unit-step error ``E = (1 + G (Cy - Cr)) / (s (1 + G Cy))`` against that of the
optimal PD of the same true process, and the margins of ``L = Cy G``.

That ``J`` (the headline, the method's definition) counts what the autopilot's structure costs
as well as what the tune did. :func:`structure_floor` separates the two: the best two written
numbers can do on the vehicle's own structure (ISE-optimal, the same PM >= 20 deg as the ideal
PD), so each loop also reads ``J`` of the floor against the ideal PD (what the structure costs,
0 where the written parameters close exactly a PD) and ``J`` of the written gains against the
floor (what the tune left on the table).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.optimize import minimize

from mrft_gcs.loops import SIDE_INNER, Loop
from mrft_gcs.pd_design import PM_MIN_DEG, deterioration, frequency_grid, margins, optimal_pd
from mrft_gcs.plant import PD, closed_inner_response, inner_response, side_response

if TYPE_CHECKING:
    from mrft_gcs.sitl.airframe import Airframe, OnboardSpec

__all__ = ["LoopScore", "StepFigures", "true_response", "score_gains", "step_figures",
           "onboard_attitude_response", "WrittenScore", "score_written", "onboard_process",
           "onboard_controller", "general_ise", "StructureFloor", "structure_floor"]


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
    if loop in SIDE_INNER:
        mi = models[SIDE_INNER[loop].value]
        ms = models[loop.value]
        w = frequency_grid(mi["T_prop"], mi["T1"], mi["tau"], extra_T=(ms["T2"], ms["tau"]))
        if attitude_params is not None:
            t_att = onboard_attitude_response(mi, attitude_params,
                                              SIDE_INNER[loop].value.upper(), w)
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
        inner = gains.get(SIDE_INNER.get(loop, loop)) if loop in SIDE_INNER else None
        if loop in SIDE_INNER and inner is None and attitude_params is None:
            continue
        G, w = true_response(models, loop, inner, attitude_params)
        best = optimal_pd(G, w)
        J = deterioration(pd, G, w, best.ise)
        m = margins((pd.Kc + pd.Kd * 1j * w) * G, w)
        out[loop] = LoopScore(loop, pd, best.pd, J, float(m.pm_deg), bool(m.stable))
    return out


# ----------------------------------------------------------------- written gains, onboard
#: the SITL's velocity-D low-pass (MPC_VELD_LP), Hz
_VELD_CUTOFF_HZ = 5.0
#: the SITL's physics step, s: the linear models already stand for a loop closed at it
_PHYSICS_DT_S = 0.001
_AXIS = {Loop.ROLL: "ROLL", Loop.PITCH: "PITCH"}


@dataclass(frozen=True)
class WrittenScore:
    """One written loop scored two ways.

    Attributes
    ----------
    onboard : LoopScore
        The written parameters on the loop the autopilot closes (``gains`` is their PD
        equivalent, ``optimal`` the optimal PD of the true onboard process).
    gcs : LoopScore or None
        The identified PD on the true ground-station-side process (the model with the
        ground station's delay added): the loop the tune flew; None where not asked.
    """

    loop: Loop
    onboard: LoopScore
    gcs: LoopScore | None
    #: the best the autopilot's own structure allows on the same truth (None: not asked)
    floor: StructureFloor | None = None

    @property
    def J_vs_floor_pct(self) -> float:
        """``J`` of the written parameters against the structure's best (%; NaN: no floor)."""
        if self.floor is None:
            return float("nan")
        return ((1.0 + self.onboard.J_pct / 100.0) / (1.0 + self.floor.J_pct / 100.0)
                - 1.0) * 100.0


def _lowpass(s: np.ndarray, hz: float) -> np.ndarray | float:
    return 1.0 / (1.0 + s / (2 * np.pi * hz)) if hz > 0 else 1.0


def _hold(s: np.ndarray, period_s: float) -> np.ndarray:
    """Sample-and-hold at ``period_s`` beyond the physics step the models already hold."""
    def zoh(t: float) -> np.ndarray:
        return (1.0 - np.exp(-s * t)) / (s * t)

    return zoh(period_s) / zoh(_PHYSICS_DT_S) if period_s > _PHYSICS_DT_S * 1.0001 else \
        np.ones_like(s)


def general_ise(Cr: np.ndarray, Cy: np.ndarray, G: np.ndarray, w: np.ndarray) -> float:
    """ISE of the unit-step error under ``u = Cr r - Cy y`` (stability not checked).

    Equals :func:`mrft_gcs.pd_design.ise` for a PD (``Cr = Kc``, ``Cy = Kc + Kd s``).
    """
    s = 1j * w
    e2 = np.abs((1.0 + G * (Cy - Cr)) / (s * (1.0 + G * Cy))) ** 2
    body = np.trapezoid(e2 * w, np.log(w))
    return float((body + e2[0] * w[0] + 1.0 / w[-1]) / np.pi)


def _attitude_controller(spec: OnboardSpec, params: Mapping[str, float], axis: str,
                         s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pa = params[f"MC_{axis}_P"]  # ArduPilot's square root, linearised: P for small errors
    pre = f"MC_{axis}RATE"
    p, i, d = (params[f"{pre}_{k}"] for k in ("P", "I", "D"))
    ff = params.get(f"{pre}_FF", 0.0)
    Fd = _lowpass(s, spec.dgyro_cutoff_hz)
    if spec.style == "ardupilot":
        c = p + i / s + d * s * Fd  # on the error of the filtered target; no K
        Cr = (c + ff) * _lowpass(s, spec.target_cutoff_hz) * pa
        return Cr, Cr + c * s
    kr = params[f"{pre}_K"]
    c = kr * (p + i / s)
    Cr = (c + ff) * pa
    return Cr, Cr + c * s + kr * d * s * s * Fd


def _position_controller(params: Mapping[str, float], prefix: str, gain: float,
                         s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pos_p = params[f"{prefix}_P"]
    vp, vi, vd = (params[f"{prefix}_VEL_{k}_ACC"] for k in ("P", "I", "D"))
    c = gain * (vp + vi / s)
    Cr = c * pos_p
    return Cr, Cr + c * s + gain * vd * s * s * _lowpass(s, _VELD_CUTOFF_HZ)


def onboard_controller(airframe: Airframe, loop: Loop, params: Mapping[str, float],
                       w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(Cr, Cy)`` of the autopilot's loop ``loop`` under ``params``: ``u = Cr r - Cy y``.

    Units: roll/pitch normalised torque per rad, altitude normalised thrust per m, x/y
    attitude set point (rad) per m. Linearised (no limits; square root as its slope at 0).
    """
    s = 1j * np.asarray(w, float)
    g = 9.80665
    if loop in _AXIS:
        return _attitude_controller(airframe.onboard, params, _AXIS[loop], s)
    if loop is Loop.ALTITUDE:
        return _position_controller(params, "MPC_Z", params["MPC_THR_HOVER"] / g, s)
    return _position_controller(params, "MPC_XY", 1.0 / g, s)


def _true_models(airframe: Airframe) -> dict[str, dict[str, float]]:
    """The linear models with the small-signal part of the undeclared effects: a thrust
    curve changes the slope of thrust against command at hover (every inner loop's K)."""
    models = {k: dict(v) for k, v in airframe.linear_models().items()}
    a = airframe.effects.thrust_curve
    if a:
        f = airframe.hover_thrust  # force at hover over full thrust
        c = (-(1 - a) + np.sqrt((1 - a) ** 2 + 4 * a * f)) / (2 * a)  # its command
        for lp in ("roll", "pitch", "altitude"):
            models[lp]["K"] *= (1 - a) + 2 * a * c
    return models


def _inner(airframe: Airframe, models, loop: Loop, w: np.ndarray, extra_delay_s: float = 0.0
           ) -> np.ndarray:
    """An inner loop's true process, with an undeclared sensor low-pass where there is one
    (the angle and the position are both filtered: the side part keeps its relation)."""
    m = models[loop.value]
    G = inner_response(m["K"], m["T_prop"], m["T1"], m["tau"] + extra_delay_s, w)[0]
    return G * _lowpass(1j * w, airframe.effects.sensor_lpf)


def onboard_process(airframe: Airframe, loop: Loop, params: Mapping[str, float]
                    ) -> tuple[np.ndarray, np.ndarray]:
    """``(G(jw), w)``: the true process the autopilot's ``loop`` controls.

    The airframe's linear model with its onboard delays, held at the loop's rate
    (attitude: ``loop_hz``; altitude and x/y: ``position_loop_hz``); x and y through the
    onboard closed attitude loop under ``params`` (pitch for x, roll for y). Of the
    undeclared effects, the linear ones are in: a sensor low-pass, and a thrust curve's
    slope at hover; the others (limits, dead band, saturation) are large-signal.
    """
    models = _true_models(airframe)
    spec = airframe.onboard
    if loop in SIDE_INNER:
        mi, ms = models[SIDE_INNER[loop].value], models[loop.value]
        w = frequency_grid(mi["T_prop"], mi["T1"], mi["tau"], extra_T=(ms["T2"], ms["tau"]))
        s = 1j * w
        gi = _inner(airframe, models, SIDE_INNER[loop], w) * _hold(s, 1.0 / spec.loop_hz)
        Cr, Cy = onboard_controller(airframe, SIDE_INNER[loop], params, w)
        t_att = gi * Cr / (1.0 + gi * Cy)
        G = t_att * side_response(ms["K"], ms["T2"], ms["tau"], w)[0]
        return G * _hold(s, 1.0 / spec.position_loop_hz), w
    m = models[loop.value]
    w = frequency_grid(m["T_prop"], m["T1"], m["tau"])
    rate = spec.loop_hz if loop in _AXIS else spec.position_loop_hz
    return _inner(airframe, models, loop, w) * _hold(1j * w, 1.0 / rate), w


def _pd_equivalent(loop: Loop, params: Mapping[str, float]) -> PD:
    """The PD a parameter set amounts to (docs/writing-gains.md), ignoring I, D, FF and filters."""
    if loop in _AXIS:
        a = _AXIS[loop]
        kd = params[f"MC_{a}RATE_P"] * params.get(f"MC_{a}RATE_K", 1.0)
        return PD(params[f"MC_{a}_P"] * kd, kd)
    if loop is Loop.ALTITUDE:
        kd = params["MPC_Z_VEL_P_ACC"] * params["MPC_THR_HOVER"] / 9.80665
        return PD(params["MPC_Z_P"] * kd, kd)
    kd = params["MPC_XY_VEL_P_ACC"] / 9.80665
    return PD(params["MPC_XY_P"] * kd, kd)


def _score(loop: Loop, gains: PD, Cr: np.ndarray, Cy: np.ndarray, G: np.ndarray,
           w: np.ndarray) -> LoopScore:
    best = optimal_pd(G, w)
    m = margins(Cy * G, w)
    J = ((general_ise(Cr, Cy, G, w) - best.ise) / best.ise * 100.0 if m.stable else np.inf)
    return LoopScore(loop, gains, best.pd, float(J), float(m.pm_deg), bool(m.stable))


def _gcs_score(airframe: Airframe, loop: Loop, pd: PD, identified: Mapping[Loop, PD],
               delay_s: float) -> LoopScore | None:
    # the GCS sees angle and position equally late: the side part keeps its relative delay
    models = _true_models(airframe)
    if loop in SIDE_INNER:
        inner = identified.get(SIDE_INNER[loop])
        if inner is None:
            return None
        mi, ms = models[SIDE_INNER[loop].value], models[loop.value]
        w = frequency_grid(mi["T_prop"], mi["T1"], mi["tau"] + delay_s,
                           extra_T=(ms["T2"], ms["tau"]))
        gi = _inner(airframe, models, SIDE_INNER[loop], w, delay_s)
        G = closed_inner_response(inner.Kc, inner.Kd, gi, w)[0] \
            * side_response(ms["K"], ms["T2"], ms["tau"], w)[0]
    else:
        m = models[loop.value]
        w = frequency_grid(m["T_prop"], m["T1"], m["tau"] + delay_s)
        G = _inner(airframe, models, loop, w, delay_s)
    s = 1j * w
    return _score(loop, pd, pd.Kc + 0 * s, pd.Kc + pd.Kd * s, G, w)


@dataclass(frozen=True)
class StructureFloor:
    """The best two written numbers on an autopilot's loop structure (its floor).

    Attributes
    ----------
    gains : PD
        Their PD equivalent (angle P x rate P, rate P; as the written gains).
    J_pct : float
        Their ``J`` against the ideal PD of the same truth (%; 0 where the structure is a PD).
    pm_deg : float
        Their phase margin on the truth (deg; >= :data:`~mrft_gcs.pd_design.PM_MIN_DEG`).
    plain : bool
        The written parameters close exactly a PD: the floor is the ideal PD.
    """

    gains: PD
    J_pct: float
    pm_deg: float
    plain: bool


def _with_pd(loop: Loop, params: Mapping[str, float], pd: PD) -> dict[str, float]:
    """``params`` with the two written numbers set for ``pd`` (the inverse of
    :func:`_pd_equivalent`); an attitude loop's rate D at 0: the floor is that of the two
    numbers, which a rate D written beside them may take the loop below."""
    p = dict(params)
    if loop in _AXIS:
        a = _AXIS[loop]
        p[f"MC_{a}RATE_P"] = pd.Kd / params.get(f"MC_{a}RATE_K", 1.0)
        p[f"MC_{a}_P"] = pd.Kc / pd.Kd
        p[f"MC_{a}RATE_D"] = 0.0
    elif loop is Loop.ALTITUDE:
        p["MPC_Z_VEL_P_ACC"] = pd.Kd * 9.80665 / params["MPC_THR_HOVER"]
        p["MPC_Z_P"] = pd.Kc / pd.Kd
    else:
        p["MPC_XY_VEL_P_ACC"] = pd.Kd * 9.80665
        p["MPC_XY_P"] = pd.Kc / pd.Kd
    return p


def structure_floor(airframe: Airframe, loop: Loop, params: Mapping[str, float],
                    pm_min_deg: float = PM_MIN_DEG) -> StructureFloor:
    """The ISE-optimal written gains of ``loop`` on the autopilot's own structure.

    The loop's two written numbers (angle or position P, rate or velocity P) are searched on
    the true onboard process and controller (:func:`onboard_process`,
    :func:`onboard_controller`) with every other parameter as in ``params`` (filters, I,
    FF, velocity D; an attitude loop's rate D at 0), under phase margin ``pm_min_deg``
    there: the best the structure allows, scored as :func:`score_written` scores the
    written gains. A structure that closes exactly a PD has
    the ideal PD as its floor (``J`` 0).

    Examples
    --------
    >>> from mrft_gcs.sitl import load_airframe
    >>> from mrft_gcs.sitl.onboard import ParamStore
    >>> f = structure_floor(load_airframe("qdrone"), Loop.ROLL, ParamStore(0.45).values)
    >>> f.J_pct <= 1e-6 or not f.plain, f.pm_deg >= 20.0 - 1e-6
    (True, True)
    """
    G, w = onboard_process(airframe, loop, params)
    best = optimal_pd(G, w, pm_min_deg)
    s = 1j * w

    def paths(pd: PD) -> tuple[np.ndarray, np.ndarray]:
        return onboard_controller(airframe, loop, _with_pd(loop, params, pd), w)

    Cr, Cy = paths(best.pd)
    ref = np.abs(Cy) + 1e-12
    if (np.max(np.abs(Cr - best.pd.Kc) / ref) < 1e-9
            and np.max(np.abs(Cy - best.pd.Kc - best.pd.Kd * s) / ref) < 1e-9):
        return StructureFloor(best.pd, 0.0, float(best.margins.pm_deg), True)

    def pm_of(pd: PD) -> float:
        m = margins(paths(pd)[1] * G, w)
        return float(m.pm_deg) if m.stable else -np.inf

    def cost(x: np.ndarray) -> float:
        pd = PD(float(np.exp(x[0])), float(np.exp(x[1])))
        pm = pm_of(pd)
        if pm == -np.inf:
            return 1e12
        q = general_ise(*paths(pd), G, w)
        short = max(0.0, pm_min_deg - pm)
        return q * (1.0 + 0.05 * short + 0.02 * short ** 2) if np.isfinite(q) else 1e12

    res = min((minimize(cost, np.log([x0.Kc, x0.Kd]), method="Nelder-Mead",
                        options={"xatol": 1e-4, "fatol": 1e-9, "maxiter": 600})
               for x0 in (best.pd, PD(best.pd.Kc * 0.8, best.pd.Kd))), key=lambda r: r.fun)
    g = PD(float(np.exp(res.x[0])), float(np.exp(res.x[1])))
    k, pm = 1.0, pm_of(g)
    while pm < pm_min_deg and k > 1e-3:  # the search ended short of the margin: less gain
        k *= 0.99
        pm = pm_of(PD(g.Kc * k, g.Kd * k))
    g = PD(g.Kc * k, g.Kd * k)
    J = (general_ise(*paths(g), G, w) - best.ise) / best.ise * 100.0
    return StructureFloor(g, float(J), float(pm), False)


def score_written(airframe: Airframe, params: Mapping[str, float], loops=None,
                  identified: Mapping[Loop, PD] | None = None,
                  gcs_delay_s: float | Mapping[Loop, float] = 0.0,
                  floor: bool = False) -> dict[Loop, WrittenScore]:
    """Score written parameters on the vehicle's true onboard loops (and the GCS side).

    Parameters
    ----------
    airframe : Airframe
        The simulated vehicle (its linear models and :class:`OnboardSpec`).
    params : mapping
        The vehicle's parameter values after the write (every ``MC_*``/``MPC_*`` name the
        loops use; :attr:`mrft_gcs.sitl.onboard.ParamStore.values` has them all).
    loops : iterable of Loop, optional
        The loops to score (default: roll, pitch, altitude, x, y).
    identified : mapping, optional
        The PDs the ground station flew (identified); with them each loop also gets its
        ``gcs`` score: that PD on the true process with ``gcs_delay_s`` more delay (s,
        one value or per loop; x/y through the identified attitude PD).
    floor : bool
        Also the best the autopilot's structure allows on each loop
        (:func:`structure_floor`, :attr:`WrittenScore.J_vs_floor_pct`).

    Returns
    -------
    dict
        ``{Loop: WrittenScore}``; ``onboard.J_pct`` is ``inf`` for an unstable loop.

    Examples
    --------
    >>> from mrft_gcs.sitl import load_airframe
    >>> from mrft_gcs.sitl.onboard import ParamStore
    >>> sc = score_written(load_airframe("qdrone"), ParamStore(0.45).values, [Loop.ROLL])
    >>> sc[Loop.ROLL].onboard.stable
    True
    """
    out: dict[Loop, WrittenScore] = {}
    for loop in loops or (Loop.ROLL, Loop.PITCH, Loop.ALTITUDE, Loop.X, Loop.Y):
        G, w = onboard_process(airframe, loop, params)
        Cr, Cy = onboard_controller(airframe, loop, params, w)
        onboard = _score(loop, _pd_equivalent(loop, params), Cr, Cy, G, w)
        gcs = None
        if identified is not None and loop in identified:
            d = gcs_delay_s.get(loop, 0.0) if isinstance(gcs_delay_s, Mapping) else gcs_delay_s
            gcs = _gcs_score(airframe, loop, identified[loop], identified, float(d))
        fl = structure_floor(airframe, loop, params) if floor else None
        out[loop] = WrittenScore(loop, onboard, gcs, fl)
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
