"""The colour of the measurement noise: a low-pass filter on the measurement leaves it there.

A first-order low-pass on the measurement is, for the relay cycle, one more lag pole:
an identification that fits the cycle absorbs it into its own lag and delay (the
identified model is plant and filter together), so the cycle left to compare shows
little. The sensor noise still tells: the filter acts on the noisy reading, so the
noise that reaches the log is coloured (correlated from sample to sample), where a
delay, an actuator lag, a rate limit or a bias leave it white.

:func:`noise_colour` high-passes the record with a cubic Savitzky-Golay residual
(11 samples: it removes the smooth relay cycle, keeps the noise above about a tenth
of the sample rate), subtracts what the same filter leaves of a noise-free reference
cycle (the model's), and compares the autocorrelation at lags 1-3 with that of white
noise through the same filter. Its first-order cutoff (from the AR(1) coefficient
that matches them) is rough below about a tenth of the sample rate: there the noise
left is mostly the filter's roll-off, whatever the corner.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["NoiseColour", "noise_colour", "WHITE_MARGIN"]

#: Lag-1 autocorrelation above white noise's (through the same high-pass) that counts as
#: coloured, at least; 3 standard errors of the estimate where the record is short. The
#: bundled SITL's attitude over a live link (fractional delays interpolated, clean
#: vehicle) sits 0.11-0.16 above white; a 30 Hz first-order filter at 250 Hz 0.22-0.25,
#: 12 Hz 0.3-0.6.
WHITE_MARGIN = 0.2

_W, _ORDER, _LAGS = 11, 3, 3


def _residual_filter() -> np.ndarray:
    k = np.arange(_W) - _W // 2
    A = np.vander(k, _ORDER + 1)
    h = -(A @ np.linalg.pinv(A))[_W // 2]
    h[_W // 2] += 1.0
    return h


_H = _residual_filter()


def _acov(r: np.ndarray) -> np.ndarray:
    r = r - r.mean()
    return np.array([np.dot(r[lag:], r[:r.size - lag]) / r.size for lag in range(_LAGS + 1)])


def _ar1_acf(phi: float) -> np.ndarray:
    """Autocorrelation at lags 1.._LAGS of AR(1) noise (coefficient ``phi``) after ``_H``."""
    m = np.arange(-(_W + _LAGS), _W + _LAGS + 1)
    g = phi ** np.abs(m)
    i, j = np.arange(_W)[:, None], np.arange(_W)[None, :]
    cov = [float(np.sum(_H[:, None] * _H[None, :] * g[lag + i - j + _W + _LAGS]))
           for lag in range(_LAGS + 1)]
    return np.asarray(cov[1:]) / cov[0]


_PHI = np.linspace(0.0, 0.98, 99)
_ACF = np.array([_ar1_acf(p) for p in _PHI])


@dataclass(frozen=True)
class NoiseColour:
    """How far the measurement noise is from white.

    Attributes
    ----------
    rho1, rho1_white : float
        Lag-1 autocorrelation of the high-passed noise, and white noise's.
    cutoff_hz : float
        Cutoff of the first-order low-pass that matches lags 1-3 (inf: white).
    noise, leak : float
        Standard deviation of the high-passed record, and of what the high-pass leaves
        of the noise-free reference (output units).
    coloured : bool
        ``rho1`` above white's by ``WHITE_MARGIN`` and 3 standard errors, with the noise
        at least twice the reference's leak.
    """

    rho1: float
    rho1_white: float
    cutoff_hz: float
    noise: float
    leak: float
    coloured: bool


def noise_colour(y: np.ndarray, dt: float, reference: np.ndarray | None = None
                 ) -> NoiseColour | None:
    """Colour of the noise in ``y`` sampled every ``dt`` s (None: under 4 windows of data).

    ``reference``: a noise-free record of the same kind of cycle (e.g. the model's under
    the same relay), whose high-pass leak is taken out of the estimate.
    """
    y = np.asarray(y, dtype=float)
    if y.size < 4 * _W:
        return None
    r = np.convolve(y, _H[::-1], mode="valid")
    c = _acov(r)
    leak = 0.0
    if reference is not None and np.asarray(reference).size >= 4 * _W:
        cl = _acov(np.convolve(np.asarray(reference, float), _H[::-1], mode="valid"))
        leak = float(np.sqrt(cl[0]))
        c = c - cl  # the cycle's leak and the noise are independent
    if not c[0] > 0:
        return NoiseColour(np.nan, float(_ACF[0, 0]), np.nan, 0.0, leak, False)
    acf = c[1:] / c[0]
    i = int(np.argmin(np.sum((_ACF - acf) ** 2, axis=1)))
    phi = float(_PHI[i])
    cutoff = -np.log(phi) / (2 * np.pi * dt) if phi > 0 else np.inf
    white = float(_ACF[0, 0])
    noise = float(np.sqrt(c[0]))
    margin = max(WHITE_MARGIN, 3.0 / np.sqrt(r.size))
    coloured = bool(acf[0] - white > margin and noise > 2.0 * leak)
    return NoiseColour(float(acf[0]), white, float(cutoff), noise, leak, coloured)
