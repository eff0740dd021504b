"""The autopilot's closed attitude loop, measured during the side relay, as an inner loop.

On the attitude actuation path (SET_ATTITUDE_TARGET) the autopilot keeps its own
attitude loop, so the side-motion identification cannot start from an identified
attitude model and its PD as on the torque path. What the side fit needs of the
attitude loop is only its closed-loop response ``T_att(jw)`` (attitude set point to
measured angle), and that can be *measured*: the side relay drives the tilt set
point with a square wave whose odd harmonics (1, 3, 5, ... 15) each give a point of
``T_att`` as the ratio of the Fourier coefficients of the measured tilt (ATTITUDE)
and the commanded tilt, over the same steady cycles
(:func:`mrft_gcs.identify.harmonics.harmonic_points`).

Between and beyond those points ``T_att`` comes from a small model fitted on them:
the closed loop of an *equivalent* attitude process ``e^{-tau s}/(s (T_prop s + 1)
(T1 s + 1))`` (``K = 1``) under a PD ``u = Kc e - Kd dy/dt``,
``T = Kc G / (1 + (Kc + Kd s) G)``, the very form the side identification
(:func:`mrft_gcs.identify.identify` with ``inner=``) takes its attitude loop in. The
closed loop depends on ``K Kc`` and ``K Kd`` only, so ``K = 1`` loses nothing. This is
a description of the measured response, not a claim about the autopilot's structure:
a real PX4 or ArduPilot loop (rate I, feed-forward, input shaping, filters) is not of
this form, and the fit only promises to follow the measured points (its residual is
reported, and a fit that does not follow them is refused). Above the highest
measured harmonic the equivalent is an extrapolation; there the side cascade is
already attenuated by its integrator and drag lag.

The attitude class reported with it (``diagnostics.shape`` and ``.scale``: the
bundled attitude shape whose closed loop under its own optimal PD is nearest to the
measurement) picks the side classifier, which decides only when the harmonic fit of
the side model cannot run.
"""

from __future__ import annotations

import json
from collections import Counter
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from mrft_gcs.errors import IdentificationError
from mrft_gcs.identify.harmonics import harmonic_points
from mrft_gcs.identify.result import (
    Diagnostics,
    Identification,
    MeasuredLoop,
    Method,
    RelaySettings,
)
from mrft_gcs.identify.side import SIDE_H
from mrft_gcs.loops import LoopKind
from mrft_gcs.pd_design import margins
from mrft_gcs.plant import PD, InnerModel, closed_inner_response, inner_response

__all__ = [
    "CLOSED_LOOP_HARMONICS",
    "ClosedLoopFit",
    "closed_loop_points",
    "fit_closed_loop",
    "closed_attitude_identification",
    "side_relay_settings",
]

#: Odd harmonics of the side relay cycle at which the closed attitude loop is measured
#: (a side cycle of 1-3 s puts the 15th at 30-95 rad/s, past an attitude loop's bandwidth).
CLOSED_LOOP_HARMONICS = (1, 3, 5, 7, 9, 11, 13, 15)
#: A fit whose RMS residual over the measured points (log magnitude and phase together,
#: weighted) exceeds this many standard errors does not describe the loop: refused.
MAX_RMS_SD = 3.0
#: Harmonics up to this one are never dropped from the fit (the side fit uses 1-7).
KEPT_HARMONICS = 7
#: Model error allowed at every point on top of its measured standard error (log units):
#: the equivalent form cannot follow every autopilot's loop exactly, and the side fit
#: needs ``T_att`` to a few per cent, not to the measurement's precision.
MODEL_SD = 0.05
#: Width (log units) of the prior on the five parameters about the grid start: only
#: regularises the one direction the points cannot see (without delay the closed loop is a
#: third-order all-pole form with three free coefficients for four parameters). Measured on
#: a PX4-style loop (test_closed_loop): with 1.0 the fit missed harmonics 1-7 by 8-16 %,
#: with 10 by 2-7 %.
PRIOR_LOG_SD = 10.0

_MODELS = Path(__file__).resolve().parents[2] / "models"


@dataclass(frozen=True)
class ClosedLoopFit:
    """An equivalent attitude model (``K = 1``) and PD whose closed loop follows the points.

    Attributes
    ----------
    model : InnerModel
        ``K = 1``, ``T_prop``, ``T1``, ``tau`` (s).
    gains : PD
        The equivalent's PD (for ``K = 1``).
    w : array (k,)
        Measured frequencies (rad/s).
    T : array (k,) complex
        Measured closed-loop response there.
    sd : array (k,)
        Standard errors of ``log T`` (:class:`~mrft_gcs.identify.harmonics.HarmonicPoints`).
    rms_sd : float
        RMS weighted residual of the fit over the points (1 = within the standard errors).
    max_dev : tuple of float
        Largest deviation of the fitted from the measured response: magnitude ratio - 1
        and phase (deg).
    shape, scale : int, float
        The nearest bundled attitude shape and its time scale.
    cost : float
        Weighted sum of squared residuals (a chi-square figure with ``2k - 5`` degrees
        of freedom when the standard errors are right).
    harmonics : tuple of int
        The harmonics of the relay cycle behind ``w`` (some high ones may be dropped).
    """

    model: InnerModel
    gains: PD
    w: np.ndarray
    T: np.ndarray
    sd: np.ndarray
    rms_sd: float
    max_dev: tuple[float, float]
    shape: int
    scale: float
    cost: float = float("nan")  # weighted sum of squared residuals (chi-square, 2k - 5 dof)
    harmonics: tuple[int, ...] = ()  # the harmonics fitted (after dropping spoilt ones)

    def response(self, w) -> np.ndarray:
        """The fitted closed loop at ``w`` (rad/s), shape ``(m,)``."""
        return _closed(np.log(self.params()), np.asarray(w, float))

    def params(self) -> np.ndarray:
        """``(Kc, Kd, T_prop, T1, tau)``."""
        m, g = self.model, self.gains
        return np.array([g.Kc, g.Kd, m.T_prop, m.T1, m.tau])


def _closed(lp: np.ndarray, w: np.ndarray) -> np.ndarray:
    Kc, Kd, Tp, T1, tau = np.exp(lp)
    return closed_inner_response(Kc, Kd, inner_response(1.0, Tp, T1, tau, w), w)[0]


def closed_loop_points(t, u, tilt, cycles: int = 3, harmonics=CLOSED_LOOP_HARMONICS):
    """``T_att`` at the odd harmonics of the side relay, from commanded and measured tilt.

    Parameters
    ----------
    t, u, tilt : arrays (m,)
        Time (s), commanded tilt along the axis (the side relay's output, rad) and the
        measured tilt along it (rad) at the same times, covering the steady cycles.

    Returns
    -------
    HarmonicPoints
        See :func:`mrft_gcs.identify.harmonics.harmonic_points`.

    Raises
    ------
    IdentificationError
        Fewer than two complete relay cycles, or values that are not finite.
    """
    t, u, tilt = (np.asarray(a, float) for a in (t, u, tilt))
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(u)) and np.all(np.isfinite(tilt))):
        raise IdentificationError("the tilt record holds NaN or infinite values; drop them "
                                  "first")
    try:
        return harmonic_points(t, u, tilt, cycles=cycles, harmonics=harmonics)
    except ValueError as exc:
        raise IdentificationError(f"closed attitude loop: {exc}: let the side relay run "
                                  "longer") from None


@lru_cache(maxsize=1)
def _shape_table() -> tuple[np.ndarray, np.ndarray]:
    """The bundled attitude shapes ``(T_prop, T1, tau)`` and their unit optimal PDs."""
    path = _MODELS / "attitude" / "classes.json"
    try:
        c = json.loads(path.read_text())
        return np.asarray(c["shape_params"], float), np.asarray(c["shape_pd"], float)
    except (OSError, KeyError, ValueError) as exc:
        raise IdentificationError(
            f"no usable bundled attitude class table in {path} ({exc}): regenerate it with "
            "'mrft-tune design train --loop attitude'") from None


@lru_cache(maxsize=1)
def _side_betas() -> dict[int, float]:
    """The MRFT beta of each bundled side classifier, by attitude shape."""
    out = {}
    for d in sorted((_MODELS / "side").glob("shape_*")):
        try:
            out[int(d.name.split("_")[1])] = float(json.loads(
                (d / "classes.json").read_text())["beta"])
        except (OSError, KeyError, ValueError, IndexError):
            continue
    return out


def side_relay_settings() -> RelaySettings:
    """Side relay settings when the attitude loop is not identified (attitude path).

    The side classifiers' beta depends on the attitude shape, which is measured only
    during the side relay itself; the bundled ones share one beta (the most common is
    taken, and the attitude shape is then chosen among those that use it).

    Raises
    ------
    IdentificationError
        No bundled side classifiers.
    """
    betas = _side_betas()
    if not betas:
        raise IdentificationError(
            f"no bundled side classifiers in {_MODELS / 'side'}: regenerate them with "
            "'mrft-tune design side' (needs pip install -e '.[design]')")
    beta = Counter(betas.values()).most_common(1)[0][0]
    return RelaySettings(beta=beta, h=SIDE_H)


def _grid_starts(w, T, wt, shapes: np.ndarray, n: int = 4) -> list[tuple[int, float, np.ndarray]]:
    """The ``n`` bundled shapes (with their best time scale) whose closed loop under their
    optimal PD fits best: ``(shape, scale, log (Kc, Kd, T_prop, T1, tau))``, best first."""
    params, pds = _shape_table()
    scales = np.exp(np.linspace(np.log(1e-3), np.log(10.0), 161))
    found = []
    for k in shapes:
        tp, t1, tau = params[k]
        kc, kd = pds[k]
        # the unit shape stretched by c has the closed loop T_unit(j w c) under (Kc, Kd c)
        s = 1j * w[None, :] * scales[:, None]
        G = np.exp(-tau * s) / (s * (tp * s + 1) * (t1 * s + 1))
        d = np.log(kc * G / (1 + (kc + kd * s) * G) / T[None, :])
        cost = np.sum(wt * (d.real ** 2 + d.imag ** 2), axis=1)
        i = int(np.argmin(cost))
        c = float(scales[i])
        # as K = 1 with time constants x c: gains Kc / c, Kd
        found.append((float(cost[i]), int(k), c, np.log([kc / c, kd, tp * c, t1 * c, tau * c])))
    found.sort(key=lambda f: f[0])
    return [(k, c, p) for _, k, c, p in found[:n]]


def _fit(w, T, sd, shapes) -> tuple[int, float, np.ndarray]:
    """Best ``(shape, scale, log params)`` over the grid starts (see :func:`fit_closed_loop`)."""
    best = None
    for k, c, p0 in _grid_starts(w, T, 1.0 / sd ** 2, shapes):
        def resid(lp, p0=p0):
            d = np.log(_closed(lp, w) / T) / sd
            return np.r_[d.real, d.imag, (lp - p0) / PRIOR_LOG_SD]

        res = least_squares(resid, p0, method="lm", xtol=1e-10, ftol=1e-10, max_nfev=2000)
        if best is None or res.cost < best[0]:
            best = (res.cost, k, c, res.x)
    assert best is not None
    return best[1], best[2], best[3]


def fit_closed_loop(points, shapes=None) -> ClosedLoopFit:
    """Fit the equivalent attitude model and PD on measured closed-loop points.

    Weighted least squares on log magnitude and phase (weights ``1/sd``), started from
    the nearest bundled shapes (:func:`_grid_starts`) and held near it by a weak prior
    (:data:`PRIOR_LOG_SD`); the four best starts are tried. Each point's standard
    error is widened by :data:`MODEL_SD`. While a point above :data:`KEPT_HARMONICS`
    misses the fit by more than :data:`MAX_RMS_SD` standard errors, the worst is
    dropped and the fit repeated: the high harmonics are small (``|T|`` of 0.1-0.3) and
    the first to be spoilt by a stalled setpoint stream, and the side fit needs them
    least. The fit is refused if it then still misses the points (RMS).

    Parameters
    ----------
    points : HarmonicPoints
        From :func:`closed_loop_points`.
    shapes : sequence of int, optional
        Attitude shapes the class may be chosen from (default all).

    Raises
    ------
    IdentificationError
        The fit does not follow the points within :data:`MAX_RMS_SD` standard errors,
        or its equivalent loop is unstable.
    """
    keep = np.isfinite(points.G) & (np.abs(points.G) > 0)
    w, T, sd = points.w[keep], points.G[keep], points.sd[keep]
    harm = np.asarray(points.harmonics)[keep]
    if w.size < 3:
        raise IdentificationError("closed attitude loop: fewer than three measured harmonics; "
                                  "let the side relay run longer")
    shapes = np.asarray(list(range(len(_shape_table()[0])) if shapes is None else shapes), int)
    sd = np.sqrt(sd ** 2 + MODEL_SD ** 2)
    while True:
        k, c, lp = _fit(w, T, sd, shapes)
        d = np.log(_closed(lp, w) / T)
        z = (d.real ** 2 + d.imag ** 2) / sd ** 2
        rms = float(np.sqrt(np.mean(z)))
        worst = int(np.argmax(np.where(harm > KEPT_HARMONICS, z, -1.0)))
        if z[worst] <= MAX_RMS_SD ** 2 or harm[worst] <= KEPT_HARMONICS or w.size <= 4:
            break
        w, T, sd, harm = (np.delete(a, worst) for a in (w, T, sd, harm))
    Kc, Kd, Tp, T1, tau = (float(v) for v in np.exp(lp))
    model, gains = InnerModel(1.0, Tp, T1, tau), PD(Kc, Kd)
    wg = np.logspace(np.log10(1e-3 / (Tp + T1 + tau)), np.log10(200 / min(Tp, tau)), 1500)
    stable = margins((Kc + Kd * 1j * wg) * inner_response(1.0, Tp, T1, tau, wg)[0], wg).stable
    dev = (float(np.max(np.abs(np.exp(d.real) - 1))), float(np.degrees(np.max(np.abs(d.imag)))))
    if not stable:
        raise IdentificationError("closed attitude loop: the fitted equivalent loop is "
                                  "unstable; let the side relay run longer and retry")
    if rms > MAX_RMS_SD:
        raise IdentificationError(
            f"closed attitude loop: no equivalent loop follows the measured points (residual "
            f"{rms:.1f} standard errors, up to {dev[0]:.0%} and {dev[1]:.0f} deg): the "
            f"autopilot's attitude loop is not linear at this tilt (saturation?); lower the "
            f"side relay amplitude or check the attitude loop")
    return ClosedLoopFit(model=model, gains=gains, w=w, T=T, sd=sd, rms_sd=rms, max_dev=dev,
                         shape=k, scale=c, cost=float(np.sum(z)),
                         harmonics=tuple(int(h) for h in harm))


def closed_attitude_identification(t, u, tilt, *, beta: float, h: float,
                                   cycles: int = 3) -> Identification:
    """The closed attitude loop behind a side relay, as an attitude :class:`Identification`.

    Its ``model`` (``K = 1``) and ``gains`` reproduce the measured closed loop through
    :func:`mrft_gcs.plant.closed_inner_response`, so it can be passed as ``inner`` to
    :func:`mrft_gcs.identify.identify` for the side loop. ``beta``, ``h``: the side
    relay's. ``diagnostics``: :attr:`Method.CLOSED_LOOP`, ``shape`` and ``scale`` (the
    nearest bundled attitude shape among those whose side classifier ran at ``beta``)
    and the measured points with the fit's residual (``measured``).

    Raises
    ------
    IdentificationError
        See :func:`closed_loop_points` and :func:`fit_closed_loop`.
    """
    pts = closed_loop_points(t, u, tilt, cycles=cycles)
    shapes = [k for k, b in _side_betas().items() if abs(b - beta) <= 1e-6]
    if not shapes:
        raise IdentificationError(
            f"no bundled side classifier for beta={beta}: run the side relay with "
            f"side_relay_settings() or regenerate the side classifiers")
    fit = fit_closed_loop(pts, shapes=[k for k in shapes if k < len(_shape_table()[0])])
    from scipy.stats import chi2  # lazy: scipy.stats takes 0.6 s to import, at CLI start

    dof = 2 * fit.w.size - 5
    return Identification(
        kind=LoopKind.ATTITUDE, model=fit.model, class_index=fit.shape,
        confidence=float(chi2.sf(fit.cost, dof)) if dof > 0 else 1.0, beta=beta, h=h,
        period_s=pts.period_s, amplitude=0.5 * float(np.ptp(np.asarray(tilt, float))),
        gains=fit.gains,
        diagnostics=Diagnostics(Method.CLOSED_LOOP, shape=fit.shape, scale=fit.scale,
                                measured=MeasuredLoop(fit.w, fit.T, fit.sd, fit.rms_sd,
                                                      fit.harmonics, fit.max_dev)))
