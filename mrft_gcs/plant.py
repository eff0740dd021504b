"""Plant models of multirotor loops (paper eq. 1, 2, 8) and their responses.

Inner loops (roll, pitch, altitude)::

    G(s) = K e^{-tau s} / (s (T_prop s + 1) (T1 s + 1))

Side motion (x, y) is the closed inner loop, under the deployed PD with the
derivative on the measurement (``u = Kc e - Kd dy/dt``), in cascade with::

    G_side(s) = K_side e^{-tau_side s} / ((T2 s + 1) s)

so the attitude setpoint-to-position transfer function is
``T_inner(s) G_side(s)`` with ``T_inner = Kc G / (1 + (Kc + Kd s) G)``.

All functions are vectorised: model parameters may be arrays of shape ``(n,)``
and frequencies of shape ``(m,)``; responses are ``(n, m)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "InnerModel",
    "SideModel",
    "PD",
    "inner_response",
    "side_response",
    "closed_inner_response",
    "loop_response",
    "modal_form",
]


@dataclass(frozen=True)
class InnerModel:
    """``K e^{-tau s} / (s (T_prop s + 1)(T1 s + 1))``; times in s.

    ``K`` is in output units per input unit per second (rad/s per unit torque
    command for attitude; m/s per unit thrust command for altitude).
    """

    K: float
    T_prop: float
    T1: float
    tau: float

    @property
    def params(self) -> np.ndarray:
        """``(T_prop, T1, tau)``: the gain-free shape used by the domains."""
        return np.array([self.T_prop, self.T1, self.tau])

    def scaled(self, c: float) -> InnerModel:
        """The same process with time stretched by ``c`` (gain-normalised: K / c)."""
        return InnerModel(self.K / c, self.T_prop * c, self.T1 * c, self.tau * c)

    def as_dict(self) -> dict[str, float]:
        return {"K": self.K, "T_prop": self.T_prop, "T1": self.T1, "tau": self.tau}


@dataclass(frozen=True)
class SideModel:
    """``K e^{-tau s} / ((T2 s + 1) s)``: closed attitude loop's output (rad) to position (m)."""

    K: float
    T2: float
    tau: float

    def as_dict(self) -> dict[str, float]:
        return {"K": self.K, "T2": self.T2, "tau": self.tau}


@dataclass(frozen=True)
class PD:
    """The deployed PD ``u = Kc e - Kd dy/dt`` (derivative on the measurement)."""

    Kc: float
    Kd: float

    def for_gain(self, K: float) -> PD:
        """Gains for a plant of gain ``K`` from gains designed for ``K = 1``."""
        return PD(self.Kc / K, self.Kd / K)


def _col(x) -> np.ndarray:
    return np.asarray(x, dtype=float).reshape(-1, 1)


def inner_response(K, T_prop, T1, tau, w) -> np.ndarray:
    """Frequency response ``G(jw)`` of inner-loop models, shape ``(n, m)``.

    Examples
    --------
    >>> g = inner_response(1.0, 0.05, 0.5, 0.0, [1.0])
    >>> round(abs(g[0, 0]), 4)  # 1 / (1 * |0.05j+1| * |0.5j+1|)
    0.8934
    """
    s = 1j * np.asarray(w, dtype=float)[None, :]
    K, T_prop, T1, tau = map(_col, (K, T_prop, T1, tau))
    return K * np.exp(-tau * s) / (s * (T_prop * s + 1) * (T1 * s + 1))


def side_response(K, T2, tau, w) -> np.ndarray:
    """Frequency response of the side part ``K e^{-tau s}/((T2 s + 1) s)``, shape ``(n, m)``."""
    s = 1j * np.asarray(w, dtype=float)[None, :]
    K, T2, tau = map(_col, (K, T2, tau))
    return K * np.exp(-tau * s) / ((T2 * s + 1) * s)


def loop_response(Kc, Kd, G, w) -> np.ndarray:
    """Open-loop ``L = (Kc + Kd s) G`` given ``G(jw)`` of shape ``(n, m)``."""
    s = 1j * np.asarray(w, dtype=float)[None, :]
    return (_col(Kc) + _col(Kd) * s) * G


def closed_inner_response(Kc, Kd, G, w) -> np.ndarray:
    """Setpoint-to-output of the inner loop under the deployed PD: ``Kc G/(1+(Kc+Kd s)G)``."""
    return _col(Kc) * G / (1 + loop_response(Kc, Kd, G, w))


@dataclass(frozen=True)
class ModalForm:
    """Diagonal realisation ``z' = diag(lam) z + 1 u``, ``y = K (r . z)``.

    Arrays are ``(n, 3)`` for ``n`` processes; ``lam`` are the poles
    ``(0, -1/T_prop, -1/T1)`` and ``r`` the residues of
    ``1/(s (T_prop s + 1)(T1 s + 1))``.
    """

    lam: np.ndarray
    r: np.ndarray
    K: np.ndarray


def modal_form(K, T_prop, T1, rel_sep: float = 1e-4) -> ModalForm:
    """Modal realisation of ``K/(s (T_prop s + 1)(T1 s + 1))`` (no delay).

    When ``T_prop`` and ``T1`` coincide to within ``rel_sep`` the two poles are
    pulled apart by that relative amount (a change far below any measurable
    effect) so the realisation stays diagonal.
    """
    K = np.atleast_1d(np.asarray(K, dtype=float))
    a = np.atleast_1d(np.asarray(T_prop, dtype=float)).copy()
    b = np.atleast_1d(np.asarray(T1, dtype=float)).copy()
    a, b, K = np.broadcast_arrays(a, b, K)
    a, b = a.copy(), b.copy()
    close = np.abs(a - b) < rel_sep * np.maximum(a, b)
    a[close] *= 1 - rel_sep / 2
    b[close] *= 1 + rel_sep / 2
    p1, p2 = 1 / a, 1 / b
    lam = np.stack([np.zeros_like(p1), -p1, -p2], axis=1)
    r = np.stack([np.ones_like(p1), -p2 / (p2 - p1), p1 / (p2 - p1)], axis=1)
    return ModalForm(lam=lam, r=r, K=K.copy())
