"""PNG figures of a tune or a dry-run: per loop the relay test, the predicted step response
of the written gains and their open-loop Bode plot with the margins marked.

Rendering only: the curves come from :func:`mrft_gcs.plots.curves.loop_curves`; nothing
else is computed here. matplotlib is imported when a figure is drawn (Agg backend, no
display needed). A figure with nothing to show is not written: the functions return None.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mrft_gcs.errors import MissingDependency
from mrft_gcs.loops import SIDE_INNER, Loop, LoopKind
from mrft_gcs.plant import PD, InnerModel
from mrft_gcs.plots.curves import LoopCurves, loop_curves

__all__ = ["LoopPanel", "plot_tune", "plot_dry_run", "render_panels", "panels_figure",
           "tune_panels", "dry_run_panels"]

_Y_LABEL = {Loop.ROLL: "roll angle (rad)", Loop.PITCH: "pitch angle (rad)",
            Loop.ALTITUDE: "altitude (m)", Loop.X: "x, north (m)", Loop.Y: "y, east (m)"}
_U_LABEL = {Loop.ROLL: "torque command (normalised)", Loop.PITCH: "torque command (normalised)",
            Loop.ALTITUDE: "thrust command (normalised)", Loop.X: "-pitch set point (rad)",
            Loop.Y: "roll set point (rad)"}
_STEP_LABEL = {LoopKind.ATTITUDE: "angle per unit set point (rad/rad)",
               LoopKind.ALTITUDE: "height per unit set point (m/m)",
               LoopKind.SIDE: "position per unit set point (m/m)"}


@dataclass(frozen=True)
class LoopPanel:
    """What one loop's row of a figure shows (data already at hand; nothing to compute)."""

    loop: Loop
    title: str
    relay: tuple[np.ndarray, np.ndarray, np.ndarray] | None  # t (s), u, y of the relay test
    cycles_s: tuple[float, float] | None  # the identified cycles within ``relay`` (s)
    curves: LoopCurves | None
    note: str = ""
    #: the written loop's phase margin measured in the air, and the prediction it was
    #: checked against (deg); None where no in-air check measured it
    measured_pm: tuple[float, float] | None = None

    @property
    def empty(self) -> bool:
        return self.relay is None and self.curves is None


def _pyplot() -> Any:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as err:  # pragma: no cover - matplotlib is a core dependency
        raise MissingDependency("--plot needs matplotlib: pip install matplotlib") from err
    return plt


def _inner_of(loops: dict, loop: Loop) -> tuple[InnerModel, PD] | None:
    """The attitude loop behind x or y: its model and the gains its side design assumed."""
    att = loops.get(SIDE_INNER.get(loop)) if loop in SIDE_INNER else None
    ident = getattr(att, "identification", None) if att is not None else None
    if ident is None or not isinstance(ident.model, InnerModel):
        return None
    return ident.model, ident.gains


def _curves(loop: Loop, lr: Any, loops: dict) -> LoopCurves | None:
    ident, gains = lr.identification, lr.gains
    if ident is None or gains is None:
        return None
    return loop_curves(loop, ident.model, gains, inner=_inner_of(loops, loop),
                       less_delay_s=getattr(lr, "gcs_delay_s", math.nan))


def _gains_text(g: PD | None) -> str:
    return f"; written Kc {g.Kc:.3g}, Kd {g.Kd:.3g}" if g is not None else ""


def tune_panels(result: Any) -> list[LoopPanel]:
    """Panels of a :class:`~mrft_gcs.flight.api.TuneResult`, one per loop that ran."""
    panels = []
    for lp in Loop:
        lr = result.loops.get(lp)
        if lr is None:
            continue
        relay = None
        if lr.cycles is not None:
            t, u, y = lr.cycles
            relay = (t - t[0], u, y)
        title = (f"{lp.value}: {lr.state}; relay beta {lr.beta:.3g}, h {lr.h:.3g}, "
                 f"period {lr.period_s:.3f} s" + _gains_text(lr.gains))
        ver = getattr(lr, "verification", None)
        measured = None
        if ver is not None and math.isfinite(ver.measured_pm_deg):
            measured = (ver.measured_pm_deg, ver.predicted_pm_deg)
        panels.append(LoopPanel(lp, title, relay, None, _curves(lp, lr, result.loops),
                                lr.note or "", measured))
    return panels


def dry_run_panels(res: Any) -> list[LoopPanel]:
    """Panels of a :class:`~mrft_gcs.dryrun.DryRunResult`, one per relay test found."""
    by_loop = {r.loop: r for r in res.loops}
    panels = []
    for r in res.loops:
        s = r.segment
        t0 = float(s.t[0])
        span = None
        if r.cycles is not None and len(r.cycles[0]):
            span = (float(r.cycles[0][0]) - t0, float(r.cycles[0][-1]) - t0)
        title = (f"{r.loop.value}: relay from {s.source}, beta {s.beta:+.2f}, h {s.h:.3g}"
                 + _gains_text(r.gains))
        if r.residual is not None:
            title += f"; residual {r.residual.rms_before:.3f}"
        panels.append(LoopPanel(r.loop, title, (s.t - t0, s.u, s.y), span,
                                _curves(r.loop, r, by_loop),
                                "" if r.identification else "not identified"))
    return panels


def _draw_relay(ax: Any, p: LoopPanel) -> None:
    if p.relay is None:
        ax.text(0.5, 0.5, f"no relay cycles\n{p.note[:80]}", ha="center", va="center",
                transform=ax.transAxes, fontsize=8)
        ax.set_axis_off()
        return
    t, u, y = p.relay
    ax.step(t, u, where="post", color="tab:blue", lw=0.9)
    ax.set_ylabel(f"relay u: {_U_LABEL[p.loop]}", color="tab:blue", fontsize=8)
    ax.set_xlabel("time (s)")
    ax2 = ax.twinx()
    ax2.plot(t, y, color="tab:red", lw=0.9)
    ax2.set_ylabel(f"measured {_Y_LABEL[p.loop]}", color="tab:red", fontsize=8)
    if p.cycles_s is not None:
        ax.axvspan(*p.cycles_s, color="0.9", zorder=0, label="identified cycles")
        ax.legend(loc="upper left", fontsize=7)
    ax.set_title("relay test", fontsize=9)


def _draw_step(ax: Any, p: LoopPanel) -> None:
    c = p.curves
    if c is None:
        ax.text(0.5, 0.5, "no identified model and written gains:\nno prediction",
                ha="center", va="center", transform=ax.transAxes, fontsize=8)
        ax.set_axis_off()
        return
    ax.plot(c.t_s, c.y, color="tab:green", lw=1.2, label="predicted")
    ax.axhline(1.0, color="0.5", lw=0.8, ls="--", label="set point")
    lo, hi = float(np.min(c.y)), float(np.max(c.y))
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi > 3 or lo < -2:
        ax.set_ylim(-0.5, 2.0)  # an unstable loop: keep the scale readable
    ax.set_xlabel("time (s)")
    ax.set_ylabel(_STEP_LABEL[p.loop.kind], fontsize=8)
    ax.set_title("predicted unit step, written gains on the identified model", fontsize=9)
    ax.legend(loc="lower right", fontsize=7)
    ax.grid(alpha=0.3)


def _draw_bode(ax_m: Any, ax_p: Any, p: LoopPanel) -> None:
    c = p.curves
    if c is None:
        for ax in (ax_m, ax_p):
            ax.set_axis_off()
        return
    m = c.margins
    ax_m.semilogx(c.w, c.magnitude_db, color="tab:purple", lw=1.1)
    ax_m.axhline(0.0, color="0.5", lw=0.8)
    ax_m.set_ylabel("|L| (dB)")
    ph = c.phase_deg
    ax_p.semilogx(c.w, ph, color="tab:purple", lw=1.1)
    ax_p.axhline(-180.0, color="0.5", lw=0.8)
    ax_p.set_ylabel("phase of L (deg)")
    ax_p.set_xlabel("frequency (rad/s)")
    if math.isfinite(m.wc):
        ph_c = float(np.interp(np.log(m.wc), np.log(c.w), ph))
        ax_p.plot([m.wc, m.wc], [-180.0, ph_c], color="tab:orange", lw=2.5, marker="o", ms=3,
                  label=f"phase margin {m.pm_deg:.1f} deg at {m.wc:.3g} rad/s")
        ax_m.axvline(m.wc, color="tab:orange", lw=0.8, ls=":")
        if p.measured_pm is not None:  # the in-air check, at the predicted crossover
            got, want = p.measured_pm
            ax_p.plot([m.wc], [-180.0 + got], color="tab:red", marker="D", ms=5, ls="none",
                      label=f"measured in the air: PM {got:.1f} deg (predicted {want:.1f})")
    if math.isfinite(c.w_pc) and math.isfinite(m.gm):
        mag_pc = float(np.interp(np.log(c.w_pc), np.log(c.w), c.magnitude_db))
        ax_m.plot([c.w_pc, c.w_pc], [mag_pc, 0.0], color="tab:brown", lw=2.5, marker="o", ms=3,
                  label=f"gain margin {20 * np.log10(m.gm):.1f} dB at {c.w_pc:.3g} rad/s")
        ax_p.axvline(c.w_pc, color="tab:brown", lw=0.8, ls=":")
    # show two decades below the crossover to one and a half above: where the margins are
    lo_w, hi_w = (m.wc / 100.0, m.wc * 30.0) if math.isfinite(m.wc) else (c.w[0], c.w[-1])
    seen = (c.w >= lo_w) & (c.w <= hi_w)
    ax_m.set_xlim(lo_w, hi_w)
    mag, ph_seen = c.magnitude_db[seen], ph[seen]
    if mag.size:
        ax_m.set_ylim(max(float(mag.min()), -60.0) - 5.0, min(float(mag.max()), 80.0) + 5.0)
        ax_p.set_ylim(max(float(ph_seen.min()), -450.0) - 10.0, float(ph_seen.max()) + 10.0)
    for ax in (ax_m, ax_p):
        ax.grid(alpha=0.3, which="both")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(loc="lower left", fontsize=7)
    verdict = "stable" if m.stable else "UNSTABLE"
    ax_m.set_title(f"open loop L = (Kc + Kd s) G of the written gains ({verdict})", fontsize=9)


def panels_figure(panels: list[LoopPanel], title: str) -> Any:
    """The matplotlib figure: one row per panel (relay test, predicted step, Bode magnitude
    over phase); None when no panel has anything to show. Close it when done."""
    panels = [p for p in panels if not p.empty]
    if not panels:
        return None
    plt = _pyplot()
    n = len(panels)
    fig = plt.figure(figsize=(16, 4.2 * n + 0.5), layout="constrained")
    rows = fig.subfigures(n, 1, squeeze=False)[:, 0]
    for sub, p in zip(rows, panels, strict=True):
        grid = sub.add_gridspec(2, 3, width_ratios=[1.3, 1.0, 1.1])
        ax_m = sub.add_subplot(grid[0, 2])
        _draw_relay(sub.add_subplot(grid[:, 0]), p)
        _draw_step(sub.add_subplot(grid[:, 1]), p)
        _draw_bode(ax_m, sub.add_subplot(grid[1, 2], sharex=ax_m), p)
        sub.suptitle(p.title, fontsize=10, fontweight="bold", x=0.01, ha="left")
    fig.suptitle(title, fontsize=11)
    return fig


def render_panels(panels: list[LoopPanel], path: str | os.PathLike[str],
                  title: str) -> Path | None:
    """Write :func:`panels_figure` as a PNG; None (nothing written) when it has nothing."""
    fig = panels_figure(panels, title)
    if fig is None:
        return None
    out = Path(path)
    fig.savefig(out, dpi=100)
    _pyplot().close(fig)
    return out


def plot_tune(result: Any, path: str | os.PathLike[str]) -> Path | None:
    """The figure of a tune (``tune --plot``); None (nothing written) if no loop ran."""
    return render_panels(tune_panels(result), path,
                         f"tune {result.status} ({result.actuation} path), {result.connection}")


def plot_dry_run(res: Any, path: str | os.PathLike[str]) -> Path | None:
    """The figure of a dry-run (``dry-run --plot``); None (nothing written) without a relay
    test in the log."""
    return render_panels(dry_run_panels(res), path, f"dry-run of {res.source}")
