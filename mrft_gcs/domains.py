"""Parameter domains of the models (paper Table I), as data.

The domains are boxes in model-parameter space. The gain ``K`` is not part of
a domain: identification is gain-normalised and the gain is recovered from
the oscillation amplitude (exact gain scaling).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mrft_gcs.loops import LoopKind

__all__ = ["Domain", "D_ATT", "D_ALT", "D_SIDE", "domain_for", "AIRFRAME_RANGES"]


@dataclass(frozen=True)
class Domain:
    """An axis-aligned box of model parameters.

    Attributes
    ----------
    name : str
        ``attitude``, ``altitude`` or ``side``.
    names : tuple of str
        Parameter names in order, e.g. ``("T_prop", "T1", "tau")``.
    low, high : tuple of float
        Bounds in seconds, same order as ``names``.
    """

    name: str
    names: tuple[str, ...]
    low: tuple[float, ...]
    high: tuple[float, ...]

    @property
    def lo(self) -> np.ndarray:
        return np.asarray(self.low, dtype=float)

    @property
    def hi(self) -> np.ndarray:
        return np.asarray(self.high, dtype=float)

    def contains(self, params: np.ndarray, rtol: float = 1e-9) -> np.ndarray:
        """Boolean mask of rows of ``params`` (shape ``(n, d)``) inside the box."""
        p = np.atleast_2d(params)
        return np.all((p >= self.lo * (1 - rtol)) & (p <= self.hi * (1 + rtol)), axis=1)

    def sample_log_uniform(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """``n`` points drawn log-uniformly in the box, shape ``(n, d)``."""
        u = rng.random((n, len(self.names)))
        return np.exp(np.log(self.lo) + u * (np.log(self.hi) - np.log(self.lo)))

    def vertices(self) -> np.ndarray:
        """The ``2**d`` corners of the box, shape ``(2**d, d)``."""
        d = len(self.names)
        idx = (np.arange(2**d)[:, None] >> np.arange(d)[None, :]) & 1
        return np.where(idx == 1, self.hi, self.lo)


D_ATT = Domain("attitude", ("T_prop", "T1", "tau"), (0.015, 0.2, 0.0005), (0.3, 2.0, 0.03))
D_ALT = Domain("altitude", ("T_prop", "T1", "tau"), (0.015, 0.2, 0.0005), (0.3, 2.0, 0.15))
D_SIDE = Domain("side", ("T2", "tau"), (0.2, 0.0005), (6.0, 0.15))

#: Airframe ranges of Table I (peak thrust-to-weight, motor-to-motor distance in m,
#: roll/pitch moment of inertia in kg m^2). Vehicle profiles are checked against them.
AIRFRAME_RANGES = {
    "thrust_to_weight": (1.5, 5.0),
    "motor_distance_m": (0.15, 1.5),
    "inertia_kg_m2": (1.6e-3, 2.25),
}


def domain_for(kind: LoopKind) -> Domain:
    """The parameter domain of a loop kind."""
    return {LoopKind.ATTITUDE: D_ATT, LoopKind.ALTITUDE: D_ALT, LoopKind.SIDE: D_SIDE}[kind]
