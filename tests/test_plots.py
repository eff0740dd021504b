"""Plots a tuner looks at: the curves (step response, open loop and margins of the written
gains) and the figures of a tune and a dry-run (labelled axes; nothing written when empty)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from mrft_gcs.loops import Loop
from mrft_gcs.pd_design import PM_MIN_DEG, frequency_grid, optimal_pd
from mrft_gcs.plant import (
    PD,
    InnerModel,
    SideModel,
    closed_inner_response,
    inner_response,
    side_response,
)
from mrft_gcs.plots import loop_curves

ROLL = InnerModel(K=32.0, T_prop=0.025, T1=0.2, tau=0.019)
X = SideModel(K=9.5, T2=0.3, tau=0.05)


def _optimal_inner(m: InnerModel) -> PD:
    w = frequency_grid(m.T_prop, m.T1, m.tau)
    return optimal_pd(inner_response(1.0, m.T_prop, m.T1, m.tau, w)[0], w).pd.for_gain(m.K)


def test_inner_curves_of_the_optimal_pd_show_its_design_margin():
    """The optimal PD is designed to a 20 deg phase margin: the curves show it, and the
    simulated step (time domain) settles on the set point."""
    c = loop_curves(Loop.ROLL, ROLL, _optimal_inner(ROLL))
    assert c.margins.stable
    assert c.margins.pm_deg == pytest.approx(PM_MIN_DEG, abs=0.5)
    assert 1.0 < c.margins.gm < 10.0 and c.w_pc > c.margins.wc
    assert abs(c.y[-len(c.y) // 10:].mean() - 1.0) < 0.02
    assert c.y.max() > 1.05  # 20 deg of phase margin overshoots
    # the -180 deg crossing is where the gain margin is read
    assert 20 * np.log10(c.margins.gm) == pytest.approx(
        -np.interp(np.log(c.w_pc), np.log(c.w), c.magnitude_db), abs=0.2)


def test_less_delay_gives_more_phase_margin():
    g = _optimal_inner(ROLL)
    base = loop_curves(Loop.ROLL, ROLL, g).margins
    onboard = loop_curves(Loop.ROLL, ROLL, g, less_delay_s=0.004).margins
    assert onboard.pm_deg > base.pm_deg + 2.0


def test_side_curves_need_the_attitude_loop_and_match_its_design():
    g_att = _optimal_inner(ROLL)
    assert loop_curves(Loop.X, X, PD(0.5, 0.5)) is None  # no attitude loop given
    w = frequency_grid(ROLL.T_prop, ROLL.T1, ROLL.tau, extra_T=(X.T2, X.tau))
    G = closed_inner_response(g_att.Kc, g_att.Kd, inner_response(
        ROLL.K, ROLL.T_prop, ROLL.T1, ROLL.tau, w), w)[0] * side_response(X.K, X.T2, X.tau, w)[0]
    side = optimal_pd(G, w).pd
    c = loop_curves(Loop.X, X, side, inner=(ROLL, g_att))
    assert c.margins.stable and c.margins.pm_deg == pytest.approx(PM_MIN_DEG, abs=1.0)
    assert abs(c.y[-len(c.y) // 10:].mean() - 1.0) < 0.03
    bad = loop_curves(Loop.X, X, PD(side.Kc * 8, side.Kd * 0.2), inner=(ROLL, g_att))
    assert not bad.margins.stable


def test_non_finite_gains_have_no_curves():
    assert loop_curves(Loop.ROLL, ROLL, PD(math.nan, 0.1)) is None


@pytest.fixture(scope="module")
def dry(tmp_path_factory):
    """A dry-run of a roll relay test on the simulated vehicle (real tlog, real pipeline)."""
    from mrft_gcs.dryrun import dry_run
    from mrft_gcs.identify import relay_settings
    from mrft_gcs.loops import LoopKind
    from mrft_gcs.residual.synth import sitl_relay_record, write_relay_tlog

    rec = sitl_relay_record("roll", seed=4, beta=relay_settings(LoopKind.ATTITUDE).beta, h=0.08,
                            duration_s=6.0)
    path = tmp_path_factory.mktemp("plots") / "relay.tlog"
    write_relay_tlog(path, "roll", rec.t, rec.u, rec.y)
    res = dry_run(path)
    assert res.loops and res.loops[0].identification is not None
    return res


def _tune_result(dry, with_roll: bool = True):
    """A TuneResult holding what the dry-run identified (roll), altitude left alone."""
    from mrft_gcs.flight.api import LoopResult, TuneResult

    r = dry.loops[0]
    loops = {Loop.ALTITUDE: LoopResult(Loop.ALTITUDE, "left alone", math.nan, math.nan,
                                       math.nan, math.nan, math.nan, None, None, math.nan,
                                       "not requested", None)}
    if with_roll:
        ident = r.identification
        loops[Loop.ROLL] = LoopResult(Loop.ROLL, "tuned", ident.beta, ident.h, 0.0,
                                      ident.period_s, ident.amplitude, ident, r.gains, 3.0, "",
                                      r.cycles, gcs_delay_s=r.gcs_delay_s)
    return TuneResult("udp:127.0.0.1:14540", "px4", "sitl", "torque", "2025-01-01T00:00:00",
                      10.0, loops, (), None, "ok")


def _labels(fig) -> str:
    parts = []
    for ax in fig.get_axes():
        parts += [ax.get_title(), ax.get_xlabel(), ax.get_ylabel()]
        if ax.get_legend():
            parts += [t.get_text() for t in ax.get_legend().get_texts()]
    return " | ".join(parts)


def test_tune_figure_has_relay_step_and_bode_per_loop(dry, tmp_path):
    import matplotlib.pyplot as plt

    from mrft_gcs.plots.figures import panels_figure, plot_tune, tune_panels

    result = _tune_result(dry)
    panels = tune_panels(result)
    assert [p.loop for p in panels] == [Loop.ROLL, Loop.ALTITUDE]
    assert panels[1].empty  # left alone: no row in the figure
    fig = panels_figure(panels, "tune")
    try:
        text = _labels(fig)
        assert len(fig.subfigs) == 1
        assert "written Kc" in fig.subfigs[0]._suptitle.get_text()
    finally:
        plt.close(fig)
    for want in ("relay u: torque command (normalised)", "measured roll angle (rad)",
                 "time (s)", "predicted unit step", "angle per unit set point (rad/rad)",
                 "|L| (dB)", "phase of L (deg)", "frequency (rad/s)", "phase margin",
                 "gain margin"):
        assert want in text, (want, text)
    png = plot_tune(result, tmp_path / "tune.png")
    assert png is not None and png.read_bytes()[:4] == b"\x89PNG"


def test_tune_figure_marks_the_margin_measured_in_the_air(dry):
    import matplotlib.pyplot as plt

    from mrft_gcs.flight.api import Verification
    from mrft_gcs.plots.figures import panels_figure, tune_panels

    result = _tune_result(dry)
    roll = result.loops[Loop.ROLL]
    ver = Verification("square wave", True, 20.0, 18.4, "none", "")
    result = dataclasses.replace(result, loops={
        **result.loops, Loop.ROLL: dataclasses.replace(roll, verification=ver)})
    panels = tune_panels(result)
    assert panels[0].measured_pm == (18.4, 20.0)
    fig = panels_figure(panels, "tune")
    try:
        assert "measured in the air: PM 18.4 deg (predicted 20.0)" in _labels(fig)
    finally:
        plt.close(fig)
    assert tune_panels(_tune_result(dry))[0].measured_pm is None  # no check ran


def test_nothing_to_show_writes_nothing(dry, tmp_path):
    from mrft_gcs.dryrun import DryRunResult
    from mrft_gcs.plots import plot_dry_run, plot_tune

    out = tmp_path / "empty.png"
    assert plot_tune(_tune_result(dry, with_roll=False), out) is None
    empty = DryRunResult(dry.source, dry.summary, ())
    assert plot_dry_run(empty, out) is None
    assert not out.exists()
