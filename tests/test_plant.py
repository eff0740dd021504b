"""Plant models: transfer functions, modal realisation, time scaling."""

from __future__ import annotations

import numpy as np
import pytest

from mrft_gcs.plant import (
    InnerModel,
    closed_inner_response,
    inner_response,
    modal_form,
    side_response,
)


def test_inner_response_matches_formula():
    w = np.array([0.3, 2.0, 40.0])
    K, Tp, T1, tau = 2.0, 0.05, 0.5, 0.01
    s = 1j * w
    expected = K * np.exp(-tau * s) / (s * (Tp * s + 1) * (T1 * s + 1))
    np.testing.assert_allclose(inner_response(K, Tp, T1, tau, w)[0], expected, rtol=1e-12)


def test_vectorised_shapes():
    g = inner_response([1, 2], [0.05, 0.1], [0.5, 1.0], [0.01, 0.02], np.logspace(-1, 2, 7))
    assert g.shape == (2, 7)
    assert side_response(1.0, [0.5, 1, 2], 0.05, [1.0, 2.0]).shape == (3, 2)


@pytest.mark.parametrize("Tp,T1", [(0.05, 0.5), (0.3, 0.2), (0.2, 0.2), (0.1, 0.1 * (1 + 1e-6))])
def test_modal_form_reproduces_transfer_function(Tp, T1):
    m = modal_form(1.7, Tp, T1)
    w = np.logspace(-2, 3, 50)
    s = 1j * w
    modal = 1.7 * np.sum(m.r[0][None, :] / (s[:, None] - m.lam[0][None, :]), axis=1)
    exact = inner_response(1.7, Tp, T1, 0.0, w)[0]
    # Coincident poles are pulled apart by 1e-4 relative: a negligible change.
    np.testing.assert_allclose(modal, exact, rtol=2e-4)
    assert abs(m.r[0].sum()) < 1e-6 * np.abs(m.r[0]).max()  # no feed-through to the rate


def test_time_scaling_is_exact():
    g = InnerModel(2.0, 0.05, 0.5, 0.01)
    c = 3.0
    gs = g.scaled(c)
    w = np.logspace(-1, 2, 20)
    # c * G(c s) with gain K/c ... i.e. G_scaled(jw) = G(j c w)
    np.testing.assert_allclose(
        inner_response(gs.K, gs.T_prop, gs.T1, gs.tau, w)[0],
        inner_response(g.K, g.T_prop, g.T1, g.tau, c * w)[0],
        rtol=1e-12,
    )


def test_closed_inner_loop_unity_dc_gain():
    w = np.array([1e-5])
    G = inner_response(1.0, 0.05, 0.5, 0.01, w)
    T = closed_inner_response(5.0, 1.0, G, w)
    assert abs(T[0, 0] - 1) < 1e-3
