"""Training data for the inner-loop classifiers (paper section VI), from simulation only.

Processes are drawn log-uniformly from the whole domain (not only the
representatives), simulated under MRFT at the distinguishing phase with
random measurement noise and relay bias (up to ``h/2``), and labelled with the
representative shape whose region holds them. Each row also carries the joint
cost from its region's candidate to every representative, which the
cost-augmented soft-max (eq. 19) uses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mrft_gcs.design.discretize import Discretisation
from mrft_gcs.design.phase import hb_period
from mrft_gcs.domains import Domain
from mrft_gcs.features import N_POINTS, cycle_features
from mrft_gcs.simulate import simulate_mrft

__all__ = ["Dataset", "make_dataset", "NOISE_MAX", "BIAS_MAX"]

#: Largest measurement noise (standard deviation), as a fraction of the expected cycle
#: amplitude: EKF / motion-capture grade. With 2-3 % noise *and* a relay bias of 0.2 h or
#: more the relay test itself degenerates into a slow, large cycle (measured: J p90 ~ 280 %
#: over random attitude processes), whatever the classifier does.
NOISE_MAX = 0.01
#: Largest relay bias, as a fraction of ``h``. The paper trains with up to h/2, but an
#: MRFT with the distinguishing lead does not keep a proper cycle at that bias (see
#: :data:`mrft_gcs.design.phase.BETA_GRID`); 0.3 h is what the test survives, and live tuning
#: keeps the relay centred on the hover command.
BIAS_MAX = 0.3


@dataclass(frozen=True)
class Dataset:
    """Classifier rows.

    Attributes
    ----------
    x : array (n, N_POINTS + 2), float32
    label : array (n,)
        Representative shape index.
    J : array (n, S)
        Joint cost (%) of each row's region to each representative.
    params : array (n, 3)
        The true ``(T_prop, T1, tau)``.
    period_s, amplitude : arrays (n,)
        Measured cycle figures (``K = 1``, ``h = 1``).
    noise, bias : arrays (n,)
        The imperfections drawn.
    """

    x: np.ndarray
    label: np.ndarray
    J: np.ndarray
    params: np.ndarray
    period_s: np.ndarray
    amplitude: np.ndarray
    noise: np.ndarray
    bias: np.ndarray

    def __len__(self) -> int:
        return len(self.label)


def make_dataset(disc: Discretisation, domain: Domain, beta: float, unit_period: np.ndarray,
                 unit_amplitude: np.ndarray, n: int, seed: int, chunk: int = 800,
                 dt: float = 1e-3, progress=None) -> Dataset:
    """Simulate ``n`` labelled MRFT cycles of random processes of ``domain``.

    ``unit_period`` and ``unit_amplitude`` are the representatives' unit-scale
    cycle figures at ``beta`` (used to size each simulation and its noise).
    """
    rng = np.random.default_rng(seed)
    params = domain.sample_log_uniform(n, rng)
    label = disc.owner_of(params)
    cand = disc.nearest_candidate(np.column_stack([np.log(params[:, 0] / params[:, 1]),
                                                   np.log(params[:, 2] / params[:, 1])]))
    J = disc.cand_J[cand]
    scale = params[:, 1]  # T1 of a unit shape is 1
    # Each process's own describing-function period sizes its record (its region's
    # representative can be a good deal faster or slower).
    bias = rng.uniform(-BIAS_MAX, BIAS_MAX, n)
    # A biased relay lengthens the cycle: the slow half is driven by only h - |bias|.
    T_est = 1.15 / (1 - np.abs(bias)) * np.concatenate(
        [hb_period(params[i:i + 500], beta) for i in range(0, n, 500)])
    A_est = unit_amplitude[label] * scale
    noise = rng.uniform(0, NOISE_MAX, n) * A_est
    rows = np.zeros((n, N_POINTS + 2), np.float32)
    period = np.full(n, np.nan)
    amp = np.full(n, np.nan)
    ok = np.zeros(n, bool)
    order = np.argsort(T_est)  # similar durations together
    for start in range(0, n, chunk):
        idx = order[start:start + chunk]
        Tmax = float(T_est[idx].max())
        duration = 1.0 + 12 * Tmax
        run = simulate_mrft(1.0, params[idx, 0], params[idx, 1], params[idx, 2], beta=beta, h=1.0,
                            bias=bias[idx], noise_std=noise[idx], band=4 * noise[idx],
                            duration_s=duration, dt=dt, seed=int(rng.integers(2**31)),
                            keep_s=min(duration, 5.2 * Tmax + 0.05))
        t = run.t
        for j, i in enumerate(idx):
            try:
                f = cycle_features(t, run.u[j], run.y[j], setpoint=0.0)
            except Exception:  # noqa: BLE001 - a rare run without two cycles is dropped
                continue
            rows[i], period[i], amp[i], ok[i] = f.x, f.period_s, f.amplitude, True
        if progress:
            progress(min(start + chunk, n), n)
    return Dataset(rows[ok], label[ok], J[ok], params[ok], period[ok], amp[ok], noise[ok],
                   bias[ok])
