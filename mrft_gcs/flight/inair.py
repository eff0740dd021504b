"""The in-air check of written attitude gains: the margin the autopilot's own loop achieves.

After the gains are written, the autopilot closes its attitude loop with them (its
delays, its rate, its controller structure), which is not the ground-station loop the
identification saw. The check measures that loop. A square wave on the attitude set
point, with its fundamental at the predicted gain crossover of the written loop, gives
the closed loop ``T(jw) = angle / set point`` at the odd harmonics 1, 3, 5 (ratios of
Fourier coefficients over whole cycles, the set point integrated exactly as held
levels). With the written cascade ``u = Kc (r - y) - Kd dy/dt`` (angle-P ``Kc/Kd``
feeding rate-P ``Kd``), ``T = Kc G / (1 + (Kc + Kd s) G)``, so each point gives the
onboard plant ``G = T / (Kc - T (Kc + Kd s))`` and the open loop
``L = (Kc + Kd s) G``. What one short test leaves open is taken as a gain ``k`` and
an extra delay ``d`` on the predicted onboard model (``G_true = k e^{-d s} G``), matched at
the fundamental (the predicted crossover); the measured phase margin is that of the
corrected loop. Where it is short of
:data:`PASS_PM_DEG`, or beyond :data:`PM_HIGH_DEG` (gains more cautious than the loop needs),
the gains are re-designed on the corrected model (the project's ISE-optimal PD, PM >= 20
deg on it) and written and checked again.

The link's round trip lies outside the loop (the set point leaves the ground station
and the angle comes back over it): it is taken out of the measured points where it is
measured; left in, it reads mostly as a lower ``k`` and moves the margin little (6 ms
of round trip: 0.4 deg on a 20 deg loop crossing at 27 rad/s).

ArduPilot's cascade (the rate path's hand-over writes angle P ``Kc/Kd`` and rate P ``Kd``)
is not that PD: the rate target is angle P times the error *plus the target's own rate*
(feed-forward, ``ATC_RATE_FF_ENAB``), low-passed by the rate loop's target filter
(``FLTT``), the rate error by its error filter (``FLTE``), and the rate loop's
feed-forward gain adds ``FF`` times the filtered rate target. :class:`OnboardCascade`
carries those; with one, the points are inverted with its set-point and feedback paths.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from mrft_gcs.flight.onboard import _cascade_poles_stable, cascade_controller
from mrft_gcs.flight.scoring import general_ise
from mrft_gcs.flight.structure import (
    D_GM_MIN,
    OnboardStructure,
    structure_controller,
    structured_pd,
)
from mrft_gcs.loops import Loop
from mrft_gcs.pd_design import frequency_grid, margins, optimal_pd
from mrft_gcs.plant import PD, InnerModel, SideModel, inner_response, side_response

__all__ = ["PM_MIN_DEG", "PASS_PM_DEG", "AGREE_DEG", "MAX_STEADY_SE", "CHECK_HARMONICS",
           "CHECK_AMPLITUDE_RAD",
           "CheckPlan", "InAirCheck", "Verification", "SquareWaveProbe", "plan_check",
           "square_wave", "harmonic_points", "check_margin", "redesigned_gains",
           "PM_HIGH_DEG", "CHECK_ROUNDS", "OnboardCascade", "side_behind_checked",
           "SIDE_PM_MIN_DEG", "STRUCT_TIGHTEN_GAIN", "STRUCT_TIGHTEN_LIVE",
           "structured_redesign", "probe_centre", "CHECK_AMPLITUDE_SQRT_RAD", "probe_amplitude",
           "tighten_above", "without_gain_deficit", "TIGHTEN_OVER_DEG", "TIGHTEN_NEAR_PM_DEG",
           "TIGHTEN_MIN_K"]

#: the least phase margin the written loop must keep (deg), and what its check must measure:
#: that plus the measurement's own error (live, 1-2.5 deg from the onboard truth)
PM_MIN_DEG = 15.0
PASS_PM_DEG = 17.0
#: a written loop measured with more margin than this is re-designed on the measured loop
#: (tighter gains, checked in turn; written back to the first ones if they fail): the
#: ground station cannot see every delay it removes (a link's fixed latency, an onboard filter).
#: The ISE-optimal PD at 25 deg instead of 20 already costs 5-9 % J, at 28 deg 9-16 %; a PD
#: merely too slow at 29 deg was measured at 40 % on a random vehicle
PM_HIGH_DEG = 25.0
#: tightened gains aim at this margin on the measured model (deg; the design's own is 20),
#: leaving room for the error of the model measured about the old crossover (2-3 % J)
TIGHTEN_PM_DEG = 22.0
#: and move at most this many times from the gains checked, per check
TIGHTEN_MAX = 2.0
#: a loop designed at the margin is tightened where it measures more than its prediction plus
#: this (deg; the check's own error is 1-2 deg live), to :data:`TIGHTEN_NEAR_PM_DEG` while it
#: measures within the band: its new crossover lies near the one measured, where the corrected
#: model holds (in-process, PX4-like vehicles: J max 4.4 % vs 6.3 % aiming at 22 from 3 over)
TIGHTEN_OVER_DEG = 2.0
TIGHTEN_NEAR_PM_DEG = 21.0
#: a loop closed through a rate-target low-pass (ArduPilot's FLTT) measured within the band is
#: re-designed on that structure where the design at PM 20 deg on the measured loop lowers its
#: ISE by at least this share: the J of such a loop climbs steeply with margin above 20 deg
#: (in-process, 20.5-22 deg measured: 8.6-10.3 % J on the truth, 4.6-8.2 % re-designed)
STRUCT_TIGHTEN_GAIN = 0.03
#: whether a live tune's check re-designs on the rate-target low-pass at all. Off: with it on,
#: a small live ArduPilot-like vehicle still lost its hover after repeated checks, and the live
#: in-domain population completed no more vehicles (docs/writing-gains.md)
STRUCT_TIGHTEN_LIVE = False
#: checks of one loop at most (each re-designs on the loop measured by the one before)
CHECK_ROUNDS = 3
#: predicted and measured margins that differ by more are reported as a disagreement (deg)
AGREE_DEG = 3.0
#: odd harmonics of the square wave at which the closed loop is measured
CHECK_HARMONICS = (1, 3, 5)
#: whole cycles measured (:data:`SETTLE_CYCLES` run first, to let the start transient die out)
CHECK_CYCLES = 3
#: cycles flown before those measured: after one, a 20 deg loop's slow mode (the PD's zero,
#: some 0.1 s) still carried the start through the cycles measured, which read 1-2 deg high
#: (in-process, noise-free; after two, within 0.7 deg on five of six PX4-like vehicles)
SETTLE_CYCLES = 2
#: the square wave starts this share of a period into its positive half: from a quarter, the
#: wave's running integral swings about zero and the start excites the slow modes less
#: (in-process: 0.3-0.5 deg of the transient's bias less than from the wave's edge)
START_PHASE = 0.25
#: a fundamental whose cycle-to-cycle spread is larger (relative standard error) is not a
#: steady response to the square wave: a loop that oscillates on its own reads as any margin
#: (in-process, a written loop at -1 deg: 0.35 and "27 deg"; steady loops 0.05-0.06)
MAX_STEADY_SE = 0.15
#: the least phase margin side gains re-designed behind checked attitude gains keep on the
#: measured cascade (deg): the written side loops' robust margin
SIDE_PM_MIN_DEG = 15.0
#: the least delay (and fast lag) of a corrected model (s)
MIN_TAU_S = 1e-4
#: the square wave's amplitude on the attitude set point (rad): 2 deg, some 6 deg of swing
#: at a 20 deg loop's resonance, well clear of noise and of the tilt limits
CHECK_AMPLITUDE_RAD = 0.035
#: the amplitude on a loop closed through ArduPilot's angle controller (rad): its square-root
#: controller is linear only for errors under ``accel_max / P^2`` (1-3 deg at the angle P
#: written with rate D), and each step of the square wave puts twice the amplitude into the
#: error; beyond it the angle P acts smaller and the check reads a larger margin (in-process,
#: 2 deg: up to 6 deg over the onboard truth; 1 deg: within 2, the noise's share rising)
CHECK_AMPLITUDE_SQRT_RAD = math.radians(1.0)


@dataclass(frozen=True)
class OnboardCascade:
    """ArduPilot's attitude cascade as it closes with angle P ``Kc/Kd`` and rate P ``Kd``.

    ``u = (Kd F_E + ff) F_T r - Kd F_E s y`` with the rate target
    ``r = (Kc/Kd) (x - y) + s x`` (``x`` the attitude target, ``y`` the angle): ``F_T``,
    ``F_E`` first-order low-passes at ``target_filter_hz``, ``error_filter_hz`` (0: none),
    ``ff`` the rate loop's feed-forward gain (normalised command per rad/s).
    """

    target_filter_hz: float = 0.0
    error_filter_hz: float = 0.0
    ff: float = 0.0
    #: the rate target holds the attitude target's own rate (ArduPilot's ATC_RATE_FF_ENAB);
    #: False: angle P times the error alone (the bundled SITL's ArduPilot-like cascade)
    target_rate_ff: bool = True
    #: the rate loop's integrator zero (rad/s; 0: no rate I): rate P and I act on the same
    #: (error-filtered) rate error, so the PID is ``Kd (1 + w_i / s)`` in both paths
    integrator_zero_rad_s: float = 0.0
    #: rate D as a share of rate P (s; 0: none), on the same rate error (AC_PID), low-passed
    #: at ``d_filter_hz`` (0: none): the PID is ``Kd (1 + w_i / s + r s F_D)``
    d_over_p_s: float = 0.0
    d_filter_hz: float = 0.0
    #: the gyro low-pass the rate error is taken on (Hz, second order; 0: none;
    #: ``INS_GYRO_FILTER``): in the rate feedback only, not in the angle error
    gyro_hz: float = 0.0

    def paths(self, gains: PD, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(C_r, C_y)``: the command ``u = C_r x - C_y y`` at ``w`` (rad/s).

        >>> c = OnboardCascade()
        >>> cr, cy = c.paths(PD(2.0, 0.5), np.array([4.0]))
        >>> bool(np.allclose(cr, 2 + 2j) and np.allclose(cy, 2 + 2j))
        True
        """
        # the PID and filters as every design of written gains models them: u = cr x - cy y;
        # the vehicle's rate FF and the target's own rate (ATC_RATE_FF_ENAB) go on top
        cr, cy = cascade_controller(gains, w, self.target_filter_hz, self.error_filter_hz,
                                    self.integrator_zero_rad_s, self.d_over_p_s,
                                    self.d_filter_hz, self.gyro_hz)
        s = 1j * np.asarray(w, float)
        hz = self.target_filter_hz
        ft = 1.0 / (1.0 + s / (2 * np.pi * hz)) if hz > 0 else np.ones_like(s)
        ff = self.ff * ft * gains.Kc / gains.Kd
        if self.target_rate_ff:  # the rate PID on the filtered target rate s x, FF too
            return cr + ff + (cy - cr) * ft + self.ff * ft * s, cy + ff
        return cr + ff, cy + ff

    def filters(self, w: np.ndarray) -> np.ndarray:
        """The target and error filters in series at ``w`` (rad/s)."""
        s = 1j * np.asarray(w, float)
        out = np.ones_like(s)
        for hz in (self.target_filter_hz, self.error_filter_hz):
            if hz > 0:
                out = out / (1.0 + s / (2 * np.pi * hz))
        return out

    def describe(self) -> str:
        rate = " + target rate" if self.target_rate_ff else ""
        return (f"ArduPilot cascade: rate target = angle P x error{rate}, target filter "
                f"{self.target_filter_hz:g} Hz, error filter {self.error_filter_hz:g} Hz, "
                f"rate FF {self.ff:g}"
                + (f", rate I zero {self.integrator_zero_rad_s:.3g} rad/s"
                   if self.integrator_zero_rad_s > 0 else "")
                + (f", rate D {self.d_over_p_s * 1e3:.1f} ms x rate P through "
                   f"{self.d_filter_hz:g} Hz" if self.d_over_p_s > 0 else "")
                + (f", gyro filter {self.gyro_hz:g} Hz" if self.gyro_hz > 0 else ""))

    @property
    def structure(self) -> OnboardStructure | None:
        """The same loop as an :class:`~mrft_gcs.flight.structure.OnboardStructure` where it
        is one (a target filter, no rate FF or I, no target rate; None otherwise)."""
        if (self.target_filter_hz > 0 and not self.target_rate_ff and self.ff == 0
                and self.error_filter_hz == 0 and self.integrator_zero_rad_s == 0):
            return OnboardStructure(self.target_filter_hz, "", self.d_over_p_s,
                                    self.d_filter_hz, gyro_hz=self.gyro_hz)
        return None


def _paths(gains: PD, w: np.ndarray, cascade: OnboardCascade | None
           ) -> tuple[np.ndarray, np.ndarray]:
    """Set-point and feedback paths of the written loop: the plain PD ``u = Kc (x - y) -
    Kd dy/dt`` without a cascade."""
    if cascade is not None:
        return cascade.paths(gains, w)
    s = 1j * np.asarray(w, float)
    return gains.Kc + 0 * s, gains.Kc + gains.Kd * s


def probe_amplitude(target_filter_hz: float) -> float:
    """The check's square-wave amplitude (rad) on a loop whose rate target is low-passed at
    ``target_filter_hz`` (read from the vehicle; 0: none).

    A rate-target filter is ArduPilot's cascade, whose angle controller is a square root
    beyond a small error: :data:`CHECK_AMPLITUDE_SQRT_RAD` keeps the probe nearer its linear
    part; elsewhere :data:`CHECK_AMPLITUDE_RAD`.

    >>> probe_amplitude(20.0) < probe_amplitude(0.0)
    True
    """
    return CHECK_AMPLITUDE_SQRT_RAD if target_filter_hz > 0 else CHECK_AMPLITUDE_RAD


#: a measured gain under this share of the model's is a loop riding its torque limits, whose
#: phase reading is off as well: no tightening stands on it (:func:`without_gain_deficit`)
TIGHTEN_MIN_K = 0.85


def tighten_above(predicted_pm_deg: float, rate_d: bool = False) -> float:
    """The measured margin (deg) above which gains designed at the margin are re-designed on
    the loop measured and checked again.

    A loop written with rate D sits under its gain cap, not at the margin (``rate_d``: never
    tightened, ``inf``; the ArduCopter rate path's loops too).

    The prediction is the design's margin at the ground-station delay re-targeted out of
    the gains, held back where they must keep PM 15 deg over every plausible delay: the
    onboard loop's own delay is what the ground station cannot see. A check that measures
    more than the prediction plus :data:`TIGHTEN_OVER_DEG` has pinned less onboard delay than
    the design allowed for, and the gains are more cautious than its target. Never above
    :data:`PM_HIGH_DEG`.

    >>> tighten_above(20.0), tighten_above(24.0), tighten_above(20.0, rate_d=True)
    (22.0, 25.0, inf)
    """
    if rate_d:
        return math.inf
    return min(PM_HIGH_DEG, predicted_pm_deg + TIGHTEN_OVER_DEG)


@dataclass(frozen=True)
class CheckPlan:
    """The square wave of one loop's check and what it should find.

    ``period_s`` puts the fundamental at the predicted crossover ``wc_rad_s`` of the
    written loop on ``model`` (the identified model with the onboard delay).
    """

    model: InnerModel
    gains: PD
    period_s: float
    amplitude: float
    cycles: int
    wc_rad_s: float
    predicted_pm_deg: float
    #: the autopilot's cascade the gains close (None: the plain PD)
    cascade: OnboardCascade | None = None

    @property
    def duration_s(self) -> float:
        """Settling cycles plus measured cycles (s)."""
        return (self.cycles + SETTLE_CYCLES) * self.period_s


@dataclass(frozen=True)
class InAirCheck:
    """What the check measured on one loop.

    ``w``, ``T`` and ``se`` are the measured closed-loop points (rad/s, complex, relative
    standard error); ``k`` and ``extra_delay_s`` the fitted correction of the predicted
    onboard model; ``measured_pm_deg`` the phase margin of the written gains on the
    corrected model; ``fit_rms`` the misfit of the corrected model to the points in
    units of their standard errors.
    """

    predicted_pm_deg: float
    measured_pm_deg: float
    k: float
    extra_delay_s: float
    w: np.ndarray
    T: np.ndarray
    se: np.ndarray
    fit_rms: float
    #: what the input was (the vehicle's record of the set point, or the set point as sent)
    source: str = ""

    def corrected_model(self, plan: CheckPlan) -> InnerModel:
        """The plan's model with the measured gain and extra delay: the onboard loop's plant.

        Where the model has less delay to give than the lead measured (its re-targeted delay
        near 0: the identified lags, not the delay, are what is too slow), the rest of the
        lead comes out of its fast lag ``T_prop``, matched at the fundamental in phase and
        gain: clipped at no delay instead, the model kept the lag the check had measured
        away, and gains re-designed on it came out more cautious than those checked."""
        m = plan.model
        tau = m.tau + self.extra_delay_s
        if tau >= MIN_TAU_S or self.w.size == 0:
            return InnerModel(m.K * self.k, m.T_prop, m.T1, max(tau, MIN_TAU_S))
        w = float(np.min(self.w))
        ph = math.atan(w * m.T_prop) - (MIN_TAU_S - tau) * w
        t_prop = max(math.tan(ph) / w if ph > 0 else 0.0, MIN_TAU_S)
        gain = math.hypot(1.0, w * t_prop) / math.hypot(1.0, w * m.T_prop)
        return InnerModel(m.K * self.k * gain, t_prop, m.T1, MIN_TAU_S)

    @property
    def steady(self) -> bool:
        """The response followed the square wave cycle after cycle."""
        return bool(self.se[0] <= MAX_STEADY_SE)

    @property
    def passed(self) -> bool:
        return bool(self.steady and np.isfinite(self.measured_pm_deg)
                     and self.measured_pm_deg >= PASS_PM_DEG)

    @property
    def agrees(self) -> bool:
        return abs(self.measured_pm_deg - self.predicted_pm_deg) <= AGREE_DEG


def _open_loop(model: InnerModel, gains: PD, w: np.ndarray,
               cascade: OnboardCascade | None = None) -> np.ndarray:
    G = inner_response(model.K, model.T_prop, model.T1, model.tau, w)[0]
    return _paths(gains, w, cascade)[1] * G


def _stable(model: InnerModel, gains: PD, cascade: OnboardCascade | None, nyquist: bool
            ) -> bool:
    """Whether the written loop on ``model`` is stable. With a rate I the loop has two
    integrators and its phase starts at -180 deg: the Nyquist count of
    :func:`~mrft_gcs.pd_design.margins` (``nyquist``, written for one) takes a drag pole
    under the I's zero for an encirclement, so the closed loop's poles decide, as in the
    design (the rate FF, 0 on ArduCopter's roll and pitch, is not in that pole model)."""
    c = cascade
    if c is None or c.integrator_zero_rad_s <= 0 or c.ff != 0:
        return nyquist
    return _cascade_poles_stable(model, gains, c.target_filter_hz, c.error_filter_hz,
                                 c.integrator_zero_rad_s, c.d_over_p_s, c.d_filter_hz,
                                 loop_delay_s=0.0)


def plan_check(model: InnerModel, gains: PD, amplitude: float,
               cycles: int = CHECK_CYCLES, cascade: OnboardCascade | None = None) -> CheckPlan:
    """The check of ``gains`` on ``model``: fundamental at the predicted gain crossover.

    >>> p = plan_check(InnerModel(K=40.0, T_prop=0.03, T1=0.2, tau=0.01), PD(0.8, 0.1), 0.05)
    >>> 0.05 < p.period_s < 1.0 and 15 < p.predicted_pm_deg < 90
    True
    """
    w = frequency_grid(model.T_prop, model.T1, model.tau)
    m = margins(_open_loop(model, gains, w, cascade), w)
    if not np.isfinite(m.wc) or not _stable(model, gains, cascade, m.stable):
        raise ValueError("the written loop has no gain crossover on its model, or is unstable")
    return CheckPlan(model, gains, 2 * np.pi / m.wc, float(amplitude), int(cycles),
                     float(m.wc), float(m.pm_deg), cascade)


def square_wave(t_s: float, period_s: float, amplitude: float) -> float:
    """``+amplitude`` in the first half of each period from ``t_s = 0``, ``-amplitude`` after.

    >>> square_wave(0.1, 1.0, 2.0), square_wave(0.6, 1.0, 2.0)
    (2.0, -2.0)
    """
    return amplitude if (t_s / period_s) % 1.0 < 0.5 else -amplitude


def _held_coefficient(t: np.ndarray, u: np.ndarray, w: float, t0: float, t1: float) -> complex:
    """``(2/(t1-t0)) * integral of u(t) e^{-jwt}`` with ``u`` held from each ``t[i]``."""
    edges = np.clip(np.append(t, t1), t0, t1)
    e = np.exp(-1j * w * edges)
    return complex(2.0 / (t1 - t0) * np.sum(u * (e[1:] - e[:-1]) / (-1j * w)))


def _sampled_coefficient(t: np.ndarray, y: np.ndarray, w: float, t0: float, t1: float
                         ) -> complex:
    """The same integral for a sampled signal, linear between samples (trapezoid)."""
    grid = np.linspace(t0, t1, max(64, int(8 * (t1 - t0) * w / (2 * np.pi)) * 16))
    yi = np.interp(grid, t, y)
    return complex(2.0 / (t1 - t0) * np.trapezoid(yi * np.exp(-1j * w * grid), grid))


def harmonic_points(t_u, u, t_y, y, period_s: float, t0_s: float, cycles: int,
                    harmonics=CHECK_HARMONICS, link_delay_s: float = 0.0,
                    sampled_u: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closed-loop points ``(w, T, se)`` from a square-wave test, one per harmonic.

    ``t_u, u``: the set points as sent (held until the next) or, ``sampled_u``, as the
    vehicle reported tracking them (samples, linear between), ``t_y, y``: the measured
    angle, both on one clock (s); the cycles measured start at ``t0_s``. ``T`` is the
    mean of the per-cycle ratios ``Y_k / U_k``, multiplied by ``e^{j w link_delay_s}``;
    ``se`` its standard error relative to ``|T|`` (cycle-to-cycle spread).
    """
    t_u, u = np.asarray(t_u, float), np.asarray(u, float)
    t_y, y = np.asarray(t_y, float), np.asarray(y, float)
    w0 = 2 * np.pi / period_s
    ws, Ts, ses = [], [], []
    for k in harmonics:
        w = k * w0
        per = []
        for c in range(cycles):
            a, b = t0_s + c * period_s, t0_s + (c + 1) * period_s
            U = (_sampled_coefficient(t_u, u, w, a, b) if sampled_u
                 else _held_coefficient(t_u, u, w, a, b))
            Y = _sampled_coefficient(t_y, y, w, a, b)
            per.append(Y / U)
        r = np.asarray(per) * np.exp(1j * w * link_delay_s)
        mean = complex(np.mean(r))
        se = float(np.std(r, ddof=1) / np.sqrt(len(r)) / abs(mean)) if len(r) > 1 else np.inf
        ws.append(w)
        Ts.append(mean)
        ses.append(max(se, 0.01))
    return np.asarray(ws), np.asarray(Ts), np.asarray(ses)


def check_margin(plan: CheckPlan, w, T, se) -> InAirCheck:
    """Measured phase margin of ``plan.gains`` from closed-loop points ``(w, T, se)``.

    The onboard plant at each point, ``G = T / (Kc - T (Kc + Kd s))`` (with a cascade
    ``T / (C_r - T C_y)``), is compared with the predicted model: ``k`` and the extra delay
    ``d`` make it match at the fundamental (the predicted crossover); the harmonics give the
    misfit of that correction (``fit_rms``).
    """
    w, T, se = np.asarray(w, float), np.asarray(T, complex), np.asarray(se, float)
    g = plan.gains
    cr, cy = _paths(g, w, plan.cascade)
    G = T / (cr - T * cy)
    m = plan.model
    Gm = inner_response(m.K, m.T_prop, m.T1, m.tau, w)[0]
    ratio = G / Gm
    # a point's relative error in G grows with |1 + L| / ... ; the relative error of T is
    # the measured one, carried through by the derivative of G(T): dG/G = dT/T * 1/(1 - T
    # C_y / C_r)
    amp = np.abs(1.0 / (1.0 - T * cy / cr))
    sg = np.maximum(se * amp, 1e-3)
    # the gain and delay from the fundamental alone: it lies at the predicted crossover, where
    # the margin is, and the model's error is no pure gain and delay (the identified shape
    # leaves the vehicle's above the relay's frequency): fitted over the harmonics, the delay
    # (weighted by w^2, the 5th harmonic's) moved the corrected phase at the crossover
    i = int(np.argmin(w))
    lnk = float(np.log(np.abs(ratio[i])))
    d = float(-np.angle(ratio[i]) / w[i])
    fitted = np.exp(lnk - 1j * w * d)
    resid = np.abs(np.log(ratio / fitted)) / sg
    grid = frequency_grid(m.T_prop, m.T1, m.tau + max(d, 0.0))
    L = np.exp(lnk - 1j * grid * d) * _open_loop(m, g, grid, plan.cascade)
    mm = margins(L, grid)
    corrected = InnerModel(m.K * math.exp(lnk), m.T_prop, m.T1, max(m.tau + d, 0.0))
    pm = float(mm.pm_deg) if _stable(corrected, g, plan.cascade, mm.stable) else float("-inf")
    return InAirCheck(plan.predicted_pm_deg, pm, float(np.exp(lnk)), d, w, T, se,
                      float(np.sqrt(np.mean(resid**2))))


def without_gain_deficit(plan: CheckPlan, check: InAirCheck) -> InAirCheck:
    """``check`` with a measured gain under the model's (``k < 1``) taken as the model's, its
    margin read again: what a tightening may stand on.

    A loop whose torque command rides its limits (sensor noise through the rate P of a light
    vehicle) answers the square wave with less gain than it has for small signals, and reads
    as more margin than its linear loop keeps (in-process, noise on: k 0.65-0.68 and 24-28 deg
    read, 16.8 on the onboard truth; noise off: k 1.04 and 17.3). Re-designed on that gain,
    the gains went to PM 11-12 deg on the truth. A measured delay (the onboard one the ground
    station cannot see) is kept: it is what the check is for. Under :data:`TIGHTEN_MIN_K` the
    phase is biased too (a re-design on its delay alone went to PM 15.0 on the truth from
    17.1): the prediction stands, nothing to tighten on.
    """
    if not check.k < 1.0:
        return check
    if check.k < TIGHTEN_MIN_K:
        return dataclasses.replace(check, k=1.0, measured_pm_deg=plan.predicted_pm_deg)
    m, g = plan.model, plan.gains
    d = check.extra_delay_s
    grid = frequency_grid(m.T_prop, m.T1, m.tau + max(d, 0.0))
    mm = margins(np.exp(-1j * grid * d) * _open_loop(m, g, grid, plan.cascade), grid)
    out = dataclasses.replace(check, k=1.0)
    stable = _stable(out.corrected_model(plan), g, plan.cascade, mm.stable)
    return dataclasses.replace(out, measured_pm_deg=float(mm.pm_deg) if stable else -math.inf)


def _on_structure(plan: CheckPlan, check: InAirCheck, target_hz: float
                  ) -> tuple[np.ndarray, np.ndarray, float]:
    """``(G, w, ise)``: the onboard plant the check's points give when inverted through the
    rate-target low-pass at ``target_hz`` (the loop it closes), and the ISE of the gains
    checked on it."""
    on = check_margin(dataclasses.replace(
        plan, cascade=OnboardCascade(target_hz, target_rate_ff=False)), check.w, check.T,
        check.se)
    m = on.corrected_model(plan)
    w = frequency_grid(m.T_prop, m.T1, m.tau)
    G = inner_response(m.K, m.T_prop, m.T1, m.tau, w)[0]
    return G, w, general_ise(*structure_controller(plan.gains, OnboardStructure(target_hz), w),
                             G, w)


def structured_redesign(plan: CheckPlan, check: InAirCheck, target_hz: float
                        ) -> tuple[PD, float]:
    """Gains designed on a rate-target low-pass (ArduPilot's FLTT, ``target_hz``) for the loop
    a plain check measured, and the share by which they lower the ISE there.

    The check's points are inverted through the filter (the plant, not a PD-equivalent one);
    the gains are the ISE-optimal ones of that structure under PM 20 deg on it
    (:func:`~mrft_gcs.flight.structure.structured_pd`); a tightening moves at most
    :data:`TIGHTEN_MAX` times from the gains checked.
    """
    G, w, ise_now = _on_structure(plan, check, target_hz)
    d = structured_pd(G, w, OnboardStructure(target_hz), starts=(plan.gains,))
    new, ise_new = d.gains, d.ise
    up = max(new.Kc / plan.gains.Kc, new.Kd / plan.gains.Kd)
    if check.passed and up > TIGHTEN_MAX:
        new = PD(new.Kc * TIGHTEN_MAX / up, new.Kd * TIGHTEN_MAX / up)
    return new, (1.0 - ise_new / ise_now) if np.isfinite(ise_now) and ise_now > 0 else 0.0


def redesigned_gains(plan: CheckPlan, check: InAirCheck, target_hz: float = 0.0) -> PD:
    """The ISE-optimal PD of the measured onboard model ``k e^{-d s} G``.

    Backing off (margin short), the design's own PM >= 20 deg. Tightening (margin beyond
    :data:`PM_HIGH_DEG`), PM >= :data:`TIGHTEN_PM_DEG` (within it, over :func:`tighten_above`:
    :data:`TIGHTEN_NEAR_PM_DEG`) and at most :data:`TIGHTEN_MAX` times
    the gains checked: the model was measured about the old crossover, and the new one lies
    above it, where the fitted gain and delay are an extrapolation. A loop the autopilot
    closes through a rate-target low-pass at ``target_hz`` (> 0, a plain check) is
    re-designed on it (:func:`structured_redesign`).
    """
    if target_hz > 0 and plan.cascade is None and check.steady:
        return structured_redesign(plan, check, target_hz)[0]
    m = check.corrected_model(plan)
    w = frequency_grid(m.T_prop, m.T1, m.tau)
    G = inner_response(m.K, m.T_prop, m.T1, m.tau, w)[0]
    st = plan.cascade.structure if plan.cascade is not None else None
    if st is not None and st.d_over_p_s > 0:
        # rate D written: re-designed on that structure, never above the gains checked (a
        # loop with D is designed under a gain cap, not at the margin: it is not tightened)
        return structured_pd(G, w, st, starts=(plan.gains,), gm_min=D_GM_MIN,
                             most=plan.gains).gains
    if plan.cascade is not None:
        # the cascade's filters lag angle P's part of the loop; designing the PD on the plant
        # behind them (its D part lagged too) keeps the design's margin, conservatively
        G = G * plan.cascade.filters(w)
    if not check.passed:
        return optimal_pd(G, w).pd
    pm = TIGHTEN_PM_DEG if check.measured_pm_deg > PM_HIGH_DEG else TIGHTEN_NEAR_PM_DEG
    new = optimal_pd(G, w, pm_min_deg=pm).pd
    up = max(new.Kc / plan.gains.Kc, new.Kd / plan.gains.Kd)
    return new if up <= TIGHTEN_MAX else PD(new.Kc * TIGHTEN_MAX / up, new.Kd * TIGHTEN_MAX / up)


def _side_cascade(side: SideModel, plan: CheckPlan, check: InAirCheck, gains: PD
                  ) -> tuple[np.ndarray, np.ndarray]:
    """``(G, w)``: the side process behind attitude ``gains`` on the plant the check measured."""
    m = check.corrected_model(plan)
    w = frequency_grid(m.T_prop, m.T1, m.tau, extra_T=(side.T2, side.tau))
    g = inner_response(m.K, m.T_prop, m.T1, m.tau, w)[0]
    cr, cy = _paths(gains, w, plan.cascade)
    return cr * g / (1.0 + cy * g) * side_response(side.K, side.T2, side.tau, w)[0], w


def side_behind_checked(written: PD, side: SideModel, first: PD, plan: CheckPlan,
                        check: InAirCheck) -> PD:
    """Side gains for the attitude gains a check kept (``plan.gains``, in place of ``first``).

    x and y are flown behind pitch and roll; ``written`` were designed behind the attitude
    gains ``first`` written. Where a check re-wrote those (backing off: a slower attitude loop,
    less margin for the side loop behind it), ``written`` stay where they keep
    :data:`SIDE_PM_MIN_DEG` on the side process behind the gains kept, on the attitude plant
    the check measured (:meth:`InAirCheck.corrected_model`) and the side part ``side``
    identified; short of it, the ISE-optimal PD of that process (PM 20 deg on it) replaces
    them. Side gains with more margin are left as they are: the check did not measure the side
    loop.

    Examples
    --------
    >>> plan = plan_check(InnerModel(40.0, 0.02, 0.3, 0.010), PD(1.5, 0.15), 0.035)
    >>> chk = InAirCheck(20.0, 20.0, 1.0, 0.0, np.ones(3), np.ones(3), np.full(3, 0.05), 0.0)
    >>> side = SideModel(9.8, 1.5, 0.01)
    >>> side_behind_checked(PD(2.0, 1.0), side, PD(3.0, 0.25), plan, chk)  # margin kept
    PD(Kc=2.0, Kd=1.0)
    >>> side_behind_checked(PD(9.0, 1.0), side, PD(3.0, 0.25), plan, chk).Kc < 9.0
    True
    """
    if first == plan.gains:
        return written
    G, w = _side_cascade(side, plan, check, plan.gains)
    m = margins((written.Kc + written.Kd * 1j * w) * G, w)
    if m.stable and m.pm_deg >= SIDE_PM_MIN_DEG:
        return written
    return optimal_pd(G, w).pd


@dataclass(frozen=True)
class Verification:
    """How one written loop was checked in the air (the report's ``verification``)."""

    method: str
    passed: bool
    predicted_pm_deg: float = math.nan
    measured_pm_deg: float = math.nan
    action: str = "none"
    note: str = ""

    def as_dict(self) -> dict[str, Any]:
        def num(x: float) -> float | None:
            return float(x) if math.isfinite(x) else None
        return {"method": self.method, "passed": self.passed,
                "predicted_pm_deg": num(self.predicted_pm_deg),
                "measured_pm_deg": num(self.measured_pm_deg), "action": self.action,
                "note": self.note or None}

    def line(self) -> str:
        """What a user reads, e.g. ``verified: PM 21 deg measured (predicted 20)``."""
        if not math.isfinite(self.measured_pm_deg):
            return f"{'checked' if self.passed else 'not verified'}: {self.method}"
        word = "verified" if self.passed else "NOT verified"
        tail = f"; {self.action}" if self.action != "none" else ""
        return (f"{word}: PM {self.measured_pm_deg:.0f} deg measured (predicted "
                f"{self.predicted_pm_deg:.0f}){tail}")


def probe_centre(hold_rad: float, trim: float, kc: float) -> float:
    """The attitude set point (rad) at which a written loop without integrator holds the
    attitude ``hold_rad`` that the ground station's own PD (``u = trim + Kc e - Kd dy/dt``)
    held with its torque ``trim``.

    The written cascade (angle P ``Kc/Kd``, rate P ``Kd``, rate I 0) settles where
    ``Kc (set point - angle)`` balances the vehicle's torque bias, which the ground station's
    PD carried as ``trim``: centred on ``hold_rad`` alone, the check's loop would lean by
    ``trim / Kc`` and the vehicle, its x/y hold off through the check, would drift.

    >>> round(probe_centre(0.01, 0.02, 2.0), 3)
    0.02
    """
    return hold_rad + trim / kc if kc > 0 else hold_rad


class SquareWaveProbe:
    """The set points of a check on roll and pitch at once, and the record of the test.

    ``step(now_s, t_att_s, roll, pitch)`` is called on every setpoint tick with the ground
    station's monotonic time and the latest ATTITUDE sample (vehicle time); it returns
    the roll and pitch set points (rad) about ``centre``. The record maps the commands
    onto the vehicle clock by the least ``now - t_att`` seen during the test (the link's
    quickest delivery), so no clock offset from earlier in the session enters it.
    """

    def __init__(self, plans: dict[Loop, CheckPlan],
                 centre: tuple[float, float] = (0.0, 0.0),
                 swing_limit: float | None = None, settle_s: float = 0.0) -> None:
        self.plans = dict(plans)
        self.centre = centre
        #: the centre alone is flown this long after the square waves (s) before :attr:`done`
        self.settle_s = settle_s
        #: a swing off the centre past this many of a loop's amplitudes is recorded in
        #: :attr:`swing_over` (the caller stops the check); None: not watched
        self.swing_limit = swing_limit
        self.waves_s = max(p.duration_s for p in self.plans.values())
        self.duration_s = self.waves_s + settle_s
        self.reset()

    def reset(self) -> None:
        self.t0: float | None = None
        self.cmd: list[tuple[float, float, float]] = []  # now, roll_sp, pitch_sp
        self.smp: dict[float, tuple[float, float]] = {}  # t_att -> roll, pitch
        self.offset = math.inf
        #: the set points as the vehicle reported tracking them (ATTITUDE_TARGET), if it did
        self.tracked: dict[float, tuple[float, float]] = {}
        #: per loop, whether :meth:`points` took the input from that record
        self.used_tracked: dict[Loop, bool] = {}
        #: the first loop that swung past ``swing_limit`` and its swing (rad), else None
        self.swing_over: tuple[Loop, float] | None = None

    def track(self, t_s: float, roll: float, pitch: float) -> None:
        """One set point the vehicle reported tracking (vehicle clock, s; rad)."""
        self.tracked[t_s] = (roll, pitch)

    @property
    def done(self) -> bool:
        return bool(self.cmd) and self.cmd[-1][0] - self.cmd[0][0] >= self.duration_s

    def step(self, now_s: float, t_att_s: float, roll: float, pitch: float
             ) -> tuple[float, float]:
        if self.t0 is None:
            self.t0 = now_s
        self.offset = min(self.offset, now_s - t_att_s)
        self.smp[t_att_s] = (roll, pitch)
        if self.swing_limit is not None and self.swing_over is None:
            for lp, y, c in zip((Loop.ROLL, Loop.PITCH), (roll, pitch), self.centre, strict=True):
                p = self.plans.get(lp)
                if p is not None and abs(y - c) > self.swing_limit * p.amplitude:
                    self.swing_over = (lp, abs(y - c))
        t = now_s - self.t0
        out = [c + (square_wave(t + START_PHASE * p.period_s, p.period_s, p.amplitude)
                    if (p := self.plans.get(lp)) and t < self.waves_s else 0.0)
               for lp, c in zip((Loop.ROLL, Loop.PITCH), self.centre, strict=True)]
        self.cmd.append((now_s, out[0], out[1]))
        return out[0], out[1]

    def points(self, link_delay_s: float = 0.0
               ) -> dict[Loop, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Closed-loop points per checked loop (:func:`harmonic_points`).

        With the vehicle's own record of the set points it tracked (:meth:`track`) covering
        the measured cycles, those are the input, on the vehicle's clock like the angles: no
        link, stream or host timing enters. Otherwise the commands as sent, moved onto the
        vehicle clock, with ``link_delay_s`` (the round trip) taken out."""
        c = np.asarray(self.cmd, float)
        ts = np.asarray(sorted(self.smp), float)
        y = np.asarray([self.smp[t] for t in ts], float)
        t_cmd = c[:, 0] - self.offset  # on the vehicle clock
        tt = np.asarray(sorted(self.tracked), float)
        out = {}
        for i, lp in enumerate((Loop.ROLL, Loop.PITCH)):
            p = self.plans.get(lp)
            if p is None:
                continue
            t0 = t_cmd[0] + SETTLE_CYCLES * p.period_s
            t1 = t0 + p.cycles * p.period_s
            inside = tt[(tt >= t0) & (tt <= t1)]
            if inside.size >= 8 * p.cycles * len(CHECK_HARMONICS) and (
                    np.max(np.diff(np.concatenate(([t0], inside, [t1])))) < 0.1 * p.period_s):
                u = np.asarray([self.tracked[t][i] for t in tt], float)
                out[lp] = harmonic_points(tt, u, ts, y[:, i], p.period_s, t0, p.cycles,
                                          sampled_u=True)
                self.used_tracked[lp] = True
            else:
                self.used_tracked[lp] = False
                out[lp] = harmonic_points(t_cmd, c[:, 1 + i], ts, y[:, i], p.period_s, t0,
                                          p.cycles, link_delay_s=link_delay_s)
        return out
