"""Runtime identification with the bundled ONNX classifiers (numpy + onnxruntime only).

For an inner loop (attitude, altitude):

1. the last steady cycles become the classifier input (:mod:`mrft_gcs.features`);
2. the network gives a probability per representative shape;
3. for each likely shape ``k`` the time scale follows from the period,
   ``c = T / T_k`` (``T_k``: the shape's simulated unit-scale period at the
   test's ``beta``), and the gain from the amplitude by exact gain scaling,
   ``K = a / (h c A_k)`` (``A_k``: its simulated unit amplitude; the
   describing function would use ``4/pi |G_k|``);
4. the gains are those of the shape ``i`` whose tuning rule has the least
   *expected* cost under the classifier's probabilities,
   ``i = argmin_i sum_j p_j C[i, j]``, where ``C[i, j]`` (precomputed, time-scale
   invariant) is the cost of shape ``i``'s optimal PD, mapped by its rule, on
   shape ``j``: ``|J|`` plus two points per degree of phase margin below 20.
   When the classifier is unsure this picks a rule that is safe for all the
   likely shapes (a Bayes decision, rather than blending gains). The shape's unit
   optimal PD is mapped to the process as ``Kc = Kc_i / (c K)``, ``Kd = Kd_i / K``.

With two or more cycles, the relay cycle's measured harmonics
(:mod:`mrft_gcs.identify.harmonics`) take part: cycles that are not steady are
refused; the classifier's probabilities are multiplied by each shape's
likelihood of the measured points before the Bayes decision; the chosen
shape's model is refined on the points (its time constants held near the
class by a prior) and the gains are the optimal PD of the refined model, provided
they keep 15 deg of phase margin on every shape the posterior still holds likely
(the refinement starts from the Bayes rule's shape, and its optimum must not undo
the rule's safety); otherwise the rule's gains stand. The
reported model is then the refined one (``diagnostics.method`` says which path
ran); the classifier's most likely shape is ``diagnostics.classifier.likeliest``;
``class_index`` is the representative process of the chosen shape nearest in
scale. Side motion: see :func:`_identify_side`.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import NamedTuple, Protocol

import numpy as np

from mrft_gcs.domains import D_SIDE
from mrft_gcs.errors import CyclesTooSmall, IdentificationError
from mrft_gcs.features import cycle_features, rising_switches
from mrft_gcs.identify.closed_loop import closed_loop_points
from mrft_gcs.identify.harmonics import (
    USABLE_SD,
    class_log_likelihood,
    fit_inner_model,
    fit_side_model,
    harmonic_points,
)
from mrft_gcs.identify.result import (
    ClassifierVote,
    Diagnostics,
    HarmonicFit,
    Identification,
    Method,
    RelaySettings,
)
from mrft_gcs.identify.side import SIDE_H, side_features, side_plant_response
from mrft_gcs.loops import LoopKind
from mrft_gcs.pd_design import frequency_grid, margins, optimal_pd
from mrft_gcs.plant import (
    PD,
    InnerModel,
    SideModel,
    closed_inner_response,
    inner_response,
    side_response,
)

__all__ = ["identify", "relay_settings", "load_bundle", "Bundle", "MODELS_DIR", "GainScaling"]

MODELS_DIR = Path(__file__).resolve().parents[2] / "models"


class ClassifierSession(Protocol):
    """What the bundles use of an ``onnxruntime.InferenceSession``."""

    def run(self, output_names: list[str] | None,
            input_feed: dict[str, np.ndarray]) -> list[np.ndarray]: ...


class GainScaling:
    """How the process gain is recovered from the amplitude."""

    EXACT = "exact"  # simulated unit amplitude of the class (zeta table)
    DF = "df"  # describing function, zeta = 4/pi
    TRUE = "true"  # gain known (normalised-gain evaluation only)


@dataclass(frozen=True)
class Bundle:
    """A loop kind's classifier and class table."""

    kind: LoopKind
    beta: float
    h: float
    shape_params: np.ndarray
    shape_pd: np.ndarray
    unit_period: np.ndarray
    unit_amplitude: np.ndarray
    zeta: np.ndarray
    reps: np.ndarray
    rep_shape: np.ndarray
    rule_cost: np.ndarray
    session: ClassifierSession
    temperature: float = 1.0

    def logits(self, x: np.ndarray) -> np.ndarray:
        """Calibrated logits (divided by the validation temperature)."""
        return self.session.run(None, {"x": np.atleast_2d(x).astype(np.float32)})[0] / \
            self.temperature


@lru_cache(maxsize=8)
def load_bundle(kind: LoopKind, models: Path = MODELS_DIR) -> Bundle:
    """Load ``models/<kind>/classes.json`` and ``classifier.onnx`` (cached)."""
    d = models / kind.value
    table, onnx_path = d / "classes.json", d / "classifier.onnx"
    if not (table.exists() and onnx_path.exists()):
        raise IdentificationError(
            f"no bundled {kind.value} classifier in {d}: regenerate it with "
            f"'mrft-tune design train --loop {kind.value}' (needs pip install -e '.[design]')")
    import onnxruntime as ort  # lazy: loaded with the first classifier, not at CLI start

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    opts.inter_op_num_threads = 1
    session = ort.InferenceSession(str(onnx_path), opts, providers=["CPUExecutionProvider"])
    try:
        c = json.loads(table.read_text())
        arr = {k: np.asarray(c[k], float) for k in ("shape_params", "shape_pd", "unit_period",
                                                     "unit_amplitude", "zeta", "reps",
                                                     "rule_cost")}
        return Bundle(kind=kind, beta=float(c["beta"]), h=float(c["h"]),
                      temperature=float(c.get("temperature", 1.0)),
                      rep_shape=np.asarray(c["rep_shape"], int), session=session, **arr)
    except (KeyError, ValueError, TypeError) as exc:
        raise IdentificationError(
            f"{table} is incomplete or from an older version ({exc}): regenerate it with "
            f"'mrft-tune design zeta --loop {kind.value}' and 'mrft-tune design train'") from exc


@dataclass(frozen=True)
class SideBundle:
    """Side classes and classifier of one attitude shape (unit attitude scale)."""

    att_shape: int
    beta: float
    params: np.ndarray
    pd: np.ndarray
    unit_period: np.ndarray
    unit_amplitude: np.ndarray
    rule_cost: np.ndarray
    session: ClassifierSession
    temperature: float = 1.0
    att_params: np.ndarray = None  # type: ignore[assignment]
    att_pd: np.ndarray = None  # type: ignore[assignment]

    def logits(self, x: np.ndarray) -> np.ndarray:
        return self.session.run(None, {"x": np.atleast_2d(x).astype(np.float32)})[0] / \
            self.temperature


@lru_cache(maxsize=64)
def load_side_bundle(att_shape: int, models: Path = MODELS_DIR) -> SideBundle:
    d = models / "side" / f"shape_{att_shape:02d}"
    table, onnx_path = d / "classes.json", d / "classifier.onnx"
    if not (table.exists() and onnx_path.exists()):
        raise IdentificationError(
            f"no bundled side classifier for attitude shape {att_shape} in {d}: regenerate with "
            "'mrft-tune design side' (needs pip install -e '.[design]')")
    import onnxruntime as ort  # lazy: loaded with the first classifier, not at CLI start

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    c = json.loads(table.read_text())
    return SideBundle(att_shape, float(c["beta"]), np.asarray(c["params"]), np.asarray(c["pd"]),
                      np.asarray(c["unit_period"]), np.asarray(c["unit_amplitude"]),
                      np.asarray(c["rule_cost"]), ort.InferenceSession(str(onnx_path), opts,
                                           providers=["CPUExecutionProvider"]),
                      float(c.get("temperature", 1.0)), np.asarray(c["att_params"]),
                      np.asarray(c["att_pd"]))


def measured_margin_guard(pd: PD, period_s: float, amplitude: float, h: float, beta: float,
                          zeta: float, pm_min_deg: float = 20.0) -> tuple[PD, float]:
    """Check gains against the one frequency-response point the relay test measured.

    The steady cycle gives ``G(j Omega)`` at ``Omega = 2 pi / T``: its phase is
    ``-180 deg + arcsin(beta)`` and its magnitude ``a / (zeta h)``. If the PD puts that
    point outside the unit circle while its phase there is already below
    ``-180 + pm_min``, the crossover lies above ``Omega`` where the phase is lower still,
    so the margin is certainly short: the gains are scaled down until ``|L(j Omega)| = 1``.
    Returns the (possibly scaled) gains and the scale applied (1 when nothing changed).
    """
    w = 2 * np.pi / period_s
    lead = np.degrees(np.arctan2(pd.Kd * w, pd.Kc))
    phase = -180.0 + np.degrees(np.arcsin(beta)) + lead
    mag = abs(complex(pd.Kc, pd.Kd * w)) * amplitude / (zeta * h)
    if phase < -180.0 + pm_min_deg and mag > 1.0:
        return PD(pd.Kc / mag, pd.Kd / mag), 1.0 / mag
    return pd, 1.0


def harmonic_response(t, u, y, harmonic: int = 3, cycles: int = 4) -> tuple[float, complex]:
    """``(omega, G(j omega))`` at a harmonic of the relay cycle, from the measured signals.

    The relay output is a square wave, so its odd harmonics excite the loop too; the
    ratio of the ``y`` and ``u`` Fourier coefficients at ``harmonic * Omega`` over whole
    cycles is a second measured point of the frequency response (noise averages out
    over the cycles). Returns ``(nan, nan)`` when there are not enough cycles.
    """
    t, u, y = (np.asarray(a, float) for a in (t, u, y))
    r = rising_switches(u)
    if r.size < 2:
        return float("nan"), complex("nan")
    a, b = r[max(0, r.size - 1 - cycles)], r[-1]
    tt, uu, yy = t[a:b], u[a:b], y[a:b]
    T = (t[b] - t[a]) / (min(cycles, r.size - 1))
    w = 2 * np.pi * harmonic / T
    ph = np.exp(-1j * w * (tt - tt[0]))
    dt = np.gradient(tt)
    U = np.sum((uu - uu.mean()) * ph * dt)
    Y = np.sum((yy - yy.mean()) * ph * dt)
    return float(w), complex(Y / U) if abs(U) > 0 else complex("nan")


def harmonic_guard(pd: PD, w: float, G: complex, limit: float = 0.7) -> tuple[PD, float]:
    """Scale gains so that ``|L(j w)| <= limit`` where the measured loop has passed -180 deg.

    ``G`` is a measured frequency-response point (:func:`harmonic_response`). A lagging
    loop whose phase lies between -180 and -360 deg wraps to a positive angle; there a
    loop gain near one means little or no gain margin, so the gains are scaled down.
    Returns the gains and the scale applied (1 when nothing changed).
    """
    if not (np.isfinite(w) and np.isfinite(G.real) and np.isfinite(G.imag)):
        return pd, 1.0
    L = complex(pd.Kc, pd.Kd * w) * G
    if np.angle(L) > 0 and abs(L) > limit:
        k = limit / abs(L)
        return PD(pd.Kc * k, pd.Kd * k), k
    return pd, 1.0


def _inner_shape(inner: Identification | None) -> tuple[int, float]:
    if inner is None or inner.diagnostics.shape is None:
        raise IdentificationError("side motion needs the attitude loop identified first")
    return inner.diagnostics.shape, inner.diagnostics.scale


def relay_settings(kind: LoopKind, inner: Identification | None = None) -> RelaySettings:
    """MRFT ``beta`` and default ``h`` for a loop kind (side motion needs the attitude result).

    Raises
    ------
    IdentificationError
        No bundled classifier for the loop, or side motion without an identified
        attitude loop.
    """
    if kind is LoopKind.SIDE:
        k, _ = _inner_shape(inner)
        return RelaySettings(beta=load_side_bundle(k).beta, h=SIDE_H)
    b = load_bundle(kind)
    return RelaySettings(beta=b.beta, h=b.h)


#: The side fit on the relay's harmonics needs the fundamental and the 3rd harmonic
#: measured at least this well (standard error of log G over the cycles); else refused.
FIT_MAX_SD = (0.1, 0.5)


def _identify_side(t, u, y, beta: float, inner: Identification | None,
                   setpoint=None, tilt=None) -> Identification:
    """Side motion: a model fitted on the relay's measured harmonics, else the classifier.

    The closed attitude loop is known (the attitude identification and its gains), so
    the side model's three unknowns are fitted on the measured frequency-response
    points of the cycle (:mod:`mrft_gcs.identify.harmonics`) and the gains are the
    optimal PD of the fitted cascade. Cycles whose fundamental varies from cycle to
    cycle, or whose 3rd harmonic is lost in noise (:data:`FIT_MAX_SD`), are refused:
    the side classifier of the attitude shape, as in the paper, was measured unsafe on
    exactly those (phase margins down to 4 deg) and now decides only for a record of
    a single cycle. Measured (Table VI, side, README): the fit brought the share of
    side loops within 10 % of their optimal PD from 49 % (classifier) to over 99 %.
    """
    k, c = _inner_shape(inner)
    assert inner is not None  # _inner_shape refused None
    b = load_side_bundle(k)
    if abs(beta - b.beta) > 1e-6:
        raise IdentificationError(
            f"the side classifier of attitude shape {k} expects beta={b.beta}, the test ran {beta}")
    t, u, y = (np.asarray(a, float) for a in (t, u, y))
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(u)) and np.all(np.isfinite(y))):
        raise IdentificationError("the relay record holds NaN or infinite values; drop them first")
    fitted, fit_note = _fit_side(t, u, y, beta, b, inner, c, tilt)
    if fitted is not None:
        return fitted
    classified = _classify_side(t, u, y, beta, b, k, c, setpoint, inner)
    return dataclasses.replace(classified, diagnostics=dataclasses.replace(
        classified.diagnostics, fit_note=fit_note))


def _fit_side(t, u, y, beta, b: SideBundle, inner: Identification, c: float, tilt=None):
    """The harmonic-fit identification, or ``(None, reason)`` when the cycles do not allow it.

    ``tilt``: the measured tilt along the axis at the times ``t``. The side model is then
    fitted behind the closed attitude loop *as measured* over the same cycles (at the
    harmonics where it is measured well enough) rather than as modelled: the fit sees
    position against the tilt that really drove it, so an attitude loop that saturates
    or lags its linear model during the test (a light, high thrust-to-weight airframe
    whose motors hit zero at each side relay switch) does not pass its lag on to the side
    model. The gains are still designed for the modelled, linear attitude loop.
    """
    from scipy.stats import chi2  # lazy: scipy.stats takes 0.6 s to import, at CLI start

    try:
        pts = harmonic_points(t, u, y)
    except ValueError as exc:
        return None, str(exc)
    if pts.spread[0] > FIT_MAX_SD[0]:
        raise IdentificationError(
            f"the side relay cycles are not steady (cycle-to-cycle spread of the fundamental "
            f"{pts.spread[0]:.2f} in log units, need <= {FIT_MAX_SD[0]}): let the relay run "
            "longer or reduce disturbances, then retry")
    if pts.spread.size < 2:
        raise IdentificationError(
            "too few samples per side relay cycle to measure its 3rd harmonic: stream "
            "LOCAL_POSITION_NED faster (at least 30 samples per cycle)")
    if pts.spread[1] > FIT_MAX_SD[1]:
        # The classifier alone was measured unsafe here (phase margins down to 4 deg).
        raise CyclesTooSmall(
            f"the side relay cycles are too noisy to measure their 3rd harmonic (spread "
            f"{pts.spread[1]:.2f} in log units, need <= {FIT_MAX_SD[1]}): raise the side relay "
            "amplitude or let it run longer, then retry")
    m, g = inner.model, inner.gains
    assert isinstance(m, InnerModel)  # an inner-loop identification: it has a shape

    def t_att(w):
        return closed_inner_response(g.Kc, g.Kd, inner_response(m.K, m.T_prop, m.T1, m.tau, w),
                                     w)[0]

    T_att, fit_pts, measured = _measured_t_att(t, u, tilt, pts, t_att(pts.w))
    # searched over the side domain of Table I, widened by 2 each way
    try:
        fit = fit_side_model(fit_pts, T_att, T2_range=(D_SIDE.low[0] / 2, D_SIDE.high[0] * 2),
                             tau_range=(D_SIDE.low[1] / 2, D_SIDE.high[1] * 2),
                             accel_prior=SIDE_ACCEL_PRIOR)
    except ValueError as exc:
        # the check above reads the cycle-to-cycle spread; the fit weighs each harmonic by
        # its whole error (with the noise and timing terms), which can be over the limit
        # when the spread is just under it: a refusal to retry on, not a crash
        raise CyclesTooSmall(
            f"the side relay cycles are too noisy to measure their 3rd harmonic (error "
            f"{fit_pts.sd[1]:.3f} in log units with noise and timing, need <= "
            f"{USABLE_SD}; {exc}): raise the side relay amplitude or let it run longer, "
            "then retry") from None
    if SIDE_ACCEL_PRIOR is not None and \
            abs(np.log(fit.K / fit.T2 / SIDE_ACCEL_PRIOR[0])) > SIDE_ACCEL_REFUSE:
        raise IdentificationError(
            f"the side relay cycles give {fit.K / fit.T2:.3g} m/s^2 of acceleration per rad of "
            f"tilt where a multirotor in hover has about {SIDE_ACCEL_PRIOR[0]:.3g}: the cycles "
            "are disturbed (wind, a bumped vehicle, a stalled link); let the relay run on and "
            "retry")
    w = np.logspace(np.log10(1e-2 / (fit.T2 + m.T1 + fit.tau)),
                    np.log10(200 / min(m.T_prop, m.tau + fit.tau)), 900)
    design = optimal_pd(t_att(w) * side_response(fit.K, fit.T2, fit.tau, w)[0], w)
    if not design.margins.stable:
        return None, "no stable PD for the fitted side model"
    tau_ratio = np.maximum(b.params[:, 1] * c, 1e-4) / max(fit.tau, 1e-4)
    near = int(np.argmin(np.hypot(np.log(b.params[:, 0] * c / fit.T2), np.log(tau_ratio))))
    dof = 2 * len(fit.used) - 3 + (SIDE_ACCEL_PRIOR is not None)
    r = rising_switches(u)
    a0, b0 = r[max(0, r.size - 1 - pts.cycles)], r[-1]
    amplitude = 0.5 * float(np.ptp(y[a0:b0]))
    levels = np.asarray(u[a0:b0])
    h = 0.5 * float(levels.max() - levels.min())
    df = float(abs(pts.G[0]) * (4 * h / np.pi) / amplitude) if amplitude > 0 else float("nan")
    model = SideModel(K=fit.K, T2=fit.T2, tau=fit.tau)
    return Identification(
        kind=LoopKind.SIDE, model=model, class_index=near,
        confidence=float(chi2.sf(fit.cost, dof)) if dof > 0 else 1.0, beta=beta, h=h,
        period_s=pts.period_s, amplitude=amplitude, gains=design.pd,
        diagnostics=Diagnostics(Method.HARMONIC_FIT, fit=HarmonicFit(
            cost=float(fit.cost), harmonics=tuple(int(k) for k in fit.used),
            sd=tuple(float(s) for s in pts.sd),
            t_att_measured=tuple(int(k) for k, m in zip(pts.harmonics, measured, strict=True)
                                 if m),
            df_factor=df, pm_deg=float(design.margins.pm_deg))),
        inner=inner), None


#: prior on the side model's ``K / T2`` (m/s^2 per rad of tilt: ``g`` in hover) and its
#: spread (log units) for the harmonic fit (:func:`~mrft_gcs.identify.harmonics.fit_side_model`);
#: None: no prior
SIDE_ACCEL_PRIOR: tuple[float, float] | None = (9.80665, 0.15)
#: a fit whose ``K / T2`` still lies further than this (log units: a factor of 1.5) from
#: the prior is refused (the relay runs on and the next cycles are tried): the cycles are
#: not those of a multirotor's side motion behind the attitude loop. Measured (tune_stalls,
#: 84 side fits on 3 airframes, hover guess 0.85-1.15): all within 0.23 of g but one f550
#: y at 0.54 (16.8 m/s^2 per rad, J 14 %)
SIDE_ACCEL_REFUSE = 0.4

#: a harmonic of the measured closed attitude loop is used in the side fit only when its
#: standard error (log units) is within this; else the modelled loop stands there. With
#: :data:`~mrft_gcs.identify.harmonics.USABLE_SD` (0.5) a disturbed f550 cycle's 7th
#: harmonic (error 0.36, phase 170 deg off the model) pulled the fit to T2 0.18 s
#: against the true 0.80 s (in-process, under a per-axis torque limit tried and dropped)
MEASURED_T_ATT_MAX_SD = 0.25


def _measured_t_att(t, u, tilt, pts, modelled: np.ndarray):
    """The closed attitude loop at ``pts``' harmonics, measured where the tilt allows.

    Returns ``(T_att, points, measured)``: the loop (measured where its standard error
    is within :data:`MEASURED_T_ATT_MAX_SD`, else ``modelled``), the
    points with the measured loop's error added to theirs, and which were measured.
    """
    none = np.zeros(len(pts.harmonics), bool)
    if tilt is None:
        return modelled, pts, none
    tilt = np.asarray(tilt, float)
    if tilt.shape != np.shape(t):
        return modelled, pts, none
    try:
        cl = closed_loop_points(t, u, tilt, cycles=pts.cycles, harmonics=pts.harmonics)
    except IdentificationError:
        return modelled, pts, none
    ok = (cl.sd <= MEASURED_T_ATT_MAX_SD) & np.isfinite(cl.G) & (np.abs(cl.G) > 0)
    combined = np.hypot(pts.sd, cl.sd)
    # a harmonic whose error, with the measured loop's added, would leave the fit keeps
    # the modelled loop (else the fit can be left with the fundamental alone and fail)
    ok[1:] &= combined[1:] <= USABLE_SD
    if cl.cycles != pts.cycles or not np.allclose(cl.w, pts.w) or not ok[0]:
        return modelled, pts, none
    T_att = np.where(ok, cl.G, modelled)
    sd = np.where(ok, combined, pts.sd)
    return T_att, dataclasses.replace(pts, sd=sd), ok


def _classify_side(t, u, y, beta, b: SideBundle, k: int, c: float, setpoint,
                   inner: Identification) -> Identification:
    f, x = side_features(t, u, y, c, setpoint)
    probs = _softmax(b.logits(x)[0])
    order = np.argsort(-probs)[:3]
    r = int(np.argmin(b.rule_cost @ probs))  # Bayes decision, as for the inner loops
    Kr = f.amplitude / (f.h * c * b.unit_amplitude[r])
    zeta = b.unit_amplitude[r] / abs(side_plant_response(
        b.att_params, tuple(b.att_pd), b.params[r, 0], b.params[r, 1],
        [2 * np.pi / b.unit_period[r]])[0, 0])
    guarded, scale = measured_margin_guard(PD(b.pd[r, 0] / (c * Kr), b.pd[r, 1] / Kr),
                                           f.period_s, f.amplitude, f.h, beta, zeta)
    for n_h in (3, 5):  # the relay's odd harmonics: two more measured points
        wh, Gh = harmonic_response(t, u, y, harmonic=n_h)
        guarded, sh = harmonic_guard(guarded, wh, Gh, limit=0.5)
        scale *= sh
    Kc, Kd = guarded.Kc, guarded.Kd
    j = int(order[0])
    K = f.amplitude / (f.h * c * b.unit_amplitude[j])
    model = SideModel(K=float(K), T2=float(b.params[j, 0] * c), tau=float(b.params[j, 1] * c))
    return Identification(kind=LoopKind.SIDE, model=model, class_index=j,
                          confidence=float(probs[j]), beta=beta, h=f.h, period_s=f.period_s,
                          amplitude=f.amplitude, gains=PD(float(Kc), float(Kd)),
                          diagnostics=Diagnostics(Method.CLASSIFIER, classifier=ClassifierVote(
                              rule=r, top=tuple(int(i) for i in order), duty=float(f.duty),
                              bias=float(f.bias), margin_guard_scale=float(scale))),
                          inner=inner)


def _softmax(z: np.ndarray) -> np.ndarray:
    z = z - z.max(axis=-1, keepdims=True)
    e = np.exp(z)
    return e / e.sum(axis=-1, keepdims=True)


def scaled_gains(b: Bundle, probs: np.ndarray, period_s: float, amplitude: float, h: float,
                 scaling: str = GainScaling.EXACT, K_true: float | None = None
                 ) -> tuple[PD, int, float, float]:
    """Gains of the Bayes-chosen rule; returns ``(pd, chosen shape, its scale c, gain K)``."""
    i = int(np.argmin(b.rule_cost @ probs))
    c = period_s / b.unit_period[i]
    if scaling == GainScaling.TRUE:
        if K_true is None:
            raise TypeError("GainScaling.TRUE needs K_true")
        K = float(K_true)
    elif scaling == GainScaling.DF:
        K = amplitude / (h * c * b.unit_amplitude[i] / b.zeta[i] * 4 / np.pi)
    else:
        K = amplitude / (h * c * b.unit_amplitude[i])
    return PD(float(b.shape_pd[i, 0] / (c * K)), float(b.shape_pd[i, 1] / K)), i, c, K


#: Cycle-to-cycle spread (standard error of log G at the fundamental) above which the
#: relay cycles are not a steady oscillation and identification refuses them.
STEADY_MAX_SD = 0.1
#: Width (log units) of the prior that holds the inner-model fit near the chosen class.
PRIOR_LOG_SD = 0.5
#: Refined gains further than this factor from the chosen rule's are not trusted.
MAX_REFINE_FACTOR = 3.0
#: Nor are those of a refined model whose weighted misfit to the measured harmonics (the
#: fit's cost, a sum of squared standard errors) is above this: the model structure does
#: not explain the record. Over 474 inner loops (122 live SITL tunes, 36 in-process) its
#: median was 0.3, its 95th percentile 49; above 40, live, the refined gains were written
#: at 12.5-44 % J (3 loops) or with 9.0-11.7 deg of phase margin (3), where the rule's
#: kept 17.5-25 deg and at most 6.7 % J.
MAX_FIT_COST = 40.0
#: Refined gains must keep this phase margin (deg) on every shape the posterior still
#: holds likely (:data:`LIKELY_POSTERIOR`), each at the scale and gain its period and
#: amplitude give; the Bayes rule keeps about 20 there by construction.
REFINED_MIN_PM_DEG = 15.0
LIKELY_POSTERIOR = 0.1
#: Refined gains the margin guard refuses are still approached from the rule's, as far as
#: the guard allows (:func:`held_back_gains`), when the cycles are at least this steady
#: (spread of the fundamental, log units); wandering cycles (ground-station stalls) keep
#: the rule's gains: their harmonics are biased in ways their spread does not show.
HOLD_BACK_MAX_SPREAD = 0.05
#: Steps of the hold-back from the rule's gains (0) to the refined ones (1).
HOLD_BACK_STEPS = 20
#: The loop kinds whose refused refinements are held back rather than dropped: attitude,
#: whose posterior spreads over time constants its short cycles cannot tell apart, so the
#: rule's gains alone can be well off the optimum; altitude's rule is close to it, and a
#: hold-back there only spends phase margin (docs/identification.md).
HOLD_BACK_KINDS = (LoopKind.ATTITUDE,)


class Refinement(NamedTuple):
    """What :func:`refined_identification` decided.

    ``held_back``: how far the gains went from the Bayes rule's (0) towards the refined
    model's optimum (1), log-linearly (:func:`held_back_gains`); NaN without measured
    harmonics. ``fit_cost``: NaN without harmonics, infinite when the rule's gains stand
    alone. ``model`` is the refined one only when its own optimum is used (``held_back``
    1), else the rule's.
    """

    pd: PD
    model: InnerModel
    shape: int
    scale: float
    posterior: np.ndarray
    fit_cost: float
    held_back: float


def _shape_models(b: Bundle, f) -> tuple[np.ndarray, np.ndarray]:
    """Every shape's model for the measured cycle: gain ``K`` (n,) by exact gain scaling
    and time constants ``(T_prop, T1, tau)`` (n, 3) at the scale its period gives."""
    c = f.period_s / b.unit_period
    return f.amplitude / (f.h * c * b.unit_amplitude), b.shape_params * c[:, None]


def _min_pm_on_likely(b: Bundle, post: np.ndarray, f, pd: PD) -> float:
    """The smallest phase margin of ``pd`` on the likely shapes' models (deg)."""
    Ks, sps = _shape_models(b, f)
    worst = np.inf
    for k in np.flatnonzero(post >= LIKELY_POSTERIOR):
        K, (T_prop, T1, tau) = Ks[k], sps[k]
        w = frequency_grid(T_prop, T1, tau, n=300)
        m = margins((pd.Kc + pd.Kd * 1j * w) * inner_response(K, T_prop, T1, tau, w)[0], w)
        worst = min(worst, float(m.pm_deg) if m.stable else -np.inf)
    return worst


def held_back_gains(b: Bundle, post: np.ndarray, f, rule: PD, refined: PD) -> tuple[PD, float]:
    """``rule^(1-a) refined^a`` (each gain) with the largest ``a`` in steps of
    ``1/HOLD_BACK_STEPS`` that keeps :data:`REFINED_MIN_PM_DEG` on every likely shape, and
    that ``a`` (0: the rule's gains).

    The rule keeps about 20 deg there by construction; the step that first loses the
    margin ends the search (its evidence: docs/identification.md).
    """
    held, a = rule, 0.0
    for step in range(1, HOLD_BACK_STEPS + 1):
        x = step / HOLD_BACK_STEPS
        pd = PD(rule.Kc ** (1 - x) * refined.Kc ** x, rule.Kd ** (1 - x) * refined.Kd ** x)
        if _min_pm_on_likely(b, post, f, pd) < REFINED_MIN_PM_DEG:
            break
        held, a = pd, x
    return held, a


def steady_points(t, u, y):
    """The relay cycles' measured harmonics, or ``None`` with fewer than two cycles.

    Raises
    ------
    IdentificationError
        The fundamental varies from cycle to cycle by more than :data:`STEADY_MAX_SD`.
    """
    try:
        pts = harmonic_points(t, u, y)
    except ValueError:
        return None
    if pts.spread[0] > STEADY_MAX_SD:
        raise IdentificationError(
            f"the relay cycles are not steady (cycle-to-cycle spread of the fundamental "
            f"{pts.spread[0]:.2f} in log units, need <= {STEADY_MAX_SD}): let the relay run "
            "longer or reduce disturbances, then retry")
    return pts


def harmonic_posterior(b: Bundle, probs: np.ndarray, f, pts) -> np.ndarray:
    """The classifier's probabilities times the likelihood of the measured harmonics.

    Each shape, at the scale its period gives and the gain exact gain scaling gives,
    predicts the response at the relay's harmonics; how well it matches the measured
    points (their standard errors from the cycle spread) weighs the shape.
    """
    K, sp = _shape_models(b, f)
    T_prop, T1, tau = sp.T
    G = K[:, None] * inner_response(1.0, T_prop, T1, tau, pts.w)
    ll = np.nan_to_num(class_log_likelihood(pts, G), nan=-np.inf)
    lp = np.log(np.maximum(np.asarray(probs, float), 1e-300)) + ll
    if not np.isfinite(lp.max()):
        return probs
    post = np.exp(lp - lp.max())
    return post / post.sum()


def refined_identification(b: Bundle, probs: np.ndarray, f, pts,
                           K_true: float | None = None) -> Refinement:
    """Gains from the classifier, the measured harmonics and a local model fit.

    The Bayes rule on the posterior of :func:`harmonic_posterior` names a shape; its model
    (scale from the period, gain from exact gain scaling) is refined on the measured points
    (:func:`mrft_gcs.identify.harmonics.fit_inner_model`) and the gains are the optimal PD
    of the refined model (PM >= 20 deg on it). ``pts`` ``None``: the classifier's rule
    alone. A refinement whose gains differ from the rule's by more than
    :data:`MAX_REFINE_FACTOR`, or whose design is unstable, is dropped for the rule's
    gains; one that leaves less than :data:`REFINED_MIN_PM_DEG` on a likely shape is
    approached only as far as that margin allows (:func:`held_back_gains`; attitude only,
    :data:`HOLD_BACK_KINDS`), and on cycles less steady than :data:`HOLD_BACK_MAX_SPREAD`
    not at all. ``K_true``: the gain is known (the "normalised gain" evaluation) and is
    not fitted.
    """
    post = probs if pts is None else harmonic_posterior(b, probs, f, pts)
    if K_true is None:
        pd, k, c, K = scaled_gains(b, post, f.period_s, f.amplitude, f.h)
    else:
        pd, k, c, K = scaled_gains(b, post, f.period_s, f.amplitude, f.h, GainScaling.TRUE,
                                   K_true)
    shape = b.shape_params[k] * c
    model = InnerModel(K=K, T_prop=float(shape[0]), T1=float(shape[1]), tau=float(shape[2]))
    if pts is None:
        return Refinement(pd, model, k, c, post, float("nan"), float("nan"))
    params, cost = fit_inner_model(pts, (K, *shape), prior_log_sd=PRIOR_LOG_SD,
                                   fix_gain=K_true is not None)
    K_fit, T_prop, T1, tau = params
    w = frequency_grid(T_prop, T1, tau, n=500)
    design = optimal_pd(inner_response(K_fit, T_prop, T1, tau, w)[0], w)
    change = np.abs(np.log([design.pd.Kc / pd.Kc, design.pd.Kd / pd.Kd]))
    unexplained = K_true is None and (not np.all(change <= np.log(MAX_REFINE_FACTOR))
                                      or cost > MAX_FIT_COST)
    if not design.margins.stable or unexplained:
        # the refined model is unlike any the classifier considered: a record the model
        # structure does not explain; keep the classifier's rule
        return Refinement(pd, model, k, c, post, float("inf"), 0.0)
    refined = InnerModel(*(float(v) for v in params))
    if K_true is not None or _min_pm_on_likely(b, post, f, design.pd) >= REFINED_MIN_PM_DEG:
        return Refinement(design.pd, refined, k, c, post, cost, 1.0)
    # the refinement starts from the Bayes rule's shape, not the likeliest one: its optimum
    # must not undo the rule's safety on the shapes still in play. On wandering cycles the
    # refined delay can be far off, so the rule stands; on steady ones (whose posterior may
    # spread over a time constant the short cycles cannot see) the gains move towards the
    # refined ones as far as the margin on the likely shapes allows
    if b.kind not in HOLD_BACK_KINDS or pts.spread[0] > HOLD_BACK_MAX_SPREAD:
        return Refinement(pd, model, k, c, post, float("inf"), 0.0)
    held, a = held_back_gains(b, post, f, pd, design.pd)
    return Refinement(held, model, k, c, post, cost if a > 0 else float("inf"), a)


def identify(kind: LoopKind, t: np.ndarray, u: np.ndarray, y: np.ndarray, *, beta: float,
             h: float, bias: float = 0.0, inner: Identification | None = None,
             setpoint=None, tilt: np.ndarray | None = None) -> Identification:
    """Identify a loop from samples of its steady relay oscillation.

    Parameters
    ----------
    kind : LoopKind
        Which domain and classifier to use.
    t, u, y : arrays (m,)
        Time (s), relay output (with bias) and measured variable, covering at
        least one full cycle (more is better: the last complete one is used).
        Any sample rate; it is resampled.
    beta, h, bias : float
        The relay that ran.
    inner : Identification, optional
        The attitude identification, required for side motion.
    setpoint : float or array (m,), optional
        The relay's set point; when given, cycles that do not cross it every
        half-cycle (a degenerate test) are refused rather than identified.
    tilt : array (m,), optional
        Side motion: the measured tilt along the axis at the times ``t``. The side
        model is then fitted behind the attitude loop as measured during the test
        rather than as modelled (see :func:`_fit_side`).

    Raises
    ------
    IdentificationError
        No complete cycle in the data, or no bundled model for the loop
        (:class:`~mrft_gcs.errors.SetpointNotCrossed` for cycles that miss the set point).
    """
    if kind is LoopKind.SIDE:
        if inner is None:
            raise IdentificationError("side-motion identification needs the attitude loop "
                                      "identified first")
        return _identify_side(t, u, y, beta, inner, setpoint, tilt)
    b = load_bundle(kind)
    if abs(beta - b.beta) > 1e-6:
        raise IdentificationError(
            f"the {kind.value} classifier was trained for beta={b.beta}, the test ran beta={beta}")
    f = cycle_features(t, u, y, setpoint=setpoint)
    probs = _softmax(b.logits(f.x)[0])
    pts = steady_points(t, u, y)
    pd, model, k, c, post, cost, held_back = refined_identification(b, probs, f, pts)
    same = np.flatnonzero(b.rep_shape == k)
    rep = int(same[np.argmin(np.abs(np.log(b.reps[same, 1] / c)))]) if same.size else k
    return Identification(kind=kind, model=model, class_index=rep, confidence=float(post[k]),
                          beta=beta, h=f.h, period_s=f.period_s, amplitude=f.amplitude,
                          gains=pd, diagnostics=Diagnostics(
                              Method.CLASSIFIER if pts is None or not np.isfinite(cost)
                              else Method.CLASSIFIER_HARMONICS, shape=k, scale=float(c),
                              classifier=ClassifierVote(
                                  rule=k, top=tuple(int(i) for i in np.argsort(-post)[:3]),
                                  duty=float(f.duty), bias=float(f.bias),
                                  likeliest=int(np.argmax(probs)),
                                  probs=tuple(float(p) for p in np.sort(probs)[::-1][:3])),
                              fit=None if pts is None else HarmonicFit(float(cost),
                                                                       float(held_back))))
