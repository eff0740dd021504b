"""Rate D on ArduCopter's rate path: the roll/pitch design on the one cascade model
(:func:`mrft_gcs.flight.structure.cascade_design` on
:func:`mrft_gcs.flight.onboard.cascade_controller`).

Each figure the design claims is recomputed here from the model directly (the process with
its delay, the controller's paths), not read from the design's own output.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from mrft_gcs.flight.onboard import (
    PM_ROBUST_DEG,
    _cascade_poles_stable,
    cascade_controller,
    cascade_gains,
    cascade_process,
    rate_loop_gains,
)
from mrft_gcs.flight.scoring import general_ise
from mrft_gcs.flight.structure import (
    D_ANGLE_P_MOVE_MAX,
    D_GAIN_MOVE_MAX,
    D_GM_MIN,
    RATE_D_OVER_P_S,
    OnboardStructure,
    cascade_design,
    structure_controller,
    structured_pd,
)
from mrft_gcs.pd_design import PM_MIN_DEG, frequency_grid, margins, optimal_pd
from mrft_gcs.plant import PD, InnerModel, inner_response

#: ArduCopter SITL's quad as the rate path identified it, and vehicles around it
MODELS = [InnerModel(K=34.0, T_prop=0.0085, T1=0.095, tau=0.006),
          InnerModel(K=120.0, T_prop=0.03, T1=0.5, tau=0.02),
          InnerModel(K=34.0, T_prop=0.03, T1=0.095, tau=0.04),
          InnerModel(K=60.0, T_prop=0.015, T1=0.3, tau=0.012)]


def _identified(m: InnerModel) -> PD:
    w = frequency_grid(m.T_prop, m.T1, m.tau)
    return optimal_pd(inner_response(m.K, m.T_prop, m.T1, m.tau, w)[0], w).pd


def _pm_gm(m: InnerModel, g: PD, st: OnboardStructure, wi: float = 0.0) -> tuple[float, float]:
    w = frequency_grid(m.T_prop, m.T1, m.tau, extra_T=(1.0 / wi,) if wi > 0 else ())
    Cy = cascade_controller(g, w, st.target_hz, st.error_hz, wi, st.d_over_p_s, st.d_hz)[1]
    mm = margins(Cy * cascade_process(m, w), w)
    return float(mm.pm_deg), float(mm.gm)


@pytest.mark.parametrize("m", MODELS)
def test_rate_d_written_only_with_a_lower_ise_bounded_and_at_the_margins(m):
    st = OnboardStructure(20.0, "", RATE_D_OVER_P_S, 20.0)
    g = _identified(m)
    c = cascade_design(m, g, st, decade=10.0)
    base = cascade_gains(m, g, 20.0, PM_ROBUST_DEG)
    w = frequency_grid(m.T_prop, m.T1, m.tau)
    G = cascade_process(m, w)
    two = structured_pd(G, w, OnboardStructure(20.0), pm_min_deg=PM_MIN_DEG,
                        starts=(base.gains,))
    assert c.rate_d > 0, c.note()  # these vehicles all gain from it
    assert c.rate_d == pytest.approx(RATE_D_OVER_P_S * c.gains.Kd, rel=1e-6)
    ise_d = general_ise(*structure_controller(c.gains, st, w), G, w)
    assert ise_d < two.ise, (ise_d, two.ise)
    # bounds: each gain and the angle P against the gains without D
    b = base.gains
    assert c.gains.Kc <= b.Kc * D_GAIN_MOVE_MAX * (1 + 1e-9)
    assert c.gains.Kd <= b.Kd * D_GAIN_MOVE_MAX * (1 + 1e-9)
    assert c.gains.Kc / c.gains.Kd <= b.Kc / b.Kd * D_ANGLE_P_MOVE_MAX * (1 + 1e-6)
    # margins on the model, recomputed: PM 20 and GM 2 before rate I, the floor with it
    pm, gm = _pm_gm(m, c.gains, st)
    assert pm >= PM_MIN_DEG - 1e-6 and gm >= D_GM_MIN - 1e-6, (pm, gm)
    assert c.integrator_zero_rad_s > 0
    pm_i, _ = _pm_gm(m, c.gains, st, c.integrator_zero_rad_s)
    assert pm_i >= PM_ROBUST_DEG - 1e-6 and pm_i == pytest.approx(c.pm_deg, abs=0.5)
    assert "rate D" in c.note() and "ISE" in c.note()


def test_no_rate_d_where_it_does_not_lower_the_ise_and_the_gains_stay_main_s():
    """A D low-pass of 2 Hz turns the D into lag: no D, and the gains and rate I are those
    the rate path wrote without D (:func:`rate_loop_gains` on the identified gains)."""
    m = MODELS[0]
    g = _identified(m)
    c = cascade_design(m, g, OnboardStructure(20.0, "", RATE_D_OVER_P_S, 2.0), decade=10.0)
    old = rate_loop_gains(m, g, 20.0, decade=10.0)
    assert c.rate_d == 0.0 and c.d_over_p_s == 0.0
    assert c.gains == old.gains and c.rate_i == pytest.approx(old.rate_i)
    assert c.pm_deg == pytest.approx(old.pm_deg)
    assert "no rate D" in c.note()


def test_without_rate_d_the_design_is_the_rate_path_s_old_check():
    for m in MODELS:
        g = _identified(m)
        c = cascade_design(m, g, OnboardStructure(20.0), decade=10.0)
        old = rate_loop_gains(m, g, 20.0, decade=10.0)
        assert (c.gains, c.rate_i, c.pm_deg, c.rate_d) == (old.gains, old.rate_i, old.pm_deg,
                                                            0.0)


def test_the_structure_controller_is_the_cascade_model():
    """The bundled path's structure and the rate path's cascade are one model: the same
    paths for the same parameters (an error filter included), and the rate PID's I and D
    add (``1 + w_i/s + r s F_D``), as ArduCopter's AC_PID sums its terms."""
    w = np.logspace(-1, 3, 50)
    g = PD(5.0, 0.15)
    st = OnboardStructure(18.0, "", 0.03, 25.0, 10.0)
    a = structure_controller(g, st, w)
    b = cascade_controller(g, w, 18.0, 10.0, 0.0, 0.03, 25.0)
    assert np.allclose(a[0], b[0]) and np.allclose(a[1], b[1])
    s = 1j * w
    ft, fe, fd = (1 / (1 + s / (2 * np.pi * hz)) for hz in (18.0, 10.0, 25.0))
    cr, cy = cascade_controller(g, w, 18.0, 10.0, 3.0, 0.03, 25.0)
    kernel = 1 + 3.0 / s + 0.03 * s * fd
    assert np.allclose(cy, kernel * fe * (g.Kc * ft + g.Kd * s))
    assert np.allclose(cr, kernel * fe * g.Kc * ft)


@pytest.mark.parametrize("scale", [0.5, 1.0, 2.0, 4.0, 8.0])
def test_pole_check_with_rate_d_agrees_with_the_nyquist_count(scale):
    """Without rate I margins() counts right; the closed loop's poles (with rate D and its
    filter in the polynomial) must agree, on both sides of instability."""
    m = MODELS[0]
    g = PD(6.0 * scale, 0.2 * scale)
    w = frequency_grid(m.T_prop, m.T1, m.tau)
    Cy = cascade_controller(g, w, 20.0, 0.0, 0.0, RATE_D_OVER_P_S, 20.0)[1]
    nyq = margins(Cy * cascade_process(m, w), w).stable
    poles = _cascade_poles_stable(m, g, 20.0, 0.0, 0.0, RATE_D_OVER_P_S, 20.0)
    assert nyq == poles, (scale, nyq, poles)


@pytest.mark.parametrize("fe", [0.0, 40.0])
def test_yaw_s_check_is_unchanged_by_the_rate_d_argument(fe):
    """Yaw goes through cascade_gains with its error filter and rate I: a D of 0 leaves it
    exactly as before (no D term, no pole-polynomial change)."""
    m = InnerModel(K=60.7, T_prop=0.046, T1=4.3, tau=0.00165)
    g = PD(23.1, 2.74)
    a = cascade_gains(m, g, 20.0, error_filter_hz=fe, integrator_zero_rad_s=1.4)
    b = cascade_gains(m, g, 20.0, error_filter_hz=fe, integrator_zero_rad_s=1.4,
                      d_over_p_s=0.0, d_hz=20.0)
    assert (a.gains, a.scale, a.pm_deg, a.wc_rad_s) == (b.gains, b.scale, b.pm_deg, b.wc_rad_s)
    assert a.rate_d == b.rate_d == 0.0 and (fe > 0 or math.isfinite(a.pm_deg))


# ------------------------------------------------- the gyro filter and the GCS delay taken out
def _lowpass2p(w: np.ndarray, cutoff_hz: float, sample_hz: float) -> np.ndarray:
    """ArduPilot's LowPassFilter2p (libraries/Filter/LowPassFilter2p.cpp: its biquad's
    coefficients as compute_params writes them) at ``w`` (rad/s), sampled at ``sample_hz``."""
    ohm = math.tan(math.pi * cutoff_hz / sample_hz)
    c = 1.0 + 2.0 * math.cos(math.pi / 4.0) * ohm + ohm * ohm
    b0 = ohm * ohm / c
    a1 = 2.0 * (ohm * ohm - 1.0) / c
    a2 = (1.0 - 2.0 * math.cos(math.pi / 4.0) * ohm + ohm * ohm) / c
    z = np.exp(-1j * w / sample_hz)  # z^-1
    return b0 * (1 + 2 * z + z * z) / (1 + a1 * z + a2 * z * z)


def test_the_gyro_filter_is_ardupilot_s_on_the_rate_feedback_alone():
    """Cy's rate term carries LowPassFilter2p (within 1 deg / 2.5 % up to 200 rad/s, sampled
    as slowly as the 400 Hz loop); Cr (the angle error on the attitude) does not see it."""
    w = np.array([10.0, 50.0, 85.0, 125.0, 200.0])
    g = PD(6.0, 0.2)
    cr0, cy0 = cascade_controller(g, w, 20.0, 0.0, 3.0, RATE_D_OVER_P_S, 20.0)
    cr, cy = cascade_controller(g, w, 20.0, 0.0, 3.0, RATE_D_OVER_P_S, 20.0, gyro_hz=20.0)
    assert np.allclose(cr, cr0)
    s = 1j * w
    ft = 1 / (1 + s / (2 * np.pi * 20.0))
    kernel = (1 + 3.0 / s + RATE_D_OVER_P_S * s * ft)
    fg = (cy / kernel - g.Kc * ft) / (g.Kd * s)  # the filter the model puts on the gyro
    ap = _lowpass2p(w, 20.0, 400.0)
    assert np.allclose(np.abs(fg), np.abs(ap), rtol=0.025)
    assert np.allclose(np.angle(fg), np.angle(ap), atol=math.radians(1.0))
    assert math.degrees(-np.angle(fg[3])) > 60.0  # 20 Hz at 125 rad/s: most of a quadrant


@pytest.mark.parametrize("scale", [0.25, 0.5, 1.0, 2.0, 4.0])
def test_pole_check_with_the_gyro_filter_agrees_with_the_nyquist_count(scale):
    m = MODELS[0]
    g = PD(6.0 * scale, 0.2 * scale)
    w = frequency_grid(m.T_prop, m.T1, m.tau)
    Cy = cascade_controller(g, w, 20.0, 0.0, 0.0, RATE_D_OVER_P_S, 20.0, 20.0)[1]
    nyq = margins(Cy * cascade_process(m, w), w).stable
    poles = _cascade_poles_stable(m, g, 20.0, 0.0, 0.0, RATE_D_OVER_P_S, 20.0, gyro_hz=20.0)
    assert nyq == poles, (scale, nyq, poles)


@pytest.mark.parametrize("m", MODELS)
def test_design_on_the_gyro_filter_and_less_delay_keeps_the_margin_there(m):
    """The design with INS_GYRO_FILTER 20 Hz and the ground station's delay taken out: its
    margins, recomputed on exactly that process, hold the floor; a model without the
    filter over-states the margin of the same gains."""
    out = 0.75 * m.tau
    on = InnerModel(m.K, m.T_prop, m.T1, m.tau - out)
    st = OnboardStructure(20.0, "", RATE_D_OVER_P_S, 20.0, gyro_hz=20.0)
    c = cascade_design(m, _identified(m), st, decade=10.0, delay_out_s=out)
    assert c.gyro_hz == 20.0 and c.delay_out_s == pytest.approx(out)
    assert "20 Hz gyro filter" in c.note() and "less" in c.note()
    w = frequency_grid(on.T_prop, on.T1, on.tau, extra_T=(1.0 / c.integrator_zero_rad_s,)
                       if c.integrator_zero_rad_s > 0 else ())
    Cy = cascade_controller(c.gains, w, 20.0, 0.0, c.integrator_zero_rad_s, c.d_over_p_s,
                            20.0, 20.0)[1]
    mm = margins(Cy * cascade_process(on, w), w)
    assert mm.pm_deg >= PM_ROBUST_DEG - 0.5 and mm.pm_deg == pytest.approx(c.pm_deg, abs=0.5)
    assert _cascade_poles_stable(on, c.gains, 20.0, 0.0, c.integrator_zero_rad_s,
                                 c.d_over_p_s, 20.0, gyro_hz=20.0)
    # the same gains on the model without the filter over-state the margin
    Cy0 = cascade_controller(c.gains, w, 20.0, 0.0, c.integrator_zero_rad_s, c.d_over_p_s,
                             20.0)[1]
    assert margins(Cy0 * cascade_process(on, w), w).pm_deg > mm.pm_deg + 5.0


def test_no_gyro_filter_and_no_delay_out_leave_the_design_as_it_was():
    """The bundled SITL's ArduPilot-like cascade has no INS_GYRO_FILTER: 0 and no delay out
    give exactly the design without the new arguments."""
    m = MODELS[0]
    st = OnboardStructure(20.0, "", RATE_D_OVER_P_S, 20.0)
    a = cascade_design(m, _identified(m), st, decade=10.0)
    b = cascade_design(m, _identified(m), OnboardStructure(20.0, "", RATE_D_OVER_P_S, 20.0,
                                                           gyro_hz=0.0), 10.0, 0.0)
    assert a == b and "the identified delay kept" in a.note()


def test_delay_out_is_the_least_plausible_within_the_re_target_s_cap():
    from mrft_gcs.flight.onboard import (
        CAP_SHARE,
        CERTAIN_CAP_SHARE,
        GcsDelay,
        cascade_delay_out_s,
    )
    m = InnerModel(K=80.0, T_prop=0.008, T1=0.2, tau=0.004)
    # measured 11 ms, at least 9 ms: more than the identified delay holds, so its cap
    assert cascade_delay_out_s(m, GcsDelay(0.011, 0.009, 0.015, 0.002, True)) == \
        pytest.approx(CERTAIN_CAP_SHARE * m.tau)
    # unmeasured, at least 1 ms plausible: only that
    assert cascade_delay_out_s(m, GcsDelay(0.002, 0.001, 0.004, math.nan, False, "x")) == \
        pytest.approx(0.001)
    # measured under the identified delay: its least plausible, whole
    assert cascade_delay_out_s(m, GcsDelay(0.002, 0.0015, 0.004, 0.002, True)) == \
        pytest.approx(0.0015)
    # a measured 3.9 ms at least 2 ms plausible: 2 ms, under either cap
    assert cascade_delay_out_s(m, GcsDelay(0.0039, 0.002, 0.008, 0.0039, True)) == \
        pytest.approx(0.002) and 0.002 < CAP_SHARE * m.tau


def test_the_in_air_check_predicts_through_the_same_gyro_filter():
    """The rate path's check model (OnboardCascade) carries the gyro filter in its feedback
    path as the design's model does, and none by default."""
    from mrft_gcs.flight.inair import OnboardCascade
    w = np.array([40.0, 85.0, 125.0])
    g = PD(6.0, 0.2)
    oc = OnboardCascade(20.0, target_rate_ff=False, integrator_zero_rad_s=4.0,
                        d_over_p_s=RATE_D_OVER_P_S, d_filter_hz=20.0, gyro_hz=20.0)
    cr, cy = oc.paths(g, w)
    cr0, cy0 = cascade_controller(g, w, 20.0, 0.0, 4.0, RATE_D_OVER_P_S, 20.0, 20.0)
    assert np.allclose(cr, cr0) and np.allclose(cy, cy0)
    plain = OnboardCascade(20.0, target_rate_ff=False, integrator_zero_rad_s=4.0,
                           d_over_p_s=RATE_D_OVER_P_S, d_filter_hz=20.0)
    assert np.allclose(plain.paths(g, w)[1],
                       cascade_controller(g, w, 20.0, 0.0, 4.0, RATE_D_OVER_P_S, 20.0)[1])
    assert "gyro filter 20 Hz" in oc.describe() and "gyro" not in plain.describe()
