"""Input-driven comparison: the model driven by the relay output that was recorded.

Comparing the model's own relay cycle with the measured one (closed loop) turns
every lag the model lacks into a longer period, and the closed-loop cycle also
moves with measurement noise (which shifts the switches) and locks to whole
samples, by as much as the differences between lag effects. Driving the model
with the recorded commands instead keeps the measured switch times, so what is
left to compare is the response to each switch: a transport delay shifts it, a
rate limit ramps the input over ``2 h / rate`` (a constant slope of the input),
a sensor low-pass rounds the output exponentially, quadratic drag flattens the
fast part of the swing. Over all recorded cycles these shapes separate where
the closed-loop cycle does not (README, residual analysis).

Static input maps (bias, saturation, dead zone, thrust curve) turn the relay's
two levels into two other levels; with a free input offset (below) they are all a
gain change here, and their signature is in the closed-loop duty cycle and
amplitude instead. :func:`~mrft_gcs.residual.analysis.analyse_residual` therefore
uses this comparison only to choose among the effects that change the dynamics.

The model is simulated from rest one relay cycle before the compared span, and
its unknown initial state and a constant input offset are fitted by least squares
(regressors ``1``, ``t`` and ``exp(-t / T1)``: the integrator, an offset through
the integrator, the slow mode; the faster modes have died out by then).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mrft_gcs.plant import InnerModel
from mrft_gcs.residual.cycles import noise_std, rising_switches
from mrft_gcs.residual.effects import Knobs
from mrft_gcs.residual.simulate import simulate_input

__all__ = ["InputWindow", "input_window", "input_rms"]


@dataclass(frozen=True)
class InputWindow:
    """The recorded span an input-driven comparison uses.

    Attributes
    ----------
    dt : float
        Sample time (s).
    u, y : arrays (m,)
        Commands and measurements from the start of the lead-in cycle to the last rising switch.
    start : int
        Index in ``u``, ``y`` where the comparison starts (after the lead-in cycle).
    amplitude : float
        Half peak-to-peak of the compared measurement (output units).
    noise : float
        White measurement noise over ``amplitude`` (robust estimate).
    """

    dt: float
    u: np.ndarray
    y: np.ndarray
    start: int
    amplitude: float
    noise: float

    @property
    def samples(self) -> int:
        """Samples compared."""
        return self.y.size - self.start


def input_window(u: np.ndarray, y: np.ndarray, dt: float, *, max_cycles: int = 24,
                 lead_cycles: int = 1) -> InputWindow | None:
    """The last ``max_cycles`` whole relay cycles after ``lead_cycles`` of lead-in.

    The cycles need not be steady: the model is driven by what was sent. ``None``
    when the record holds fewer than ``lead_cycles + 1`` whole cycles.
    """
    r = rising_switches(u)
    if r.size < lead_cycles + 2:
        return None
    first = max(0, r.size - 1 - max_cycles - lead_cycles)
    s0, s, e = int(r[first]), int(r[first + lead_cycles]), int(r[-1])
    yw = np.asarray(y[s0:e], dtype=float)
    amp = float(0.5 * np.ptp(yw[s - s0:]))
    if not amp > 0:
        return None
    return InputWindow(dt, np.asarray(u[s0:e], dtype=float), yw, s - s0, amp,
                       noise_std(yw) / amp)


def input_rms(model: InnerModel, win: InputWindow, knobs: Knobs) -> np.ndarray:
    """RMS of measured minus simulated output over the compared span, per candidate, ``(n,)``.

    Normalised by the measured amplitude; the initial state and a constant input
    offset are fitted per candidate (least squares, see module docstring).
    """
    Y = simulate_input(model, win.u, knobs, win.dt)[:, win.start:]
    t = np.arange(win.u.size)[win.start:] * win.dt
    T1 = max(float(model.T1), win.dt)
    A = np.stack([np.ones_like(t), t - t[0], np.exp(-(t - t[0]) / T1)], axis=1)
    R = win.y[None, win.start:] - Y
    coef, *_ = np.linalg.lstsq(A, R.T, rcond=None)
    R = R - (A @ coef).T
    return np.sqrt(np.mean(R * R, axis=1)) / win.amplitude
