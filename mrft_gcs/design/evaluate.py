"""Table VI: identification and tuning accuracy on random processes of a domain.

For ``n`` processes drawn log-uniformly from the domain (seeded), with a random
gain, measurement noise and relay bias as in training, the MRFT at the
distinguishing phase is simulated and identified with the bundled classifier.
Gains are then computed three ways (normalised gain: the true ``K``; DF gain:
``zeta = 4/pi``; exact gain scaling) and scored on the true process by the
deterioration ``J`` against its own optimal PD and the phase margin. The
baseline is the classic relay test (``beta = 0``) with describing-function
Ziegler-Nichols PD tuning (``Kc = 0.8 Ku``, ``Td = Tu / 8``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np

from mrft_gcs.design.dataset import BIAS_MAX, NOISE_MAX
from mrft_gcs.design.discretize import Discretisation
from mrft_gcs.design.pipeline import load_json
from mrft_gcs.domains import D_ATT, D_SIDE, domain_for
from mrft_gcs.errors import IdentificationError
from mrft_gcs.features import cycle_features
from mrft_gcs.identify.result import Method
from mrft_gcs.identify.runtime import (
    MODELS_DIR,
    GainScaling,
    _softmax,
    identify,
    load_bundle,
    refined_identification,
    relay_settings,
    scaled_gains,
    steady_points,
)
from mrft_gcs.loops import LoopKind
from mrft_gcs.pd_design import frequency_grid, ise, margins, optimal_pd
from mrft_gcs.plant import (
    InnerModel,
    SideModel,
    closed_inner_response,
    inner_response,
    side_response,
)
from mrft_gcs.simulate import simulate_mrft, simulate_side_mrft

__all__ = ["MethodScore", "Trial", "Evaluation", "evaluate", "evaluate_side"]

METHODS = ("normalised gain", "DF gain", "exact gain", "classic relay + DF (baseline)")


@dataclass(frozen=True)
class MethodScore:
    """Scores of one method over the test set (J in %, PM in deg)."""

    name: str
    J: np.ndarray
    pm: np.ndarray

    def summary(self) -> dict[str, float]:
        """J and PM over the identified loops; failures counted apart.

        ``no_cycle``: no steady relay cycle to identify (``J`` is NaN there);
        ``unstable``: the tuned loop is unstable (``J`` infinite).
        """
        ok = np.isfinite(self.J)
        ident = ~np.isnan(self.J)
        return {"J_avg": float(np.mean(self.J[ok])) if ok.any() else np.inf,
                "J_p95": float(np.percentile(self.J[ok], 95)) if ok.any() else np.inf,
                "J_max": float(np.max(self.J[ident])) if ident.any() else np.inf,
                "PM_avg": float(np.mean(self.pm[ok])) if ok.any() else np.nan,
                "PM_min": float(np.min(self.pm[ident])) if ident.any() else np.nan,
                "unstable": int(np.sum(np.isinf(self.J))), "no_cycle": int(np.sum(~ident))}


@dataclass(frozen=True)
class Trial:
    """One identified loop of the evaluation, exact gain scaling: what to look at when J is off.

    Attributes
    ----------
    index : int
        Trial number (same draws for the same seed).
    true : dict
        The process: gain and time constants (s); side trials also the attitude process.
    fitted : dict
        The identified model, same keys.
    J : float
        Deterioration (%) of the identified gains on the true process.
    pm_deg : float
        Their phase margin on the true process.
    method : str
        The identification path (:class:`~mrft_gcs.identify.Method`).
    noise, bias : float
        Measurement noise (fraction of the clean cycle's amplitude) and relay bias
        (fraction of ``h``).
    """

    index: int
    true: dict
    fitted: dict
    J: float
    pm_deg: float
    method: str
    noise: float
    bias: float

    def as_dict(self) -> dict:
        return {"index": self.index, "J": self.J, "PM": self.pm_deg, "true": self.true,
                "fitted": self.fitted, "method": self.method, "noise": self.noise,
                "bias": self.bias}


@dataclass(frozen=True)
class Evaluation:
    kind: str
    n: int
    seed: int
    scores: tuple[MethodScore, ...]
    accuracy: float
    trials: tuple[Trial, ...] = ()

    def table(self) -> list[dict]:
        return [{"method": s.name, **s.summary()} for s in self.scores]

    def worst(self, count: int = 10) -> list[Trial]:
        """The ``count`` identified loops with the largest J (unstable first), exact gain."""
        return sorted(self.trials, key=lambda t: -t.J)[:count]


def _score(Kc: float, Kd: float, p, design, w) -> tuple[float, float]:
    T_prop, T1, tau = p
    G = inner_response(1.0, T_prop, T1, tau, w)[0]
    m = margins((Kc + Kd * 1j * w) * G, w)
    if not m.stable:
        return np.inf, m.pm_deg
    return (ise(Kc, Kd, G, w) - design.ise) / design.ise * 100.0, m.pm_deg


def evaluate(kind: LoopKind, n: int = 500, seed: int = 1, progress=None) -> Evaluation:
    """Run the Table VI evaluation for an inner loop kind."""
    b = load_bundle(kind)
    rng = np.random.default_rng(seed)
    params = domain_for(kind).sample_log_uniform(n, rng)
    T_prop, T1, tau = params.T
    K = np.exp(rng.uniform(np.log(0.5), np.log(50.0), n))
    h = b.h
    # size noise from the likely amplitude: simulate once noise-free (cheap) to know it
    clean = simulate_mrft(K, T_prop, T1, tau, beta=b.beta, h=h,
                          duration_s=1.0 + 12 * params[:, 1].max(), keep_s=4.0)
    amp0 = np.array([0.5 * np.ptp(clean.y[i, -1500:]) for i in range(n)])
    noise = rng.uniform(0, NOISE_MAX, n) * amp0
    bias = rng.uniform(-BIAS_MAX, BIAS_MAX, n) * h
    dur = 1.0 + 14 * params[:, 1].max()
    run = simulate_mrft(K, T_prop, T1, tau, beta=b.beta, h=h, bias=bias, noise_std=noise,
                        band=4 * noise, duration_s=dur, keep_s=5.0, seed=seed)
    base = simulate_mrft(K, T_prop, T1, tau, beta=0.0, h=h, bias=bias, noise_std=noise,
                         band=4 * noise, duration_s=dur, keep_s=5.0, seed=seed + 7)
    J = {m: np.full(n, np.nan) for m in METHODS}
    PM = {m: np.full(n, np.nan) for m in METHODS}
    trials = []
    hits = 0
    disc = Discretisation.from_json(load_json(kind, "discretisation"))
    truth = disc.owner_of(params)
    for i in range(n):
        p = params[i]
        w = frequency_grid(T_prop[i], T1[i], tau[i], n=500)
        design = optimal_pd(inner_response(1.0, T_prop[i], T1[i], tau[i], w)[0], w)
        try:
            f = cycle_features(run.t, run.u[i], run.y[i], setpoint=0.0)
        except Exception:  # noqa: BLE001 - no cycle: counts as a failure (J = inf)
            continue
        probs = _softmax(b.logits(f.x)[0])
        hits += int(np.argmax(probs) == truth[i])
        try:
            pts = steady_points(run.t, run.u[i], run.y[i])
        except IdentificationError:  # not a steady oscillation: refused, as in flight
            continue
        pd, model, _, _, _, cost, _ = refined_identification(b, probs, f, pts)
        if pts is None:
            for name, scaling in ((METHODS[0], GainScaling.TRUE), (METHODS[1], GainScaling.DF),
                                  (METHODS[2], GainScaling.EXACT)):
                g, *_ = scaled_gains(b, probs, f.period_s, f.amplitude, f.h, scaling, K[i])
                J[name][i], PM[name][i] = _score(g.Kc * K[i], g.Kd * K[i], p, design, w)
        else:
            # DF: the gain from 4/pi's estimate of |G| instead of the measured one
            df = abs(pts.G[0]) * (4 * f.h / np.pi) / f.amplitude
            for name, factor in ((METHODS[1], df), (METHODS[2], 1.0)):
                J[name][i], PM[name][i] = _score(pd.Kc * factor * K[i], pd.Kd * factor * K[i],
                                                 p, design, w)
            g, *_ = refined_identification(b, probs, f, pts, K_true=K[i])  # gain known
            J[METHODS[0]][i], PM[METHODS[0]][i] = _score(g.Kc * K[i], g.Kd * K[i], p, design, w)
        names = ("K", "T_prop", "T1", "tau")
        trials.append(Trial(
            i, dict(zip(names, (float(K[i]), *map(float, p)), strict=True)),
            {k: float(getattr(model, k)) for k in names}, float(J[METHODS[2]][i]),
            float(PM[METHODS[2]][i]),
            "classifier" if pts is None or not np.isfinite(cost) else "classifier + harmonics",
            float(noise[i] / amp0[i]) if amp0[i] > 0 else 0.0, float(bias[i] / h)))
        try:
            fb = cycle_features(base.t, base.u[i], base.y[i], setpoint=0.0)
            Ku = 4 * fb.h / (np.pi * fb.amplitude)
            Kc = 0.8 * Ku
            Kd = Kc * fb.period_s / 8
            J[METHODS[3]][i], PM[METHODS[3]][i] = _score(Kc * K[i], Kd * K[i], p, design, w)
        except Exception:  # noqa: BLE001
            pass
        if progress:
            progress(i + 1, n)
    scores = tuple(MethodScore(m, J[m], PM[m]) for m in METHODS)
    return Evaluation(kind.value, n, seed, scores, hits / n, tuple(trials))


def evaluate_side(n: int = 200, seed: int = 1, progress=None) -> Evaluation:
    """Table VI, side motion: random attitude and side processes, tuned in sequence.

    Each trial draws an attitude process (D_att) and a side process (D_side),
    identifies the attitude loop from its MRFT (as in flight), closes it with the
    identified gains, runs the side MRFT on the cascade and identifies it. The
    side gains are scored against the optimal side PD *for that closed attitude
    loop*. Noise and relay bias as in training. The DF variant uses 4/pi; the
    baseline is a classic relay on position with Ziegler-Nichols DF tuning.
    """
    b = load_bundle(LoopKind.ATTITUDE)
    rng = np.random.default_rng(seed)
    att = D_ATT.sample_log_uniform(n, rng)
    side = D_SIDE.sample_log_uniform(n, rng)
    Ka = np.exp(rng.uniform(np.log(0.5), np.log(50.0), n))
    Ks = 9.81 * side[:, 0]
    names = ("exact gain", "DF gain", "classic relay + DF (baseline)")
    J = {m: np.full(n, np.nan) for m in names}
    PM = {m: np.full(n, np.nan) for m in names}
    trials = []
    T_prop, T1, tau = att.T
    run = simulate_mrft(Ka, T_prop, T1, tau, beta=b.beta, h=b.h,
                        duration_s=1.0 + 14 * att[:, 1].max(), keep_s=5.0, seed=seed)
    for i in range(n):
        try:
            a_id = identify(LoopKind.ATTITUDE, run.t, run.u[i], run.y[i], beta=b.beta, h=b.h,
                            setpoint=0.0)
            rs = relay_settings(LoopKind.SIDE, inner=a_id)
        except Exception:  # noqa: BLE001 - attitude not identified: the side test cannot run
            continue
        pd = a_id.gains
        w = np.logspace(-3, np.log10(200 / min(att[i, 0], att[i, 2])), 900)
        T = closed_inner_response(pd.Kc * Ka[i], pd.Kd * Ka[i],
                                  inner_response(1.0, T_prop[i], T1[i], tau[i], w), w)
        P = (T * side_response(1.0, side[i, 0], side[i, 1], w))[0]
        design = optimal_pd(P, w)
        if not design.margins.stable:
            continue
        # noise sized from the cycle's own amplitude (a clean run first), as for the inner loops
        clean = simulate_side_mrft((Ka[i], *att[i]), (pd.Kc, pd.Kd), (Ks[i], *side[i]),
                                   beta=rs.beta, h=rs.h, duration_s=4.0 + 40 * side[i, 0],
                                   keep_s=10.0, seed=seed + i)
        noise = rng.uniform(0, NOISE_MAX) * 0.5 * np.ptp(clean.y[0])
        bias = rng.uniform(-BIAS_MAX, BIAS_MAX) * rs.h
        srun = simulate_side_mrft((Ka[i], *att[i]), (pd.Kc, pd.Kd), (Ks[i], *side[i]),
                                  beta=rs.beta, h=rs.h, bias=bias, noise_std=noise,
                                  band=4 * noise, duration_s=4.0 + 40 * side[i, 0],
                                  keep_s=30.0, seed=seed + i)
        try:
            s_id = identify(LoopKind.SIDE, srun.t, srun.u[0], srun.y[0], beta=rs.beta, h=rs.h,
                            inner=a_id, setpoint=0.0)
        except Exception:  # noqa: BLE001
            continue
        for name, scale in (("exact gain", 1.0), ("DF gain", None)):
            Kc, Kd = s_id.gains.Kc, s_id.gains.Kd
            vote, fit = s_id.diagnostics.classifier, s_id.diagnostics.fit
            if scale is None and s_id.diagnostics.method is Method.CLASSIFIER:
                assert vote is not None  # the side classifier ran
                # DF: gain from 4/pi |G|, not the simulated amplitude of the chosen class
                table = json.loads((MODELS_DIR / "side" / f"shape_{a_id.diagnostics.shape:02d}"
                                    / "classes.json").read_text())
                z = table["zeta"][vote.rule]
                Kc, Kd = Kc * (4 / np.pi) / z, Kd * (4 / np.pi) / z
            elif scale is None and fit is not None:  # DF estimate of |G|, not the measured one
                Kc, Kd = Kc * fit.df_factor, Kd * fit.df_factor
            Kc, Kd = Kc * Ks[i], Kd * Ks[i]
            m = margins((Kc + Kd * 1j * w) * P, w)
            J[name][i] = (ise(Kc, Kd, P, w) - design.ise) / design.ise * 100 if m.stable else np.inf
            PM[name][i] = m.pm_deg
        am, sm = a_id.model, s_id.model
        assert isinstance(am, InnerModel) and isinstance(sm, SideModel)  # by the loop kinds
        trials.append(Trial(
            i, {"K": float(Ks[i]), "T2": float(side[i, 0]), "tau": float(side[i, 1]),
                "attitude": [float(Ka[i]), *map(float, att[i])]},
            {"K": float(sm.K), "T2": float(sm.T2), "tau": float(sm.tau),
             "attitude": [float(am.K), float(am.T_prop), float(am.T1), float(am.tau)]},
            float(J["exact gain"][i]), float(PM["exact gain"][i]), str(s_id.diagnostics.method),
            float(noise / (0.5 * np.ptp(clean.y[0]))) if np.ptp(clean.y[0]) > 0 else 0.0,
            float(bias / rs.h)))
        brun = simulate_side_mrft((Ka[i], *att[i]), (pd.Kc, pd.Kd), (Ks[i], *side[i]), beta=0.0,
                                  h=rs.h, bias=bias, noise_std=noise, band=4 * noise,
                                  duration_s=4.0 + 40 * side[i, 0], keep_s=30.0, seed=seed + i)
        try:
            fb = cycle_features(brun.t, brun.u[0], brun.y[0], setpoint=0.0)
            Ku = 4 * fb.h / (np.pi * fb.amplitude)
            Kc, Kd = 0.8 * Ku, 0.8 * Ku * fb.period_s / 8
            m = margins((Kc + Kd * 1j * w) * Ks[i] * P, w)
            J[names[2]][i] = ((ise(Kc * Ks[i], Kd * Ks[i], P, w) - design.ise) / design.ise * 100
                              if m.stable else np.inf)
            PM[names[2]][i] = m.pm_deg
        except Exception:  # noqa: BLE001
            pass
        if progress:
            progress(i + 1, n)
    return Evaluation("side", n, seed, tuple(MethodScore(m, J[m], PM[m]) for m in names), np.nan,
                      tuple(trials))
