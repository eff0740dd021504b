"""Fixed-step simulation of relay tests on the plant models, vectorised over processes.

The plants are discretised exactly for a piecewise-constant input (zero-order
hold over each step ``dt``) in modal form, and the transport delay is exact
for any value, also a fraction of a step: over one step the delayed input is
``u[k-d-1]`` for the first ``eps`` seconds and ``u[k-d]`` for the rest, where
``tau = d dt + eps``. The relay samples the measurement once per step, as a
digital controller does.

Side motion is simulated as the full cascade: the attitude plant under its PD
(derivative on the measured rate), followed by the side dynamics. The side
dynamics are driven by the attitude, a continuous signal, which the hold
replaces by its staircase; that staircase lags by half a step on average, so
``dt/2`` is taken off the side delay to keep the cascade's total delay exact.

Main entry points: :func:`simulate_mrft`, :func:`simulate_side_mrft` (return a
:class:`RelayRun`) and :func:`find_cycle` (returns a :class:`Cycle`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mrft_gcs import _kernels
from mrft_gcs.plant import modal_form
from mrft_gcs.relay import MRFT

__all__ = [
    "RelayRun",
    "Cycle",
    "DelayedModal",
    "simulate_mrft",
    "simulate_side_mrft",
    "simulate_pd_step",
    "find_cycle",
    "find_cycles",
]


def _vec(x, n: int) -> np.ndarray:
    return np.ascontiguousarray(np.broadcast_to(np.asarray(x, dtype=float), (n,)))


def _broadcast(*args) -> list[np.ndarray]:
    """Broadcast scalars/arrays to a common ``(n,)`` shape, as contiguous float copies."""
    arrs = np.broadcast_arrays(*(np.atleast_1d(np.asarray(a, dtype=float)) for a in args))
    return [np.array(a, dtype=float, order="C") for a in arrs]


class DelayedModal:
    """Exact discrete-time stepping of ``K e^{-tau s} sum_i r_i / (s - lam_i)`` for ``n`` processes.

    Parameters
    ----------
    lam, r : arrays (n, k)
        Poles and residues of the delay-free part (real, distinct).
    K, tau : arrays (n,)
        Gain and delay (s).
    dt : float
        Step (s).
    """

    def __init__(self, lam, r, K, tau, dt: float) -> None:
        self.lam, self.r = np.asarray(lam, float), np.asarray(r, float)
        n = self.lam.shape[0]
        self.K, self.tau, self.dt, self.n = _vec(K, n), np.maximum(_vec(tau, n), 0.0), dt, n
        d = np.floor(self.tau / dt + 1e-9).astype(np.int64)
        eps = np.clip(self.tau - d * dt, 0.0, dt)[:, None]
        lam = self.lam
        self.Ad = np.exp(lam * dt)
        self.B0 = _phi(lam, dt - eps)  # weight of u[k-d]
        self.B1 = _phi(lam, dt) - self.B0  # weight of u[k-d-1]
        self.Kr = self.K[:, None] * self.r
        self.Krl = self.Kr * lam  # output derivative (no feed-through: sum r = 0)
        self.L = int(d.max()) + 2
        self.i0 = d
        self.rows = np.arange(n)
        self.reset()

    def reset(self) -> None:
        self.z = np.zeros_like(self.lam)
        self.buf = np.zeros((self.n, self.L))
        self.k = 0

    def output(self) -> np.ndarray:
        """Output at the current sample, shape ``(n,)``."""
        return np.einsum("ij,ij->i", self.Kr, self.z)

    def derivative(self) -> np.ndarray:
        """Output derivative at the current sample (exact, as a rate gyro sees it)."""
        return np.einsum("ij,ij->i", self.Krl, self.z)

    def step(self, u: np.ndarray) -> None:
        """Advance one step with input ``u`` (held over the step)."""
        L, k = self.L, self.k
        self.buf[:, k % L] = u
        u0 = self.buf[self.rows, (k - self.i0) % L]
        u1 = self.buf[self.rows, (k - self.i0 - 1) % L]
        self.z = self.Ad * self.z + self.B0 * u0[:, None] + self.B1 * u1[:, None]
        self.k = k + 1


def _phi(lam: np.ndarray, T) -> np.ndarray:
    """``int_0^T exp(lam s) ds`` elementwise (``T`` where ``lam == 0``)."""
    T = np.broadcast_to(np.asarray(T, dtype=float), lam.shape)
    small = np.abs(lam * T) < 1e-8
    safe = np.where(small, 1.0, lam)
    return np.where(small, T * (1 + lam * T / 2), np.expm1(lam * T) / safe)


def inner_plant(K, T_prop, T1, tau, dt: float) -> DelayedModal:
    """Stepper for ``K e^{-tau s}/(s (T_prop s + 1)(T1 s + 1))``."""
    m = modal_form(K, T_prop, T1)
    return DelayedModal(m.lam, m.r, m.K, tau, dt)


def side_plant(K, T2, tau, dt: float) -> DelayedModal:
    """Stepper for ``K e^{-tau s}/(s (T2 s + 1))`` driven by a sampled continuous signal."""
    T2 = np.atleast_1d(np.asarray(T2, dtype=float))
    n = T2.size
    lam = np.stack([np.zeros(n), -1 / T2], axis=1)
    r = np.stack([np.ones(n), -np.ones(n)], axis=1)
    return DelayedModal(lam, r, _vec(K, n), np.maximum(_vec(tau, n) - dt / 2, 0.0), dt)


@dataclass(frozen=True)
class RelayRun:
    """Time series of relay tests on ``n`` processes.

    Attributes
    ----------
    dt : float
        Sample time (s).
    t0 : float
        Time of the first kept sample (s).
    u : array (n, m)
        Relay output, including the bias, applied from each sample on.
    y : array (n, m)
        Measured process variable at each sample (with noise).
    beta, h, bias : arrays (n,)
        Relay settings of each process.
    """

    dt: float
    t0: float
    u: np.ndarray
    y: np.ndarray
    beta: np.ndarray
    h: np.ndarray
    bias: np.ndarray

    @property
    def t(self) -> np.ndarray:
        return self.t0 + self.dt * np.arange(self.u.shape[1])

    def __len__(self) -> int:
        return self.u.shape[0]


_TABLE_BITS = 12


class NoiseSource:
    """White Gaussian measurement noise, reproducible from a seed, for ``n`` processes.

    Each process draws from a shared table of 4096 standard normal values (it
    stays in the first-level cache), indexed by its own 64-bit linear
    congruential generator; the compiled kernels use the very same scheme, so a
    seed gives the same record on either path.
    """

    def __init__(self, n: int, seed) -> None:
        rng = np.random.default_rng(seed)
        self.table = rng.standard_normal(2**_TABLE_BITS)
        self.table /= self.table.std()  # exactly unit variance
        self.state = rng.integers(-(2**63), 2**63 - 1, size=n, dtype=np.int64)
        self.mask = 2**_TABLE_BITS - 1

    def draw(self) -> np.ndarray:
        with np.errstate(over="ignore"):
            s = self.state.view(np.uint64) * np.uint64(_kernels.LCG_A) + np.uint64(_kernels.LCG_C)
        self.state = s.view(np.int64)
        return self.table[(self.state >> 40) & self.mask]


def _steps(duration_s: float, keep_s, dt: float) -> tuple[int, int]:
    steps = int(round(duration_s / dt))
    return steps, steps if keep_s is None else min(steps, int(round(keep_s / dt)))


def _use_kernel(engine: str) -> bool:
    if engine not in ("auto", "numba", "numpy"):
        raise ValueError("engine must be 'auto', 'numba' or 'numpy'")
    if engine == "numba" and not _kernels.AVAILABLE:
        raise ImportError("numba is not installed: pip install -e '.[design]'")
    return engine != "numpy" and _kernels.AVAILABLE


def _run_relay(plant_step, n: int, beta, h, bias, noise_std, duration_s, dt, seed, keep_s,
               band) -> RelayRun:
    steps, keep = _steps(duration_s, keep_s, dt)
    source = NoiseSource(n, seed)
    noise = _vec(noise_std, n)
    relay = MRFT(_vec(beta, n), _vec(h, n), _vec(bias, n), _vec(band, n))
    U = np.empty((n, keep))
    Y = np.empty((n, keep))
    y = plant_step(None)
    start = steps - keep
    noisy = bool(noise.any())
    for k in range(steps):
        y_meas = y + noise * source.draw() if noisy else y
        u = relay.step(-y_meas)  # set point 0: e = -y
        if k >= start:
            U[:, k - start] = u
            Y[:, k - start] = y_meas
        y = plant_step(u)
    return RelayRun(dt, start * dt, U, Y, relay.beta, relay.h, relay.bias)


def simulate_mrft(K, T_prop, T1, tau, beta, h, *, bias=0.0, noise_std=0.0, duration_s=10.0,
                  dt=1e-3, seed=None, keep_s=None, band=0.0, engine="auto") -> RelayRun:
    """MRFT on inner-loop plants ``K e^{-tau s}/(s(T_prop s+1)(T1 s+1))``, set point 0.

    Parameters are scalars or arrays of shape ``(n,)`` (broadcast together).
    ``noise_std`` is white measurement noise (output units); ``keep_s`` keeps
    only the last seconds of the record (memory for large batches). ``engine``
    picks the compiled kernel (``numba``), the numpy reference (``numpy``), or
    the kernel when numba is installed (``auto``); both give the same record.

    Examples
    --------
    >>> run = simulate_mrft(1.0, 0.05, 0.5, 0.01, beta=0.0, h=1.0, duration_s=5.0)
    >>> c = find_cycle(run.u[0], run.y[0], run.dt)
    >>> round(c.period_s, 2)
    0.75
    """
    K, T_prop, T1, tau, beta, h, bias = _broadcast(K, T_prop, T1, tau, beta, h, bias)
    n = K.size
    plant = inner_plant(K, T_prop, T1, tau, dt)
    if _use_kernel(engine):
        steps, keep = _steps(duration_s, keep_s, dt)
        src = NoiseSource(n, seed)
        U, Y = np.empty((n, keep)), np.empty((n, keep))
        band_, noise_ = _vec(band, n), _vec(noise_std, n)
        _kernels.inner_mrft(plant.Ad, plant.B0, plant.B1, plant.Kr, plant.i0, beta, h, bias,
                            band_, noise_, src.state, src.table, steps, keep, U, Y)
        return RelayRun(dt, (steps - keep) * dt, U, Y, beta.copy(), h.copy(), bias.copy())

    def step(u):
        if u is not None:
            plant.step(u)
        return plant.output()

    return _run_relay(step, n, beta, h, bias, noise_std, duration_s, dt, seed, keep_s, band)


def simulate_side_mrft(inner, pd, side, beta, h, *, bias=0.0, noise_std=0.0, duration_s=20.0,
                       dt=1e-3, seed=None, keep_s=None, band=0.0, engine="auto") -> RelayRun:
    """MRFT on the side-motion cascade: relay -> attitude set point -> PD -> attitude -> position.

    Parameters
    ----------
    inner : tuple of arrays (K, T_prop, T1, tau)
        Attitude plant(s).
    pd : tuple of arrays (Kc, Kd)
        The attitude PD in use (``u = Kc (r - y) - Kd dy/dt``).
    side : tuple of arrays (K, T2, tau)
        Side dynamics ``K e^{-tau s}/((T2 s + 1) s)``.
    """
    Ka, Tp, T1, ta, Kc, Kd, Ks, T2, ts, beta, h, bias = _broadcast(*inner, *pd, *side, beta, h,
                                                                    bias)
    n = Ka.size
    att = inner_plant(Ka, Tp, T1, ta, dt)
    pos = side_plant(Ks, T2, ts, dt)
    if _use_kernel(engine):
        steps, keep = _steps(duration_s, keep_s, dt)
        src = NoiseSource(n, seed)
        U, Y = np.empty((n, keep)), np.empty((n, keep))
        _kernels.side_mrft(att.Ad, att.B0, att.B1, att.Kr, att.Krl, att.i0, Kc, Kd, pos.Ad,
                           pos.B0, pos.B1, pos.Kr, pos.i0, beta, h, bias, _vec(band, n),
                           _vec(noise_std, n), src.state, src.table, steps, keep, U, Y)
        return RelayRun(dt, (steps - keep) * dt, U, Y, beta.copy(), h.copy(), bias.copy())

    def step(ref):
        if ref is not None:
            # Inner loop runs at the same rate: PD on the attitude, then the side part is
            # driven by the attitude over the step.
            theta = att.output()
            u_att = Kc * (ref - theta) - Kd * att.derivative()
            pos.step(theta)
            att.step(u_att)
        return pos.output()

    return _run_relay(step, n, beta, h, bias, noise_std, duration_s, dt, seed, keep_s, band)


def simulate_pd_step(K, T_prop, T1, tau, Kc, Kd, *, duration_s=10.0, dt=1e-3) -> np.ndarray:
    """Unit-step response of the inner plant under the deployed PD; ``y`` of shape (n, m)."""
    K, T_prop, T1, tau, Kc, Kd = _broadcast(K, T_prop, T1, tau, Kc, Kd)
    plant = inner_plant(K, T_prop, T1, tau, dt)
    steps = int(round(duration_s / dt))
    Y = np.empty((K.size, steps))
    for k in range(steps):
        y = plant.output()
        Y[:, k] = y
        plant.step(Kc * (1.0 - y) - Kd * plant.derivative())
    return Y


@dataclass(frozen=True)
class Cycle:
    """One steady relay cycle.

    Attributes
    ----------
    start, stop : int
        Sample indices of the cycle (rising relay switch to the next one).
    period_s : float
        Mean of the last ``n_periods`` periods.
    amplitude : float
        Half the peak-to-peak process variable over the cycle.
    offset : float
        Mean process variable over the cycle.
    duty : float
        Fraction of the cycle the relay was high.
    spread : float
        Relative spread (max - min) / mean of the last periods: steadiness.
    steady : bool
        ``spread`` within the tolerance.
    """

    start: int
    stop: int
    period_s: float
    amplitude: float
    offset: float
    duty: float
    spread: float
    steady: bool


def find_cycle(u: np.ndarray, y: np.ndarray, dt: float, n_periods: int = 3,
               tol: float = 0.02) -> Cycle | None:
    """The last full relay cycle of one record, or ``None`` if fewer than two exist.

    Cycles are delimited by the relay's rising switches (low to high).
    """
    u = np.asarray(u, float)
    mid = 0.5 * (u.max() + u.min())
    high = u > mid
    rises = np.flatnonzero(~high[:-1] & high[1:]) + 1
    if rises.size < 2:
        return None
    periods = np.diff(rises) * dt
    last = periods[-n_periods:]
    spread = float((last.max() - last.min()) / last.mean())
    a, b = int(rises[-2]), int(rises[-1])
    seg = np.asarray(y[a:b], float)
    return Cycle(
        start=a,
        stop=b,
        period_s=float(last[-2:].mean()) if last.size > 1 else float(last[-1]),
        amplitude=float(0.5 * (seg.max() - seg.min())),
        offset=float(seg.mean()),
        duty=float(high[a:b].mean()),
        spread=spread,
        steady=bool(len(last) >= min(n_periods, 2) and spread <= tol),
    )


def find_cycles(run: RelayRun, n_periods: int = 3, tol: float = 0.02) -> list[Cycle | None]:
    """:func:`find_cycle` for every process of a run."""
    return [find_cycle(run.u[i], run.y[i], run.dt, n_periods, tol) for i in range(len(run))]
