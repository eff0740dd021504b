"""Discretisation, distinguishing phase, zeta and a tiny end-to-end design run."""

from __future__ import annotations

import numpy as np
import pytest

from mrft_gcs.design.discretize import (
    Discretisation,
    _grid_for,
    discretize_inner,
    reachable_scales,
    shape_grid,
)
from mrft_gcs.design.phase import distinguishing_phase, hb_period, unit_cycles, zeta_table
from mrft_gcs.domains import D_ATT, Domain
from mrft_gcs.loops import LoopKind

# A small box of the attitude domain: few shapes, seconds to discretise.
TINY = Domain("attitude", ("T_prop", "T1", "tau"), (0.03, 0.3, 0.004), (0.08, 0.6, 0.012))


@pytest.fixture(scope="module")
def tiny() -> Discretisation:
    return discretize_inner(TINY, J_target=10.0, grid_n=5)


def test_reachable_scales_keep_processes_in_the_box():
    cand = shape_grid(D_ATT, 10)
    lo, hi = reachable_scales(D_ATT, cand[:, 0], cand[:, 1])
    mid = np.sqrt(lo * np.maximum(hi, lo))
    p = np.column_stack([np.exp(cand[:, 0]) * mid, mid, np.exp(cand[:, 1]) * mid])
    assert np.all(D_ATT.contains(p, rtol=1e-6))


def test_tiny_discretisation_meets_its_targets(tiny):
    assert 1 <= len(tiny.shapes) < tiny.candidates
    # every representative process lies in the domain
    assert np.all(TINY.contains(tiny.reps, rtol=1e-6))
    # every candidate is within the net radius of its owner (greedy cover)
    own = tiny.cand_J[np.arange(tiny.candidates), tiny.cand_owner]
    assert np.all(own <= tiny.cover + 1e-9)
    # adjacent representatives are about J* apart, not far beyond it
    fin = tiny.adjacent_J[np.isfinite(tiny.adjacent_J)]
    assert fin.size and np.median(fin) <= tiny.J_target + tiny.tolerance


def test_owner_of_the_representatives_is_themselves(tiny):
    for s, (a, b) in enumerate(tiny.shapes):
        p = np.array([[np.exp(a) * 0.4, 0.4, np.exp(b) * 0.4]])
        assert tiny.owner_of(p)[0] == s


def test_json_round_trip(tiny):
    back = Discretisation.from_json(tiny.to_json())
    np.testing.assert_allclose(back.reps, tiny.reps)
    assert back.candidates == tiny.candidates


def test_unit_cycles_match_harmonic_balance_roughly(tiny):
    params = np.column_stack([np.exp(tiny.shapes[:, 0]), np.ones(len(tiny.shapes)),
                              np.exp(tiny.shapes[:, 1])])
    cyc = unit_cycles(params, [-0.5, 0.0])
    for k, beta in enumerate((-0.5, 0.0)):
        assert np.allclose(cyc.period[:, k], hb_period(params, beta), rtol=0.08)
    # zeta near the describing function's 4/pi but not equal to it
    z = zeta_table(params, cyc.period[:, 1], cyc.amplitude[:, 1])
    assert np.all(np.abs(z / (4 / np.pi) - 1) < 0.15)
    assert not np.allclose(z, 4 / np.pi, rtol=1e-3)


def test_distinguishing_phase_is_interior_and_beats_the_relay(tiny):
    params = np.column_stack([np.exp(tiny.shapes[:, 0]), np.ones(len(tiny.shapes)),
                              np.exp(tiny.shapes[:, 1])])
    betas = np.array([-0.8, -0.65, -0.5, 0.0, 0.3])
    res = distinguishing_phase(params, tiny.shape_pd, tiny.shape_ise, unit_cycles(params, betas),
                               _grid_for(tiny.shapes))
    assert res.beta < 0  # a phase lead, as for every PD with a 20 deg margin
    assert res.worst_J.min() < res.worst_J[betas == 0.0][0]


def test_tiny_end_to_end_design_and_identify(tmp_path, monkeypatch):
    """discretize -> phase -> zeta -> dataset -> (train -> ONNX -> identify) in a tiny box."""
    from mrft_gcs.design import pipeline as dz

    monkeypatch.setattr(dz, "domain_for", lambda kind: TINY)
    monkeypatch.setattr(dz, "BETA_GRID", np.array([-0.7, -0.6, -0.5]))
    kind = LoopKind.ATTITUDE
    dz.step_discretize(kind, tmp_path, grid_n=5)
    dz.step_phase(kind, tmp_path)
    z = dz.step_zeta(kind, tmp_path)
    train, val = dz.step_dataset(kind, tmp_path, n_train=200, n_val=60, seed=3)
    assert len(train) > 170 and len(val) > 50
    assert np.all(np.abs(train.bias) <= 0.3) and train.x.shape[1] == 66
    manifest = (tmp_path / "manifest.json").read_text()
    assert "discretize" in manifest and "dataset" in manifest
    pytest.importorskip("torch", reason="training needs the design extra (torch)")
    pytest.importorskip("onnx", reason="export needs the design extra (onnx)")
    info = dz.step_train(kind, tmp_path, epochs=15, search=[(2, 64, "relu", "ce")])
    assert (tmp_path / "attitude" / "classifier.onnx").exists()
    from mrft_gcs.identify import runtime

    b = runtime.load_bundle(kind, tmp_path)
    assert b.beta == z["beta"]
    logits = b.logits(val.x)
    assert logits.shape == (len(val), len(b.shape_params))
    assert info["val_accuracy"] >= 0.0


def test_cascade_structure_closes_the_attitude_loop_first():
    # Algorithm 2 on the side chain: a relay on attitude (rate dynamics open) is practical;
    # a relay on velocity with the attitude open is not, so attitude and side motion
    # become the two loops of the cascade (paper: "met only when i = 2").
    from mrft_gcs.design.phase import cascade_structure
    from mrft_gcs.domains import D_SIDE

    steps = cascade_structure(D_ATT.vertices(), D_SIDE.vertices(), beta=-0.5)
    assert [s.split for s in steps] == [False, True]
    assert steps[0].period_s < 4.0
