"""Relay tests on a linear inner-loop model with candidate effects switched on, batched.

One call simulates ``n`` candidates (the same model and relay, different effect
settings in :class:`~mrft_gcs.residual.effects.Knobs`) in lock-step with numpy,
under the very relay that ran: :class:`mrft_gcs.relay.MRFT` with the test's
``beta``, ``h``, ``bias``, sampling the measurement once per sample time ``dt``.

The plant ``K e^{-tau s}/(s (T_prop s + 1)(T1 s + 1))`` is stepped exactly for
an input held over each step (zero-order hold), with the states
``(m, v, y, y_f)``: motor lag output, output rate, output and low-pass filtered
output. The transport delay (model's plus any extra) is exact also for a
fraction of a step, as in :class:`mrft_gcs.simulate.DelayedModal`: over one
step the delayed input is the older sample for the first ``eps`` seconds and the
newer one for the rest. Static input maps (bias, dead zone, saturation, thrust
curve) and the rate limit act on the held input, once per step; quadratic drag
is added to the rate state explicitly (it is small over one step).

:func:`simulate_input` steps the same plant open loop, driven by a recorded
relay output instead of the relay: the input-driven comparison of
:mod:`~mrft_gcs.residual.openloop`. Fed the commands a closed-loop run recorded,
it gives that run's output back exactly (test).
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import expm

from mrft_gcs.plant import InnerModel
from mrft_gcs.relay import MRFT
from mrft_gcs.residual.effects import Knobs
from mrft_gcs.simulate import RelayRun

__all__ = ["simulate_effects", "simulate_input", "effective_input", "input_sequence"]


def effective_input(u: np.ndarray, knobs: Knobs) -> np.ndarray:
    """The static input maps of ``knobs`` applied to commands ``u`` (shape ``(n,)``).

    Order: bias, dead zone, saturation, thrust curve (as the SITL applies them).
    ``u`` may also be ``(n, m)``: ``m`` commands of each candidate.
    """
    col = (slice(None),) + (None,) * (np.ndim(u) - 1)
    w = u + knobs.bias[col]
    dz = knobs.deadzone[col]
    w = np.where(dz > 0, np.sign(w) * np.maximum(np.abs(w) - dz, 0.0), w)
    w = np.clip(w, knobs.u_min[col], knobs.u_max[col])
    a = knobs.curve_a[col]
    if np.any(a > 0):
        F = knobs.curve_hover[col]
        safe = np.where(a > 0, a, 1.0)
        c_h = np.where(a > 0, (-(1 - a) + np.sqrt((1 - a) ** 2 + 4 * a * F)) / (2 * safe), F)
        c = c_h + w
        w = np.where(a > 0, (1 - a) * c + a * c * c - F, w)
    return w


def _slew(w0: np.ndarray, target: np.ndarray, rate: np.ndarray, dt: float) -> np.ndarray:
    """Mean over one step of a ramp from ``w0`` towards ``target`` at ``rate`` (held value).

    Holding the ramp's mean keeps the rate limiter's lag right to first order
    without sub-steps.
    """
    d = target - w0
    with np.errstate(divide="ignore", invalid="ignore"):
        tr = np.where(np.isfinite(rate), np.abs(d) / rate, 0.0)
    tr = np.minimum(tr, dt)
    ramp_end = w0 + np.sign(d) * np.where(np.isfinite(rate), rate, 0.0) * tr
    # ramp part (mean of w0 .. ramp_end over tr) then held at ramp_end for the rest
    held = ((w0 + ramp_end) / 2 * tr + ramp_end * (dt - tr)) / dt
    return np.where(np.isfinite(rate), held, target)


def input_sequence(u: np.ndarray, knobs: Knobs, dt: float) -> np.ndarray:
    """What the plant receives, ``(n, m)``, when commands ``u`` ``(m,)`` are sent to each candidate.

    The static maps of :func:`effective_input`, then the rate limit (held ramp means,
    as :func:`simulate_effects` steps it); no delay (the plant applies it).
    """
    u = np.asarray(u, dtype=float)
    w = effective_input(np.broadcast_to(u, (knobs.n, u.size)), knobs)
    if not np.any(np.isfinite(knobs.rate)):
        return w
    out = np.empty_like(w)
    max_step = knobs.rate * dt
    prev = np.zeros(knobs.n)
    for k in range(u.size):
        out[:, k] = _slew(prev, w[:, k], knobs.rate, dt)
        prev = prev + np.clip(w[:, k] - prev, -max_step, max_step)
    return out


def simulate_input(model: InnerModel, u: np.ndarray, knobs: Knobs, dt: float) -> np.ndarray:
    """Output ``(n, m)`` of ``model`` with each candidate's effects, driven by commands ``u``.

    Open loop from rest (zero state, empty delay line): ``u[k]`` is held over step
    ``k`` and ``y[:, k]`` is the (filtered) output sampled at its start, as a relay
    record pairs them.
    """
    n = knobs.n
    Ad, b_new, b_old, d, out = _matrices(model, knobs, dt)
    w = input_sequence(u, knobs, dt)
    m = w.shape[1]
    pad = np.concatenate([np.zeros((n, int(d.max()) + 1)), w], axis=1)
    k = np.arange(m)[None, :] + int(d.max()) + 1 - d[:, None]
    w0 = np.take_along_axis(pad, k, axis=1)
    w1 = np.take_along_axis(pad, k - 1, axis=1)
    forced = b_new[:, :, None] * w0[:, None, :] + b_old[:, :, None] * w1[:, None, :]
    rows = np.arange(n)
    drag_on = bool(np.any(knobs.drag > 0))
    x = np.zeros((n, 4))
    Y = np.empty((n, m))
    for j in range(m):
        Y[:, j] = x[rows, out]
        x = np.einsum("nij,nj->ni", Ad, x) + forced[:, :, j]
        if drag_on:
            v = x[:, 1]
            x[:, 1] = v - dt * knobs.drag * np.abs(v) * v
    return Y


def _matrices(model: InnerModel, knobs: Knobs, dt: float):
    n = knobs.n
    Tp = max(float(model.T_prop), 1e-5)
    T1 = max(float(model.T1), 1e-5)
    lpf_on = knobs.lpf_tau_s > 0
    Tf = np.where(lpf_on, knobs.lpf_tau_s, 1.0)
    M = np.zeros((n, 5, 5))
    M[:, 0, 0] = -1 / Tp
    M[:, 0, 4] = 1 / Tp
    M[:, 1, 0] = model.K / T1
    M[:, 1, 1] = -1 / T1
    M[:, 2, 1] = 1.0
    M[:, 3, 2] = 1 / Tf
    M[:, 3, 3] = -1 / Tf
    tau = np.maximum(float(model.tau) + knobs.delay_s, 0.0)
    d = np.floor(tau / dt + 1e-9).astype(np.int64)
    eps = np.clip(tau - d * dt, 0.0, dt)
    # Candidates differ only in the filter and the delay fraction: one expm per distinct pair.
    keys = np.stack([Tf, eps], axis=1)
    uniq, inv = np.unique(keys, axis=0, return_inverse=True)
    first = np.array([np.flatnonzero(inv.ravel() == i)[0] for i in range(len(uniq))])
    E_full = expm(M[first] * dt)[inv.ravel()]
    E_part = expm(M[first] * (dt - eps[first])[:, None, None])[inv.ravel()]
    Ad = E_full[:, :4, :4]
    b_new = E_part[:, :4, 4]
    b_old = E_full[:, :4, 4] - b_new
    return Ad, b_new, b_old, d, np.where(lpf_on, 3, 2)


def simulate_effects(model: InnerModel, beta: float, h: float, knobs: Knobs, *, bias: float = 0.0,
                     dt: float = 0.004, duration_s: float = 10.0, keep_s: float | None = None,
                     band: float = 0.0) -> RelayRun:
    """MRFT on ``model`` with each candidate's effects, set point 0.

    Parameters
    ----------
    model : InnerModel
        The linear model (attitude or altitude loop).
    beta, h, bias : float
        The relay that ran (input units for ``h`` and ``bias``).
    knobs : Knobs
        Effect settings of the ``n`` candidates.
    dt : float
        Relay sample time (s); also the simulation step.
    duration_s, keep_s : float
        Simulated time, and the last seconds kept in the result.

    Returns
    -------
    RelayRun
        ``u``: the relay output as commanded (what a log records), ``y``: the measured
        output (after the sensor filter), both ``(n, m)``.
    """
    n = knobs.n
    Ad, b_new, b_old, d, out = _matrices(model, knobs, dt)
    steps = int(round(duration_s / dt))
    keep = steps if keep_s is None else min(steps, int(round(keep_s / dt)))
    start = steps - keep
    L = int(d.max()) + 2
    buf = np.zeros((n, L))
    rows = np.arange(n)
    x = np.zeros((n, 4))
    relay = MRFT(np.full(n, beta), np.full(n, h), np.full(n, bias), np.full(n, band))
    rate_on = bool(np.any(np.isfinite(knobs.rate)))
    max_step = knobs.rate * dt
    drag_on = bool(np.any(knobs.drag > 0))
    w_prev = np.zeros(n)
    U = np.empty((n, keep))
    Y = np.empty((n, keep))
    for k in range(steps):
        y = x[rows, out]
        u = relay.step(-y)
        if k >= start:
            U[:, k - start] = u
            Y[:, k - start] = y
        w = effective_input(u, knobs)
        if rate_on:
            w, w_prev = _slew(w_prev, w, knobs.rate, dt), w_prev + np.clip(w - w_prev, -max_step,
                                                                             max_step)
        buf[:, k % L] = w
        w0 = buf[rows, (k - d) % L]
        w1 = buf[rows, (k - d - 1) % L]
        x = np.einsum("nij,nj->ni", Ad, x) + b_new * w0[:, None] + b_old * w1[:, None]
        if drag_on:
            v = x[:, 1]
            x[:, 1] = v - dt * knobs.drag * np.abs(v) * v
    return RelayRun(dt, start * dt, U, Y, relay.beta, relay.h, relay.bias)
