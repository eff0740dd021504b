"""Roll and pitch designed on models with their fast lags pooled (onboard.pooled_attitude)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from mrft_gcs.flight.onboard import GcsDelay, pooled_attitude, robust_onboard_gains
from mrft_gcs.flight.structure import relay_frequency
from mrft_gcs.identify import Identification
from mrft_gcs.loops import LoopKind
from mrft_gcs.pd_design import frequency_grid, ise, margins, optimal_pd
from mrft_gcs.plant import PD, InnerModel, SideModel, inner_response

#: an onboard attitude model (K, T_prop, T1, tau) and the GCS delay its relay tests carried (s)
TRUE = InnerModel(K=170.0, T_prop=0.0215, T1=0.4, tau=0.0037)
D_GCS = 0.025
BETA = -0.7


def _at(m: InnerModel, w: float) -> complex:
    return complex(inner_response(m.K, m.T_prop, m.T1, m.tau, [w])[0, 0])


def _through(m: InnerModel, w: float, T_prop: float, tau: float) -> InnerModel:
    """The model with ``T_prop`` and ``tau`` whose response at ``w`` is ``m``'s: what a
    relay cycle at ``w`` identifies when it splits the lag differently."""
    lag = math.atan(w * m.T1) + w * (m.tau - tau) + math.atan(w * m.T_prop) - math.atan(
        w * T_prop)
    t1 = math.tan(lag) / w
    k = abs(_at(m, w)) * w * math.hypot(1, w * T_prop) * math.hypot(1, w * t1)
    return InnerModel(k, T_prop, t1, tau)


def _ident(m: InnerModel, period_s: float) -> Identification:
    w = frequency_grid(m.T_prop, m.T1, m.tau)
    pd = optimal_pd(inner_response(m.K, m.T_prop, m.T1, m.tau, w)[0], w).pd
    return Identification(LoopKind.ATTITUDE, m, 0, 1.0, BETA, 0.06, period_s, 0.1, pd)


def _gcs_side() -> tuple[InnerModel, float]:
    gcs = dataclasses.replace(TRUE, tau=TRUE.tau + D_GCS)
    return gcs, relay_frequency(gcs, BETA)


def test_each_axis_keeps_its_relay_point_and_gains():
    gcs, w0 = _gcs_side()
    r = _ident(_through(gcs, w0, gcs.T_prop + 0.005, gcs.tau - 0.003), 2 * math.pi / w0)
    p = _ident(_through(gcs, w0, gcs.T_prop - 0.004, gcs.tau + 0.001), 2 * math.pi / w0)
    pr, pp = pooled_attitude(r, p)
    for before, after in ((r, pr), (p, pp)):
        assert after.gains == before.gains  # the PD flown GCS-side stays the identified one
        assert _at(after.model, w0) == pytest.approx(_at(before.model, w0), rel=1e-9)
    assert pr.model.T_prop == pytest.approx(0.5 * (r.model.T_prop + p.model.T_prop))
    assert pp.model.tau == pytest.approx(0.5 * (r.model.tau + p.model.tau))
    assert pr.model.T_prop == pp.model.T_prop and pr.model.tau == pp.model.tau


def test_opposite_splits_average_to_the_truth():
    # roll put delay into its propeller lag, pitch the other way: each fits the cycle's point
    gcs, w0 = _gcs_side()
    r = _ident(_through(gcs, w0, gcs.T_prop + 0.005, gcs.tau - 0.002), 2 * math.pi / w0)
    p = _ident(_through(gcs, w0, gcs.T_prop - 0.005, gcs.tau + 0.002), 2 * math.pi / w0)
    for m in (i.model for i in pooled_attitude(r, p)):
        assert m.T_prop == pytest.approx(gcs.T_prop) and m.tau == pytest.approx(gcs.tau)
        assert m.T1 == pytest.approx(gcs.T1, rel=1e-6) and m.K == pytest.approx(gcs.K, rel=1e-6)


def _score(g: PD, m: InnerModel) -> tuple[float, float]:
    """J (%) and PM (deg) of ``g`` on the loop ``m``."""
    w = frequency_grid(m.T_prop, m.T1, m.tau)
    G = inner_response(m.K, m.T_prop, m.T1, m.tau, w)[0]
    best = optimal_pd(G, w)
    mg = margins((g.Kc + 1j * w * g.Kd) * G, w)
    return 100.0 * (ise(g.Kc, g.Kd, G, w) - best.ise) / best.ise, float(mg.pm_deg)


def test_written_gains_of_a_mis_split_axis_come_to_the_true_optimum():
    # the roll and pitch relay identifications of a 144 g PX4-like vehicle behind a 10.5 ms
    # link (a random-population tune), its true onboard models (the 500 Hz loop's hold as
    # 1 ms of delay) and the GCS delay measured (ages 2.5 ms, round trip 20.9 ms)
    r = Identification(LoopKind.ATTITUDE, InnerModel(177.97, 0.02675, 0.4195, 0.02775), 0,
                       0.6, BETA, 0.061, 0.3867, 0.109, PD(0.3373, 0.04324))
    p = Identification(LoopKind.ATTITUDE, InnerModel(457.8, 0.02012, 1.246, 0.02713), 0,
                       0.46, BETA, 0.071, 0.3947, 0.121, PD(0.3938, 0.05132))
    true_r = InnerModel(635.7, 0.02148, 1.564, 0.0037)
    true_p = InnerModel(585.1, 0.02148, 1.584, 0.0037)
    g = GcsDelay(0.02346, 0.02146, 0.02746, 0.00254, True, "", 0.02092)
    j_r, pm_r = _score(robust_onboard_gains(r, g).gains, true_r)
    assert j_r > 8.0 and pm_r > 23.0  # roll took 5 ms of delay for lag: written cautious
    pr, pp = pooled_attitude(r, p)
    for i, t in ((pr, true_r), (pp, true_p)):
        rt = robust_onboard_gains(i, g)
        j, pm = _score(rt.gains, t)
        assert j < 6.0 and 18.0 < pm < 23.0
        assert rt.pm_deg >= 15.0 - 1e-6  # the margin kept at the least plausible delay


def test_nothing_pooled_without_two_attitude_models():
    gcs, w0 = _gcs_side()
    r = _ident(gcs, 2 * math.pi / w0)
    side = dataclasses.replace(r, kind=LoopKind.SIDE, model=SideModel(3.0, 0.3, 0.01))
    alt = dataclasses.replace(r, kind=LoopKind.ALTITUDE)
    for a, b in ((r, side), (alt, r), (r, dataclasses.replace(r, period_s=math.nan))):
        assert pooled_attitude(a, b) == (a, b)


def test_a_phase_no_slow_pole_can_give_leaves_both_as_identified():
    # pitch's fast lags far larger than roll's: roll's phase at its cycle cannot be met
    gcs, w0 = _gcs_side()
    r = _ident(gcs, 2 * math.pi / w0)
    p = _ident(dataclasses.replace(gcs, T_prop=0.2, tau=0.1), 2 * math.pi / w0)
    assert pooled_attitude(r, p) == (r, p)


def test_same_split_on_both_axes_is_left_as_it_is():
    gcs, w0 = _gcs_side()
    r = _ident(gcs, 2 * math.pi / w0)
    pr, pp = pooled_attitude(r, r)
    for m in (pr.model, pp.model):
        assert np.allclose([m.K, m.T_prop, m.T1, m.tau], [gcs.K, gcs.T_prop, gcs.T1, gcs.tau],
                           rtol=1e-9)


def test_switched_off_nothing_is_pooled(monkeypatch):
    from mrft_gcs.flight import onboard

    gcs, w0 = _gcs_side()
    r = _ident(_through(gcs, w0, gcs.T_prop + 0.005, gcs.tau - 0.002), 2 * math.pi / w0)
    p = _ident(_through(gcs, w0, gcs.T_prop - 0.005, gcs.tau + 0.002), 2 * math.pi / w0)
    assert pooled_attitude(r, p) != (r, p)
    monkeypatch.setattr(onboard, "POOL_ATTITUDE_LAGS", False)
    assert pooled_attitude(r, p) == (r, p)
