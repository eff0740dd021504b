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
:func:`~mrft_gcs.flight.onboard.robust_onboard_gains` unchanged. The loop rate and I do not
enter: I is written as 0, and the rate loop's sample-and-hold was in the loop the relay tests
identified.

Rate D. With two numbers the filter leaves the loop 7-10 % J above the ideal PD at PM 20
deg (the structure floor, :func:`mrft_gcs.flight.scoring.structure_floor`). ArduCopter's
rate PID (``AC_PID::update_all``) differentiates the rate *error* (the FLTT-filtered target
minus the gyro), low-passed by ``ATC_RAT_*_FLTD``, so a rate D ``r Kd`` multiplies both paths
by ``1 + r s F_D``:

``u = (1 + r s F_D) (Kc F r - (Kc F + Kd s) y)``,  ``F_D = 1 / (1 + s / (2 pi f_d))``

and its lead buys back the filter's lag. ``r`` is held at ArduCopter's own default ratio
(:data:`RATE_D_OVER_P_S`, ``ATC_RAT_RLL_D`` 0.0036 over ``ATC_RAT_RLL_P`` 0.135), not
optimised: the design is linear and noise-free, where more D always looks better, while on a
vehicle D amplifies gyro noise by ``r 2 pi f_d`` over rate P (some 3.4 x at 20 Hz); at the
default ratio that is the noise every stock ArduCopter already flies with. With D the gains
stay within :data:`D_GAIN_MOVE_MAX` of the two-number design's, the angle P within
:data:`D_ANGLE_P_MOVE_MAX` of its, they keep a gain margin of :data:`D_GM_MIN` besides both
phase margins, and their crossover stays within :data:`D_WC_MAX_RATIO` of the relay cycle's
frequency: D's lead would otherwise move the crossover far above the frequency the relay
identified the model at (where the margin predicted, and checked in the air, is no longer the
vehicle's), and the angle P into the square-root controller's soft part. Where
D does not lower the design's ISE, none is written.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from mrft_gcs.flight.onboard import (
    PM_ROBUST_DEG,
    CascadeGains,
    Retarget,
    cascade_controller,
    cascade_gains,
    cascade_process,
    rate_loop_gains,
)
from mrft_gcs.flight.scoring import general_ise
from mrft_gcs.identify import Identification
from mrft_gcs.loops import Loop
from mrft_gcs.pd_design import PM_MIN_DEG, frequency_grid, margins, optimal_pd
from mrft_gcs.plant import PD, InnerModel, inner_response
from mrft_gcs.profiles import AutopilotProfile, PDGains

__all__ = ["TARGET_FILTER_PARAMS", "DEFAULT_TARGET_HZ", "D_FILTER_PARAMS", "DEFAULT_D_HZ",
           "RATE_D_OVER_P_S", "WRITE_RATE_D", "D_GAIN_MOVE_MAX", "D_GM_MIN", "D_WC_MAX_RATIO",
           "D_ANGLE_P_MOVE_MAX", "OnboardStructure", "relay_frequency",
           "read_structure", "vehicle_structure", "rate_d_values",
           "structure_controller", "StructuredDesign", "structured_pd", "structured_retarget",
           "cascade_design"]

#: the rate-target low-pass of each attitude axis, under ArduPilot's names (Hz)
TARGET_FILTER_PARAMS: dict[Loop, str] = {Loop.ROLL: "ATC_RAT_RLL_FLTT",
                                          Loop.PITCH: "ATC_RAT_PIT_FLTT"}
#: the rate-target low-pass a family's firmware has where the vehicle does not say (Hz;
#: ArduCopter's AC_ATC_MULTI_RATE_RP_FILT_HZ; PX4's rate controller has none)
DEFAULT_TARGET_HZ: dict[str, float] = {"ardupilot": 20.0, "px4": 0.0}
#: the rate-D low-pass of each attitude axis (ArduPilot's names, Hz)
D_FILTER_PARAMS: dict[Loop, str] = {Loop.ROLL: "ATC_RAT_RLL_FLTD",
                                     Loop.PITCH: "ATC_RAT_PIT_FLTD"}
#: the rate-D low-pass where the vehicle does not say (Hz; ArduCopter's
#: AC_ATC_MULTI_RATE_RPY_FILT_HZ)
DEFAULT_D_HZ = 20.0
#: rate D written per unit of rate P on a structure with a rate-target filter (s):
#: ArduCopter's defaults AC_ATC_MULTI_RATE_RP_D / AC_ATC_MULTI_RATE_RP_P
RATE_D_OVER_P_S = 0.0036 / 0.135
#: whether the design writes rate D on such a structure at all
WRITE_RATE_D = True
#: with rate D, each gain at most this many times the two-number design's: the model is
#: identified about the relay's frequency, and D's lead would otherwise carry the crossover
#: 4-5 x above it (in-process, on the random population: gain margins down to 1.15 on the truth)
D_GAIN_MOVE_MAX = 1.5
#: and a gain margin of at least this (ratio) on the nominal and the worst process
D_GM_MIN = 2.0
#: and the gain crossover on the model at most this many times the relay cycle's frequency
#: (:func:`relay_frequency`): the cycle pins the identified model there, and the model's phase
#: error grows above it; D's lead carried the crossover 2-3 x above it, where the margin on the
#: vehicle lay well off the one predicted (the in-air check's, :mod:`mrft_gcs.flight.inair`)
D_WC_MAX_RATIO = 1.5
#: and the angle P (``Kc/Kd``) at most this many times the two-number design's: ArduPilot's
#: square-root angle controller is linear only within ``accel_max / P^2`` of error, and a
#: higher P leaves larger errors to its softer part
D_ANGLE_P_MOVE_MAX = 1.25


@dataclass(frozen=True)
class OnboardStructure:
    """How the autopilot closes an attitude loop on written gains.

    Attributes
    ----------
    target_hz : float
        Low-pass on the rate target inside the loop (Hz; 0: none, the loop is the PD).
    source : str
        Where ``target_hz`` came from (a parameter read, or the family's default).
    d_over_p_s : float
        Rate D written as this share of rate P (s; 0: D written as 0). Rate D acts on the
        rate error, low-passed at ``d_hz``.
    d_hz : float
        Low-pass on the rate D term (Hz; 0: none).
    error_hz : float
        Low-pass on the rate error, before P, I and D (Hz; 0: none; ``ATC_RAT_*_FLTE``).
    gyro_hz : float
        Second-order low-pass on the gyro the rate error is taken on (Hz; 0: none;
        ``INS_GYRO_FILTER``), not on the attitude the angle error is taken on.
    """

    target_hz: float = 0.0
    source: str = ""
    d_over_p_s: float = 0.0
    d_hz: float = 0.0
    error_hz: float = 0.0
    gyro_hz: float = 0.0

    def rate_d(self, gains: PD) -> float:
        """The rate D written with ``gains`` (normalised output per rad/s^2; 0: none).

        >>> OnboardStructure(20.0, "", 0.02, 20.0).rate_d(PD(3.0, 0.15))
        0.003
        """
        return round(self.d_over_p_s * gains.Kd, 9) if self.d_over_p_s > 0 else 0.0

    @property
    def plain(self) -> bool:
        """The written parameters close exactly the PD."""
        return not self.target_hz > 0


def read_structure(loop: Loop, values: Mapping[str, float], family: str = "") -> OnboardStructure:
    """The structure of ``loop`` from parameter ``values`` read from the vehicle.

    ``values`` holds what the vehicle answered (a name it lacks is absent); ``family`` is the
    autopilot family (``"px4"``, ``"ardupilot"``) for the default. A structure with a
    rate-target filter is ArduPilot's: it gets rate D (:data:`RATE_D_OVER_P_S`, where
    :data:`WRITE_RATE_D`) through its D low-pass (``ATC_RAT_*_FLTD``, :data:`DEFAULT_D_HZ`
    where not read).

    >>> read_structure(Loop.ROLL, {"ATC_RAT_RLL_FLTT": 12.5}).target_hz
    12.5
    >>> read_structure(Loop.PITCH, {}, "ardupilot").source.split(";")[0]
    "ArduPilot's default 20 Hz (ATC_RAT_PIT_FLTT not read)"
    >>> read_structure(Loop.ROLL, {}, "px4").plain
    True
    >>> read_structure(Loop.ROLL, {"ATC_RAT_RLL_FLTT": 20.0, "ATC_RAT_RLL_FLTD": 30.0}).d_hz
    30.0
    """
    name = TARGET_FILTER_PARAMS.get(loop)
    if name is None:
        return OnboardStructure(0.0, "no rate target on this loop")
    v = values.get(name)
    if v is not None and math.isfinite(v) and v >= 0:
        st = OnboardStructure(float(v), f"{name} = {v:g} Hz read")
    elif (hz := DEFAULT_TARGET_HZ.get(family, 0.0)) > 0:
        st = OnboardStructure(hz, f"ArduPilot's default {hz:g} Hz ({name} not read)")
    else:
        return OnboardStructure(0.0, "no rate target filter")
    if st.plain or not WRITE_RATE_D:
        return st
    d_name = D_FILTER_PARAMS[loop]
    fd = values.get(d_name)
    if fd is not None and math.isfinite(fd) and fd >= 0:
        d_hz, how = float(fd), f"{d_name} = {fd:g} Hz read"
    else:
        d_hz, how = DEFAULT_D_HZ, f"ArduPilot's default {DEFAULT_D_HZ:g} Hz ({d_name} not read)"
    return dataclasses.replace(st, d_over_p_s=RATE_D_OVER_P_S, d_hz=d_hz,
                               source=f"{st.source}; rate D low-pass {how}")


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
        if WRITE_RATE_D and (fd := read(D_FILTER_PARAMS[lp])) is not None:
            values[D_FILTER_PARAMS[lp]] = float(fd)
    return {lp: read_structure(lp, values, family) for lp in (Loop.ROLL, Loop.PITCH)}


def structure_controller(gains: PD, st: OnboardStructure, w: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
    """``(Cr, Cy)`` of the written ``gains`` under ``st``: ``u = Cr r - Cy y`` on ``w`` (rad/s).

    >>> Cr, Cy = structure_controller(PD(2.0, 0.1), OnboardStructure(), np.array([1.0]))
    >>> complex(Cr[0]), complex(Cy[0])
    ((2+0j), (2+0.1j))
    >>> Cr, Cy = structure_controller(PD(2.0, 0.1), OnboardStructure(20.0, "", 0.5),
    ...                               np.array([1.0]))
    >>> lead = Cr[0] / structure_controller(PD(2.0, 0.1), OnboardStructure(20.0),
    ...                                     np.array([1.0]))[0][0]  # 1 + r s, no D filter
    >>> bool(np.isclose(lead, 1 + 0.5j))
    True
    """
    # the one cascade model (rate D on the rate error: the filtered target less the gyro)
    return cascade_controller(gains, w, st.target_hz, st.error_hz, 0.0, st.d_over_p_s,
                              st.d_hz, st.gyro_hz)


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
                  starts: Sequence[PD] = (), gm_min: float = 0.0,
                  most: PD | None = None, most_ratio: float = math.inf,
                  wc_max: float = math.inf) -> StructuredDesign:
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
    gm_min : float
        Gain margin (ratio) required on ``G`` and every ``worst`` (0: none).
    most : PD, optional
        The most each gain may be (the search is clipped there).
    most_ratio : float
        The most ``Kc / Kd`` (the angle P written, 1/s) may be.
    wc_max : float
        The highest gain crossover on ``G`` (rad/s; inf: none).

    The margins are honoured: the optimum is scaled down (a pure gain change) until they
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

    def gm_of(g: PD) -> float:
        return min(float(margins(structure_controller(g, st, w)[1] * Gx, w).gm)
                   for Gx in (G, *worst)) if gm_min > 0 else math.inf

    def wc_of(g: PD) -> float:
        return (float(margins(structure_controller(g, st, w)[1] * G, w).wc)
                if np.isfinite(wc_max) else 0.0)

    top = np.log([most.Kc, most.Kd]) if most is not None else np.array([np.inf, np.inf])

    def gains_of(x: np.ndarray) -> PD:
        x = np.minimum(x, top)
        kd = float(np.exp(x[1]))
        return PD(min(float(np.exp(x[0])), most_ratio * kd), kd)

    def cost(x: np.ndarray) -> float:
        g = gains_of(x)
        pm, pmw = pm_all(g)
        if pm == -math.inf or pmw == -math.inf:  # unstable (no worst case: pmw is +inf)
            return 1e12
        Cr, Cy = structure_controller(g, st, w)
        q = general_ise(Cr, Cy, G, w)
        short = max(0.0, pm_min_deg - pm) + max(0.0, pm_worst_deg - pmw)
        if gm_min > 0:  # in dB-like units: 1 for each 5 % short of the gain margin
            short += 20.0 * max(0.0, math.log(gm_min / gm_of(g)))
        if np.isfinite(wc_max):  # alike: 1 for each 5 % above the crossover allowed
            short += 20.0 * max(0.0, math.log(wc_of(g) / wc_max))
        return q * (1.0 + 0.05 * short + 0.02 * short ** 2) if np.isfinite(q) else 1e12

    best = None
    for s0 in (*starts, optimal_pd(G, w).pd):
        res = minimize(cost, np.log([s0.Kc, s0.Kd]), method="Nelder-Mead",
                       options={"xatol": 1e-4, "fatol": 1e-9, "maxiter": 600})
        if best is None or res.fun < best.fun:
            best = res
    assert best is not None
    g = gains_of(best.x)
    pm, pmw = pm_all(g)
    k = 1.0
    while (pm < pm_min_deg or pmw < pm_worst_deg or gm_of(PD(g.Kc * k, g.Kd * k)) < gm_min
           or wc_of(PD(g.Kc * k, g.Kd * k)) > wc_max) and k > 1e-3:
        k *= 0.98  # the search ended short of a margin: less gain until they hold
        pm, pmw = pm_all(PD(g.Kc * k, g.Kd * k))
    g = PD(g.Kc * k, g.Kd * k)
    Cr, Cy = structure_controller(g, st, w)
    return StructuredDesign(g, general_ise(Cr, Cy, G, w), pm, pmw)


def relay_frequency(model: InnerModel, beta: float) -> float:
    """The frequency (rad/s) of the relay cycle that identified ``model`` (the ground station's
    loop, its delay in): where the model's phase is ``-180 deg + arcsin(beta)``, the point the
    cycle pins it at (the describing function's; inf where it never gets there).

    >>> round(relay_frequency(InnerModel(100.0, 0.02, 0.5, 0.02), -0.7), 1)
    22.4
    """
    w = frequency_grid(model.T_prop, model.T1, model.tau, n=2000)
    ph = np.unwrap(np.angle(inner_response(1.0, model.T_prop, model.T1, model.tau, w)[0]))
    hit = np.flatnonzero(ph <= -math.pi + math.asin(beta))
    return float(w[hit[0]]) if hit.size else math.inf


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
    what = f"rate target low-pass {st.target_hz:g} Hz"
    if not st.d_over_p_s > 0:
        des = structured_pd(G, w, st, pm_min_deg=pm_min_deg, worst=(Gw,),
                            starts=(rt.gains,))
    if st.d_over_p_s > 0:
        two = structured_pd(G, w, dataclasses.replace(st, d_over_p_s=0.0),
                            pm_min_deg=pm_min_deg, worst=(Gw,), starts=(rt.gains,))
        most = PD(two.gains.Kc * D_GAIN_MOVE_MAX, two.gains.Kd * D_GAIN_MOVE_MAX)
        des = structured_pd(G, w, st, pm_min_deg=pm_min_deg, worst=(Gw,),
                            starts=(two.gains,), gm_min=D_GM_MIN, most=most,
                            most_ratio=two.gains.Kc / two.gains.Kd * D_ANGLE_P_MOVE_MAX,
                            wc_max=D_WC_MAX_RATIO * relay_frequency(m, ident.beta))
        if not two.ise > des.ise:  # D that does not pay for itself is not written
            des, st = two, dataclasses.replace(st, d_over_p_s=0.0)
            what += ", no rate D (it did not lower the ISE)"
        else:
            what += (f", rate D {st.d_over_p_s * 1e3:.1f} ms x rate P "
                     f"= {st.rate_d(des.gains):.4g} through {st.d_hz:g} Hz "
                     f"(ISE {100 * (1 - des.ise / two.ise):.0f} % below two numbers)")
    return dataclasses.replace(rt, gains=des.gains, delay_s=round(d, 6),
                               pm_deg=des.pm_worst_deg, d_over_p_s=st.d_over_p_s,
                               structure=f"{what} ({st.source})")


def rate_d_values(profile: AutopilotProfile, gains: Mapping[Loop, PDGains],
                  d_over_p_s: Mapping[Loop, float]) -> dict[str, float]:
    """The rate D parameters for the written roll/pitch ``gains`` (their rate P ``Kd`` in
    effect, after any clamp) at ``d_over_p_s`` of it, clamped into the profile's range;
    loops without D are left out (their D is written as 0 with the gains).

    >>> from mrft_gcs.profiles import load_profile
    >>> rate_d_values(load_profile("sitl"), {Loop.ROLL: PDGains(1.0, 0.2)},
    ...               {Loop.ROLL: 0.02, Loop.PITCH: 0.02})
    {'MC_ROLLRATE_D': 0.004}
    """
    out: dict[str, float] = {}
    for lp, names in ((Loop.ROLL, profile.roll), (Loop.PITCH, profile.pitch)):
        r, g = d_over_p_s.get(lp, 0.0), gains.get(lp)
        if g is None or not r > 0:
            continue
        v = round(r * g.Kd, 6)
        lo, hi = profile.param_ranges.get(names.rate_d, (0.0, math.inf))
        out[names.rate_d] = min(max(v, lo), hi)
    return out


def cascade_design(model: InnerModel, gains: PD, st: OnboardStructure,
                   decade: float = 0.0, delay_out_s: float = 0.0) -> CascadeGains:
    """Roll/pitch gains for ArduCopter's cascade on the rate path, with rate D where it pays.

    Without D the identified ``gains`` are kept where they hold
    :data:`~mrft_gcs.flight.onboard.PM_ROBUST_DEG` on the cascade (scaled down together
    where not: :func:`~mrft_gcs.flight.onboard.cascade_gains`). With ``st``'s rate D
    (``st.d_over_p_s`` of rate P through ``st.d_hz``) the ISE-optimal gains on the same
    process (:func:`~mrft_gcs.flight.onboard.cascade_process`: the identified delay kept,
    half a loop period more) are searched from those, within :data:`D_GAIN_MOVE_MAX` of
    each gain and :data:`D_ANGLE_P_MOVE_MAX` of the angle P, at phase margin
    :data:`~mrft_gcs.pd_design.PM_MIN_DEG` (5 deg above the floor without D: D amplifies
    the gyro's noise, which the model does not see) and gain margin :data:`D_GM_MIN`; they
    are written only where their ISE is below that of the best gains without D at the same
    margin (where not, the identified gains stay, as without D). A rate I with
    its zero ``decade`` below the crossover goes on top
    (:func:`~mrft_gcs.flight.onboard.rate_loop_gains`, the margin kept at
    :data:`~mrft_gcs.flight.onboard.PM_ROBUST_DEG` with it). ``delay_out_s`` of the
    identified delay is the ground station's, not the onboard loop's (s;
    :func:`~mrft_gcs.flight.onboard.cascade_delay_out_s`): the process designed on has that
    much less (never below 0).

    Examples
    --------
    >>> m = InnerModel(K=34.0, T_prop=0.0085, T1=0.095, tau=0.006)
    >>> c = cascade_design(m, PD(6.4, 0.21), OnboardStructure(20.0, "", RATE_D_OVER_P_S, 20.0))
    >>> c.rate_d > 0, c.pm_deg >= 20.0, c.gains.Kd <= 0.21 * D_GAIN_MOVE_MAX
    (True, True, True)
    >>> cascade_design(m, PD(6.4, 0.21), OnboardStructure(20.0)).rate_d
    0.0
    """
    out = min(max(float(delay_out_s), 0.0), model.tau)
    model = dataclasses.replace(model, tau=model.tau - out)
    base = cascade_gains(model, gains, st.target_hz, PM_ROBUST_DEG, st.error_hz,
                         gyro_hz=st.gyro_hz)
    chosen, r, why = base.gains, 0.0, ""
    if st.d_over_p_s > 0 and base.scale > 0 and math.isfinite(base.wc_rad_s):
        w = frequency_grid(model.T_prop, model.T1, model.tau)
        G = cascade_process(model, w)
        b = base.gains
        # D is judged against the best the two numbers do on the same cascade at the same
        # margin (not against the identified gains: that would credit D with the re-design)
        two = structured_pd(G, w, dataclasses.replace(st, d_over_p_s=0.0),
                            pm_min_deg=PM_MIN_DEG, starts=(b,))
        des = structured_pd(G, w, st, pm_min_deg=PM_MIN_DEG, starts=(b,), gm_min=D_GM_MIN,
                            most=PD(b.Kc * D_GAIN_MOVE_MAX, b.Kd * D_GAIN_MOVE_MAX),
                            most_ratio=b.Kc / b.Kd * D_ANGLE_P_MOVE_MAX)
        if des.ise < two.ise and des.pm_deg >= PM_MIN_DEG - 1e-6:
            chosen, r = des.gains, st.d_over_p_s
            why = (f"rate D designed on the cascade: ISE {100 * (1 - des.ise / two.ise):.0f} % "
                   f"below the best without D at {PM_MIN_DEG:g} deg, PM {des.pm_deg:.0f} deg "
                   f"before rate I")
        else:
            why = (f"no rate D (on the cascade it did not lower the ISE below the best without "
                   f"D at {PM_MIN_DEG:g} deg)")
    c = rate_loop_gains(model, chosen, st.target_hz, st.error_hz, decade=decade,
                        d_over_p_s=r, d_hz=st.d_hz, gyro_hz=st.gyro_hz)
    return dataclasses.replace(c, scale=base.scale, pm_identified_deg=base.pm_identified_deg,
                               d_note=why, delay_out_s=out)
