"""Written gains designed on the loop the autopilot will close: its controller structure.

A PD ``u = Kc e - Kd w`` is written as angle P ``Kc/Kd`` and rate P ``Kd`` with rate I = D = 0
(docs/writing-gains.md). On PX4 that *is* the PD. ArduPilot's rate controller low-passes its
rate target (``ATC_RAT_RLL_FLTT`` / ``ATC_RAT_PIT_FLTT``, 20 Hz by default) before the rate
error, so the loop it closes with the same two numbers is

``u = Kc F r - (Kc F + Kd s) y``,  ``F = 1 / (1 + s / (2 pi f_t))``

(the square-root angle controller is linear for the small errors the ISE weighs): the filter
costs phase inside the loop and delays the response to the set point. Gains designed as a PD
for it are at once less damped and slower than designed (measured on the random population:
their J on the onboard truth 11-15 % where the best the structure allows is 9-10 %).

:func:`structured_retarget` designs the written gains on that structure: the identified model
with the onboard delay (the GCS delay re-targeted out, :mod:`mrft_gcs.flight.onboard`), the
controller with the vehicle's own filter, minimising the ISE of the unit-step error under
phase margin :data:`~mrft_gcs.pd_design.PM_MIN_DEG` there and
:data:`~mrft_gcs.flight.onboard.PM_ROBUST_DEG` at the most onboard delay that is plausible.

The filter is read from the vehicle (:data:`TARGET_FILTER_PARAMS`); a vehicle without the
parameter gets its family's documented default (:data:`DEFAULT_TARGET_HZ`: ArduPilot 20 Hz,
PX4 none). A structure with no target filter keeps the gains of
:func:`~mrft_gcs.flight.onboard.robust_onboard_gains` unchanged. D filters, the loop rate and
I do not enter: D and I are written as 0, and the rate loop's sample-and-hold was in the
loop the relay tests identified.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from mrft_gcs.flight.onboard import PM_ROBUST_DEG, Retarget
from mrft_gcs.flight.scoring import general_ise
from mrft_gcs.identify import Identification
from mrft_gcs.loops import Loop
from mrft_gcs.pd_design import PM_MIN_DEG, frequency_grid, margins, optimal_pd
from mrft_gcs.plant import PD, InnerModel, inner_response

__all__ = ["TARGET_FILTER_PARAMS", "DEFAULT_TARGET_HZ", "OnboardStructure", "read_structure",
           "vehicle_structure",
           "structure_controller", "StructuredDesign", "structured_pd", "structured_retarget"]

#: the rate-target low-pass of each attitude axis, under ArduPilot's names (Hz)
TARGET_FILTER_PARAMS: dict[Loop, str] = {Loop.ROLL: "ATC_RAT_RLL_FLTT",
                                          Loop.PITCH: "ATC_RAT_PIT_FLTT"}
#: the rate-target low-pass a family's firmware has where the vehicle does not say (Hz;
#: ArduCopter's AC_ATC_MULTI_RATE_RP_FILT_HZ; PX4's rate controller has none)
DEFAULT_TARGET_HZ: dict[str, float] = {"ardupilot": 20.0, "px4": 0.0}


@dataclass(frozen=True)
class OnboardStructure:
    """How the autopilot closes an attitude loop on written gains.

    Attributes
    ----------
    target_hz : float
        Low-pass on the rate target inside the loop (Hz; 0: none, the loop is the PD).
    source : str
        Where ``target_hz`` came from (a parameter read, or the family's default).
    """

    target_hz: float = 0.0
    source: str = ""

    @property
    def plain(self) -> bool:
        """The written parameters close exactly the PD."""
        return not self.target_hz > 0


def read_structure(loop: Loop, values: Mapping[str, float], family: str = "") -> OnboardStructure:
    """The structure of ``loop`` from parameter ``values`` read from the vehicle.

    ``values`` holds what the vehicle answered (a name it lacks is absent); ``family`` is the
    autopilot family (``"px4"``, ``"ardupilot"``) for the default.

    >>> read_structure(Loop.ROLL, {"ATC_RAT_RLL_FLTT": 12.5}).target_hz
    12.5
    >>> read_structure(Loop.PITCH, {}, "ardupilot").source
    "ArduPilot's default 20 Hz (ATC_RAT_PIT_FLTT not read)"
    >>> read_structure(Loop.ROLL, {}, "px4").plain
    True
    """
    name = TARGET_FILTER_PARAMS.get(loop)
    if name is None:
        return OnboardStructure(0.0, "no rate target on this loop")
    v = values.get(name)
    if v is not None and math.isfinite(v) and v >= 0:
        return OnboardStructure(float(v), f"{name} = {v:g} Hz read")
    hz = DEFAULT_TARGET_HZ.get(family, 0.0)
    if hz > 0:
        return OnboardStructure(hz, f"ArduPilot's default {hz:g} Hz ({name} not read)")
    return OnboardStructure(0.0, "no rate target filter")


def vehicle_structure(read: Callable[[str], float | None], family: str = ""
                      ) -> dict[Loop, OnboardStructure]:
    """The roll and pitch structures of a vehicle, asking it through ``read`` (a parameter's
    value, None where the vehicle has no such parameter).

    A vehicle without the roll name is taken to have neither (ArduPilot has both), so a PX4
    costs one unanswered read.

    >>> st = vehicle_structure({"ATC_RAT_RLL_FLTT": 15.0, "ATC_RAT_PIT_FLTT": 18.0}.get)
    >>> st[Loop.ROLL].target_hz, st[Loop.PITCH].target_hz
    (15.0, 18.0)
    >>> vehicle_structure({}.get, "px4")[Loop.PITCH].plain
    True
    """
    values: dict[str, float] = {}
    for lp in (Loop.ROLL, Loop.PITCH):
        name = TARGET_FILTER_PARAMS[lp]
        v = read(name)
        if v is None:
            break
        values[name] = float(v)
    return {lp: read_structure(lp, values, family) for lp in (Loop.ROLL, Loop.PITCH)}


def structure_controller(gains: PD, st: OnboardStructure, w: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
    """``(Cr, Cy)`` of the written ``gains`` under ``st``: ``u = Cr r - Cy y`` on ``w`` (rad/s).

    >>> Cr, Cy = structure_controller(PD(2.0, 0.1), OnboardStructure(), np.array([1.0]))
    >>> complex(Cr[0]), complex(Cy[0])
    ((2+0j), (2+0.1j))
    """
    s = 1j * np.asarray(w, float)
    f = 1.0 / (1.0 + s / (2 * np.pi * st.target_hz)) if st.target_hz > 0 else np.ones_like(s)
    return gains.Kc * f, gains.Kc * f + gains.Kd * s


@dataclass(frozen=True)
class StructuredDesign:
    """Gains for a structure: ISE of the unit-step error and phase margins (deg)."""

    gains: PD
    ise: float
    pm_deg: float
    pm_worst_deg: float


def _pm(gains: PD, st: OnboardStructure, G: np.ndarray, w: np.ndarray) -> float:
    m = margins(structure_controller(gains, st, w)[1] * G, w)
    return float(m.pm_deg) if m.stable else -math.inf


def structured_pd(G: np.ndarray, w: np.ndarray, st: OnboardStructure, *,
                  pm_min_deg: float = PM_MIN_DEG, worst: Sequence[np.ndarray] = (),
                  pm_worst_deg: float = PM_ROBUST_DEG,
                  starts: Sequence[PD] = ()) -> StructuredDesign:
    """ISE-optimal written gains for the loop ``G`` closes under ``st``.

    Parameters
    ----------
    G : array (m,)
        The process on ``w`` (rad/s).
    st : OnboardStructure
    pm_min_deg : float
        Phase margin required on ``G`` (deg).
    worst : sequence of arrays (m,)
        Other processes the gains must hold ``pm_worst_deg`` on (the most onboard delay).
    starts : sequence of PD
        Starting points besides the plain optimal PD of ``G``.

    Both margins are honoured: the optimum is scaled down (a pure gain change) until they
    hold where the penalised search ends short of them.

    Examples
    --------
    >>> w = frequency_grid(0.02, 0.5, 0.008)
    >>> G = inner_response(100.0, 0.02, 0.5, 0.008, w)[0]
    >>> d = structured_pd(G, w, OnboardStructure(15.0))
    >>> d.pm_deg >= 20.0 - 1e-6, d.gains.Kc > 0
    (True, True)
    """
    def pm_all(g: PD) -> tuple[float, float]:
        return _pm(g, st, G, w), min((_pm(g, st, Gw, w) for Gw in worst), default=math.inf)

    def cost(x: np.ndarray) -> float:
        g = PD(float(np.exp(x[0])), float(np.exp(x[1])))
        pm, pmw = pm_all(g)
        if pm == -math.inf or pmw == -math.inf:  # unstable (no worst case: pmw is +inf)
            return 1e12
        Cr, Cy = structure_controller(g, st, w)
        q = general_ise(Cr, Cy, G, w)
        short = max(0.0, pm_min_deg - pm) + max(0.0, pm_worst_deg - pmw)
        return q * (1.0 + 0.05 * short + 0.02 * short ** 2) if np.isfinite(q) else 1e12

    best = None
    for s0 in (*starts, optimal_pd(G, w).pd):
        res = minimize(cost, np.log([s0.Kc, s0.Kd]), method="Nelder-Mead",
                       options={"xatol": 1e-4, "fatol": 1e-9, "maxiter": 600})
        if best is None or res.fun < best.fun:
            best = res
    assert best is not None
    g = PD(float(np.exp(best.x[0])), float(np.exp(best.x[1])))
    pm, pmw = pm_all(g)
    k = 1.0
    while (pm < pm_min_deg or pmw < pm_worst_deg) and k > 1e-3:
        k *= 0.98  # the search ended short of a margin: less gain until both hold
        pm, pmw = pm_all(PD(g.Kc * k, g.Kd * k))
    g = PD(g.Kc * k, g.Kd * k)
    Cr, Cy = structure_controller(g, st, w)
    return StructuredDesign(g, general_ise(Cr, Cy, G, w), pm, pmw)


def structured_retarget(ident: Identification, rt: Retarget, st: OnboardStructure,
                        pm_min_deg: float = PM_MIN_DEG) -> Retarget:
    """``rt`` re-designed for the structure ``st`` the autopilot closes the loop with.

    The identified model with the onboard delay ``tau - d`` (``d`` the re-target aimed at,
    :attr:`Retarget.aimed_s`) is the design's process; the gains keep ``pm_min_deg`` on it
    and :data:`~mrft_gcs.flight.onboard.PM_ROBUST_DEG` with the most onboard delay that is
    plausible (``tau - gcs.lo_s`` plus the unseen extra, as
    :func:`~mrft_gcs.flight.onboard.robust_onboard_gains` checks). A plain structure, or a
    loop that is not an inner one, keeps ``rt``.

    Examples
    --------
    >>> from mrft_gcs.flight.onboard import GcsDelay, robust_onboard_gains
    >>> from mrft_gcs.loops import LoopKind
    >>> m = InnerModel(K=120.0, T_prop=0.03, T1=0.5, tau=0.015)
    >>> w = frequency_grid(m.T_prop, m.T1, m.tau)
    >>> pd = optimal_pd(inner_response(m.K, m.T_prop, m.T1, m.tau, w)[0], w).pd
    >>> i = Identification(LoopKind.ATTITUDE, m, 0, 1.0, -0.8, 0.1, 0.25, 0.03, pd)
    >>> rt = robust_onboard_gains(i, GcsDelay(0.006, 0.005, 0.01, 0.006, True))
    >>> r = structured_retarget(i, rt, OnboardStructure(15.0))
    >>> r.gains != rt.gains, r.pm_deg >= 15.0, "rate target" in r.note()
    (True, True, True)
    """
    m = ident.model
    if st.plain or not isinstance(m, InnerModel):
        return rt
    d = rt.aimed_s if rt.gcs.estimate_s > 0 else rt.delay_s
    tau_on = max(m.tau - d, 1e-4)
    lo_d = min(rt.gcs.lo_s, rt.cap_s) - rt.extra_s
    tau_worst = max(m.tau - lo_d, tau_on)
    w = frequency_grid(m.T_prop, m.T1, tau_on)
    G = inner_response(m.K, m.T_prop, m.T1, tau_on, w)[0]
    Gw = inner_response(m.K, m.T_prop, m.T1, tau_worst, w)[0]
    des = structured_pd(G, w, st, pm_min_deg=pm_min_deg, worst=(Gw,),
                        starts=(rt.gains,))
    return dataclasses.replace(rt, gains=des.gains, delay_s=round(d, 6),
                               pm_deg=des.pm_worst_deg,
                               structure=f"rate target low-pass {st.target_hz:g} Hz "
                                         f"({st.source})")
