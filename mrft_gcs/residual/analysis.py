"""Residual analysis: simulate the model under the relay that ran, compare, explain the gap.

:func:`analyse_residual` takes a linear model (identified, or given), the relay
that ran (``beta``, ``h``, ``bias``) and the measured ``(t, u, y)``. It

1. averages the last steady measured cycles into one waveform
   (:func:`~mrft_gcs.residual.cycles.cycle_wave`);
2. simulates the model under the same relay at the same sample time
   (:func:`~mrft_gcs.residual.simulate.simulate_effects`) and compares the
   steady cycles, aligned at the relay's rising switch: waveform RMS of the
   difference over one measured period, normalised by the measured amplitude
   (``rms``), period, amplitude, duty-cycle and harmonic-distortion errors;
3. when the RMS is significant (above a floor calibrated on clean runs and above
   three times the measurement noise left after averaging), fits every candidate
   effect of :mod:`~mrft_gcs.residual.effects` by a bounded 1-D search (a grid,
   then two finer grids around the best point, all candidates of all effects
   simulated together in one batch per round), and names the effect that
   explains the residual best, provided it removes at least ``min_reduction`` of
   it (the penalty that keeps noise and small model errors from naming an effect);
   when that best effect changes the dynamics (not only the relay's two input
   levels), the effect is chosen among those that do by driving the model with the
   recorded commands instead (:mod:`~mrft_gcs.residual.openloop`): the closed-loop
   cycle mixes lag effects up through the period, the response to each measured
   switch does not;
4. re-designs the PD with the effect where it changes the small-signal dynamics
   (extra delay, sensor filter, rate limit via its describing function, drag
   linearised at the test's rate, thrust-curve gain at hover) and reports the
   gain change.

:class:`ResidualReport.as_dict` gives the ``residual`` field of the tuning
report (README's report schema).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mrft_gcs.errors import IdentificationError
from mrft_gcs.loops import LoopKind
from mrft_gcs.pd_design import frequency_grid, optimal_pd
from mrft_gcs.plant import PD, InnerModel, SideModel, inner_response
from mrft_gcs.residual.cycles import CycleWave, cycle_wave, noise_std, rising_switches, uniform
from mrft_gcs.residual.effects import (
    Effect,
    Knobs,
    QuadraticDrag,
    RelayContext,
    candidate_effects,
)
from mrft_gcs.residual.noise import NoiseColour, noise_colour
from mrft_gcs.residual.openloop import InputWindow, input_rms, input_window
from mrft_gcs.residual.simulate import simulate_effects

__all__ = ["RelayTest", "EffectFit", "CycleErrors", "ResidualReport", "analyse_residual",
           "RMS_FLOOR", "MIN_REDUCTION", "LIKELIHOOD_GAP", "DRIVEN_MARGIN"]

#: Normalised RMS below which a residual is never significant (model and sampling
#: mismatch of clean SITL runs stays below it; see benchmarks/residual_confusion.py).
RMS_FLOOR = 0.06
#: Fraction of the residual an effect must remove to be named.
MIN_REDUCTION = 0.4
#: Input-driven fits whose squared residuals differ by less than this many times the
#: white noise's (summed over the samples compared) are listed as alternatives.
LIKELIHOOD_GAP = 10.0
#: ... or whose RMS differ by less than this fraction.
DRIVEN_MARGIN = 0.03


@dataclass(frozen=True)
class RelayTest:
    """The relay that ran: ``u = bias +- h`` with MRFT parameter ``beta`` (input units)."""

    beta: float
    h: float
    bias: float = 0.0


@dataclass(frozen=True)
class EffectFit:
    """Best fit of one candidate effect: its parameter value and the RMS left."""

    name: str
    param: str
    units: str
    value: float
    rms: float


@dataclass(frozen=True)
class CycleErrors:
    """Simulated minus measured steady cycle.

    Attributes
    ----------
    rms : float
        RMS of the waveform difference over one measured period / measured amplitude.
    period : float
        Relative period error ``(P_sim - P_meas) / P_meas``.
    amplitude : float
        Relative amplitude error.
    duty : float
        Duty-cycle difference (fraction of the cycle at the high relay level).
    thd : float
        Harmonic distortion difference (harmonics 2..5 over the fundamental).
    """

    rms: float
    period: float
    amplitude: float
    duty: float
    thd: float

    def as_dict(self) -> dict[str, float]:
        return {"rms": self.rms, "period": self.period, "amplitude": self.amplitude,
                "duty": self.duty, "thd": self.thd}


@dataclass(frozen=True)
class ResidualReport:
    """What residual analysis found for one loop.

    Attributes
    ----------
    rms_before, rms_after : float
        Normalised waveform RMS without and with the named effect (equal when none).
    effect : str or None
        Name of the effect added to the model, ``None`` when none is needed or none helps.
    effect_params : dict
        ``{param: value}`` of the named effect (empty when none).
    before, after : CycleErrors
        Cycle errors of the model, and of the model with the effect.
    significant : bool
        ``rms_before`` above ``threshold``.
    threshold : float
        Significance threshold used (normalised RMS).
    noise : float
        Measurement noise left in the averaged cycle (normalised RMS).
    measured : CycleWave
        The measured average cycle.
    fits : tuple of EffectFit
        Best fit of every candidate effect, best first.
    alternatives : tuple of str
        Effects that explain the data about as well as the named one.
    gains_model, gains_with_effect : PD or None
        Optimal PD of the model, and re-designed with the effect (set when an effect is named).
    design_note : str
        What the re-design did with the effect.
    open_loop : tuple of EffectFit
        Input-driven fits of the effects that change the dynamics, best first (``rms``:
        normalised residual of the model driven by the recorded commands); empty unless
        the closed-loop comparison pointed at the dynamics.
    """

    rms_before: float
    rms_after: float
    effect: str | None
    effect_params: dict[str, float]
    before: CycleErrors
    after: CycleErrors
    significant: bool
    threshold: float
    noise: float
    measured: CycleWave
    fits: tuple[EffectFit, ...] = ()
    alternatives: tuple[str, ...] = ()
    gains_model: PD | None = None
    gains_with_effect: PD | None = None
    design_note: str = ""
    open_loop: tuple[EffectFit, ...] = ()

    @property
    def reduction(self) -> float:
        """Fraction of the residual removed by the effect (0 when none is named)."""
        return 1.0 - self.rms_after / self.rms_before if self.rms_before > 0 else 0.0

    def as_dict(self) -> dict[str, Any]:
        """The ``residual`` field of the report: rms_before, rms_after, effect, effect_params."""
        return {"rms_before": _num(self.rms_before), "rms_after": _num(self.rms_after),
                "effect": self.effect,
                "effect_params": {k: _num(v) for k, v in self.effect_params.items()}}

    def details(self) -> dict[str, Any]:
        """Everything, JSON-ready (for ``--report`` extras and debugging)."""
        out = self.as_dict()
        out.update(
            significant=self.significant, threshold=self.threshold, noise=self.noise,
            before=self.before.as_dict(), after=self.after.as_dict(),
            fits=[{"effect": f.name, f.param: _num(f.value), "rms": _num(f.rms)}
                  for f in self.fits],
            open_loop=[{"effect": f.name, f.param: _num(f.value), "rms": _num(f.rms)}
                       for f in self.open_loop],
            alternatives=list(self.alternatives), design_note=self.design_note,
            gains_model=_pd(self.gains_model), gains_with_effect=_pd(self.gains_with_effect),
        )
        return out


def _num(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def _pd(p: PD | None) -> dict[str, float] | None:
    return None if p is None else {"Kc": p.Kc, "Kd": p.Kd}


@dataclass
class _Batch:
    """Candidates of one simulation round: which effect, which value."""

    effects: list[Effect | None] = field(default_factory=list)
    values: list[float] = field(default_factory=list)

    def add(self, effect: Effect | None, values) -> None:
        for v in np.atleast_1d(values):
            self.effects.append(effect)
            self.values.append(float(v))

    def knobs(self, hover: float) -> Knobs:
        k = Knobs.neutral(len(self.values), hover)
        for i, (e, v) in enumerate(zip(self.effects, self.values, strict=False)):
            if e is not None:
                e.apply(k, np.array([i]), np.array([v]))
        return k


def _compare(meas: CycleWave, u: np.ndarray, y: np.ndarray, dt: float) -> CycleErrors:
    """Errors of one simulated record against the measured cycle (inf when it does not cycle)."""
    bad = CycleErrors(np.inf, np.inf, np.inf, np.inf, np.inf)
    sim = cycle_wave(u, y, dt, max_cycles=meas.cycles)
    if sim is None or sim.amplitude <= 0:
        return bad
    n = meas.y.size
    r = rising_switches(u)
    r = r[r + max(n, sim.y.size) <= y.size][-sim.cycles:]
    if r.size == 0:
        return bad
    # Averaged over as many cycles as the measured one, from each rising switch: a cycle
    # that alternates (a biased relay's does, by a sample or two) compares like for like.
    seg = np.mean([y[s:s + n] - y[s:s + sim.y.size].mean() for s in r], axis=0)
    rms = float(np.sqrt(np.mean((seg - meas.y) ** 2)) / meas.amplitude)
    return CycleErrors(rms=rms, period=sim.period_s / meas.period_s - 1,
                       amplitude=sim.amplitude / meas.amplitude - 1, duty=sim.duty - meas.duty,
                       thd=sim.thd - meas.thd)


def _run(model: InnerModel, relay: RelayTest, batch: _Batch, meas: CycleWave, hover: float,
         band: float, cycles: float) -> list[CycleErrors]:
    P = meas.period_s
    run = simulate_effects(model, relay.beta, relay.h, batch.knobs(hover), bias=relay.bias,
                           dt=meas.dt, duration_s=cycles * P,
                           keep_s=min(cycles, meas.cycles + 3.0) * P, band=band)
    return [_compare(meas, run.u[i], run.y[i], meas.dt) for i in range(len(batch.values))]


def _redesign(model: InnerModel, effect: Effect, value: float, ctx: RelayContext
              ) -> tuple[PD, PD]:
    extra = [value] if effect.name == "extra_delay" else []
    w = frequency_grid(model.T_prop, model.T1, model.tau, extra_T=extra)
    G = inner_response(1.0, model.T_prop, model.T1, model.tau, w)[0]
    before = optimal_pd(G, w).pd
    if isinstance(effect, QuadraticDrag):
        q = 1.0 + effect.linear_damping(value, ctx) * model.T1
        G_eff = inner_response(1.0 / q, model.T_prop, model.T1 / q, model.tau, w)[0]
    else:
        G_eff = G * effect.design_factor(value, ctx, w)
    after = optimal_pd(G_eff, w, x0=(before.Kc, before.Kd)).pd
    return before.for_gain(model.K), after.for_gain(model.K)


def analyse_residual(model: InnerModel | SideModel, relay: Any, t, u, y, *,
                     kind: LoopKind = LoopKind.ATTITUDE, effects: tuple[Effect, ...] | None = None,
                     hover: float = 0.5, band: float = 0.0, grid: int = 10, rounds: int = 2,
                     sim_cycles: float = 12.0, floor: float = RMS_FLOOR,
                     min_reduction: float = MIN_REDUCTION, redesign: bool = True
                     ) -> ResidualReport:
    """Compare the model's simulated relay cycle with the measured one; name a missing effect.

    On attitude loops a measurement whose noise is coloured as by a low-pass filter
    (:func:`~mrft_gcs.residual.noise.noise_colour`) names ``sensor_lpf`` whatever the
    cycle comparison named: an identified model holds the filter's lag already, so the
    cycle alone does not show it (the cycle's choice is then an alternative).

    Parameters
    ----------
    model : InnerModel
        Linear model of the loop (attitude or altitude), SI units of the loop.
    relay : RelayTest or any object with ``beta``, ``h`` (and optionally ``bias``)
        The relay that ran (input units).
    t, u, y : arrays (m,)
        Time (s), relay output as applied (with bias) and measured output, covering
        several steady cycles (any rate; resampled to the median sample time, which is
        taken as the relay's sample time).
    kind : LoopKind
        Loop family: picks the candidate effects (:func:`candidate_effects`).
    effects : tuple of Effect, optional
        Candidates to try instead of the loop family's.
    hover : float
        Hover thrust fraction (thrust-curve effect on altitude).
    band : float
        The relay's noise band (output units), as it ran.
    grid, rounds : int
        Points of the first search grid per effect, and refinement rounds.
    floor, min_reduction : float
        Significance floor (normalised RMS) and the fraction of the residual an effect
        must remove to be named.
    redesign : bool
        Re-design the PD with the named effect.

    Returns
    -------
    ResidualReport

    Raises
    ------
    IdentificationError
        No complete relay cycle in the data, or the model does not oscillate under the relay.
    """
    rep = _analyse_waveform(model, relay, t, u, y, kind=kind, effects=effects, hover=hover,
                            band=band, grid=grid, rounds=rounds, sim_cycles=sim_cycles,
                            floor=floor, min_reduction=min_reduction, redesign=redesign)
    cands = candidate_effects(kind) if effects is None else tuple(effects)
    lpf = next((e for e in cands if e.name == "sensor_lpf"), None)
    if kind is not LoopKind.ATTITUDE or lpf is None or rep.effect == "sensor_lpf":
        return rep
    assert isinstance(model, InnerModel)
    relay = RelayTest(float(relay.beta), float(relay.h), float(getattr(relay, "bias", 0.0)))
    y = np.asarray(y, dtype=float)
    dt = rep.measured.dt
    ref = simulate_effects(model, relay.beta, relay.h, Knobs.neutral(1, hover), bias=relay.bias,
                           dt=dt, duration_s=(y.size + 3 * rep.measured.period_s / dt) * dt,
                           keep_s=y.size * dt, band=band).y[0]
    colour = noise_colour(y, dt, ref[-y.size:])
    if colour is None or not colour.coloured:
        return rep
    return _lpf_from_colour(model, relay, rep, lpf, colour, hover, band, sim_cycles,
                            min_reduction, redesign)


def _lpf_from_colour(model: InnerModel, relay: RelayTest, rep: ResidualReport, lpf: Effect,
                     colour: NoiseColour, hover: float, band: float, sim_cycles: float,
                     min_reduction: float, redesign: bool) -> ResidualReport:
    """``sensor_lpf`` named from the noise's colour: at the cycle fit's cutoff when adding
    the filter to the model explains the residual, else (the model holds its lag already)
    at the colour's rough cutoff, with the cycle and the gains as they were."""
    meas = rep.measured
    ctx = RelayContext(relay.h, relay.bias, meas.period_s, meas.amplitude, meas.dt, hover)
    alts = (rep.effect,) if rep.effect else ()
    seen = (f"its noise is coloured as by a low-pass filter (lag-1 autocorrelation "
            f"{colour.rho1:.2f} after a high-pass, white noise {colour.rho1_white:.2f})")
    fit = next((f for f in rep.fits if f.name == lpf.name), None)
    if fit is not None and rep.significant and fit.rms <= (1 - min_reduction) * rep.rms_before:
        batch = _Batch()
        batch.add(lpf, [fit.value])
        after = _run(model, relay, batch, meas, hover, band, sim_cycles)[0]
        gm = ge = None
        if redesign:
            gm, ge = _redesign(model, lpf, fit.value, ctx)
        return ResidualReport(rep.rms_before, after.rms, lpf.name, {lpf.param: fit.value},
                              rep.before, after, rep.significant, rep.threshold, rep.noise,
                              meas, rep.fits, alts, gm, ge,
                              f"{lpf.design_note(fit.value, ctx)}; {seen}", rep.open_loop)
    lo, hi = lpf.bounds(ctx)
    rough = 0.1 / meas.dt  # below it the noise tells little of where the corner lies
    value = float(np.clip(colour.cutoff_hz, max(lo, 0.2 * rough), hi))
    where = (f"cutoff about {value:.3g} Hz" if value >= rough else
             f"cutoff below about {rough:.0f} Hz, which the noise cannot place closer")
    gm = _redesign(model, lpf, value, ctx)[0] if redesign else None
    note = (f"gains unchanged: the measurement is low-pass filtered ({seen}; {where}) and "
            f"the model, which fits the cycle, holds its lag already")
    return ResidualReport(rep.rms_before, rep.rms_before, lpf.name, {lpf.param: value},
                          rep.before, rep.before, rep.significant, rep.threshold, rep.noise,
                          meas, rep.fits, alts, gm, gm, note, rep.open_loop)


def _analyse_waveform(model: InnerModel | SideModel, relay: Any, t, u, y, *, kind: LoopKind,
                      effects: tuple[Effect, ...] | None, hover: float, band: float, grid: int,
                      rounds: int, sim_cycles: float, floor: float, min_reduction: float,
                      redesign: bool) -> ResidualReport:
    """:func:`analyse_residual` on the cycle alone (no noise colour)."""
    if isinstance(model, SideModel) or kind is LoopKind.SIDE:
        raise IdentificationError("residual analysis covers the inner loops (roll, pitch, "
                                  "altitude); side loops (x, y) are not analysed")
    relay = RelayTest(float(relay.beta), float(relay.h), float(getattr(relay, "bias", 0.0)))
    dt, uu, yy = uniform(t, u, y)
    meas = cycle_wave(uu, yy, dt)
    if meas is None or meas.amplitude <= 0:
        raise IdentificationError("no complete relay cycle in the data: record a few steady "
                                  "cycles of the relay test")
    noise = noise_std(yy) / np.sqrt(meas.cycles) / meas.amplitude
    threshold = max(floor, 3.0 * noise)
    ctx = RelayContext(relay.h, relay.bias, meas.period_s, meas.amplitude, dt, hover)
    cands = candidate_effects(kind) if effects is None else tuple(effects)

    cl_errs: dict[tuple[str, float], CycleErrors] = {}  # (effect name, value) -> errors

    def closed(batch: _Batch) -> list[float]:
        errs = _run(model, relay, batch, meas, hover, band, sim_cycles)
        keys = zip(map(_name, batch.effects), batch.values, strict=False)
        cl_errs.update(zip(keys, errs, strict=False))
        return [e.rms for e in errs]

    best = _search(cands, ctx, closed, grid, rounds, head=True)
    before = cl_errs[("", 0.0)]
    if not np.isfinite(before.rms):
        raise IdentificationError("the model does not oscillate under this relay: check the "
                                  "model, beta and h")
    by_name = {e.name: e for e in cands}
    fits = sorted((EffectFit(n, by_name[n].param, by_name[n].units, v, r)
                   for n, (v, r) in best.items()), key=lambda f: f.rms)
    significant = before.rms > threshold
    top = fits[0] if fits else None
    named = (top is not None and significant and top.rms <= (1 - min_reduction) * before.rms)
    if not named or top is None:
        return ResidualReport(before.rms, before.rms, None, {}, before, before, significant,
                              threshold, noise, meas, tuple(fits))
    alts = tuple(f.name for f in fits[1:] if f.rms <= 1.15 * top.rms + 0.1 * threshold)
    name, value, after = top.name, top.value, cl_errs[(top.name, top.value)]
    driven: tuple[EffectFit, ...] = ()
    dynamic = tuple(e for e in cands if not e.static_map)
    win = input_window(uu, yy, dt) if not by_name[name].static_map else None
    if win is not None and dynamic:
        # The residual is in the dynamics: choose among the effects that change them by
        # the response to the recorded commands (see openloop.py), fit there.
        driven, alts = _input_driven(model, win, dynamic, ctx, hover, grid, rounds)
        name, value = driven[0].name, driven[0].value
        check = _Batch()
        check.add(by_name[name], [value, best[name][0]])
        # The input-driven value (the closer estimate), unless its relay cycle does not
        # explain the residual where the closed-loop fit's does (the closed-loop cycle can
        # lock to another whole number of samples).
        errs = _run(model, relay, check, meas, hover, band, sim_cycles)
        value, after = check.values[0], errs[0]
        if after.rms > (1 - min_reduction) * before.rms and errs[1].rms < after.rms:
            value, after = check.values[1], errs[1]
        if not after.rms <= (1 - min_reduction) * before.rms:
            return ResidualReport(before.rms, before.rms, None, {}, before, before, significant,
                                  threshold, noise, meas, tuple(fits), open_loop=driven)
    effect = by_name[name]
    gm = ge = None
    note = effect.design_note(value, ctx)
    if redesign:
        gm, ge = _redesign(model, effect, value, ctx)
    return ResidualReport(before.rms, after.rms, name, {effect.param: value}, before, after,
                          significant, threshold, noise, meas, tuple(fits), alts, gm, ge, note,
                          driven)


def _name(e: Effect | None) -> str:
    return "" if e is None else e.name


def _search(cands: tuple[Effect, ...], ctx: RelayContext, score, grid: int, rounds: int,
            head: bool = False) -> dict[str, tuple[float, float]]:
    """Best ``(value, score)`` of each effect: a bounded grid, then ``rounds`` finer grids
    around the best point, all effects in one batch per round.

    ``score(batch) -> list of float`` rates every candidate of a batch (lower is better);
    with ``head`` the first batch starts with the model without effects.
    """
    batch = _Batch()
    if head:
        batch.add(None, 0.0)
    for e in cands:
        batch.add(e, e.grid(ctx, grid))
    best: dict[str, tuple[float, float]] = {}

    def keep(batch: _Batch, scores: list[float]) -> None:
        for e, v, r in zip(batch.effects, batch.values, scores, strict=False):
            r = float(r) if np.isfinite(r) else np.inf
            if e is not None and (e.name not in best or r < best[e.name][1]):
                best[e.name] = (v, r)

    keep(batch, score(batch))
    for r in range(rounds):
        batch = _Batch()
        for e in cands:
            lo, hi = e.bounds(ctx)
            v0 = best[e.name][0]
            # +- one step of the previous grid, a quarter as wide each round
            if e.log_grid:
                step = _grid_step(e, ctx, grid) ** (0.25 ** r)
                vals = v0 * np.geomspace(1 / step, step, 7)
            else:
                step = _grid_step(e, ctx, grid) * 0.25 ** r
                vals = v0 + np.linspace(-step, step, 7)
            batch.add(e, np.clip(vals, lo, hi))
        keep(batch, score(batch))
    return best


def _input_driven(model: InnerModel, win: InputWindow, cands: tuple[Effect, ...],
                  ctx: RelayContext, hover: float, grid: int, rounds: int
                  ) -> tuple[tuple[EffectFit, ...], tuple[str, ...]]:
    """Input-driven fits of ``cands`` (best first) and those the data cannot tell from the best.

    Two fits are told apart when their squared residuals differ by more than
    ``LIKELIHOOD_GAP`` times the white noise's (a likelihood ratio of ``e^(gap/2)``) and
    their RMS by more than ``DRIVEN_MARGIN`` (the model's own error, which is not white:
    a clean noise-free SITL record leaves 0.0014 against the model that made it cycle).
    """
    best = _search(cands, ctx, lambda b: input_rms(model, win, b.knobs(hover)), 2 * grid,
                   rounds + 2)
    by_name = {e.name: e for e in cands}
    fits = tuple(sorted((EffectFit(n, by_name[n].param, by_name[n].units, v, r)
                         for n, (v, r) in best.items()), key=lambda f: f.rms))
    gap = LIKELIHOOD_GAP * win.noise ** 2 / win.samples
    alts = tuple(f.name for f in fits[1:] if f.rms ** 2 - fits[0].rms ** 2 < gap
                 or f.rms <= (1 + DRIVEN_MARGIN) * fits[0].rms)
    return fits, alts


def _grid_step(e: Effect, ctx: RelayContext, grid: int) -> float:
    lo, hi = e.bounds(ctx)
    if e.log_grid:
        return float((hi / lo) ** (1.0 / max(grid - 1, 1)))
    return float((hi - lo) / max(grid - 1, 1))
