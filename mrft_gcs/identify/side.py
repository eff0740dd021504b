"""What side-motion identification shares with the side classifiers' design.

The side plant is the closed attitude loop in cascade with ``K e^{-tau s}/((T2 s + 1) s)``;
the side classifiers were trained on :func:`side_features` of simulated cycles
(:mod:`mrft_gcs.design.side`), so the runtime computes them the same way here.
"""

from __future__ import annotations

import numpy as np

from mrft_gcs.features import CycleFeatures, cycle_features
from mrft_gcs.plant import closed_inner_response, inner_response, side_response

__all__ = ["SIDE_H", "side_plant_response", "side_features"]

#: Default side relay amplitude: tilt set point in rad (about 4.6 deg).
SIDE_H = 0.08


def side_plant_response(att: np.ndarray, att_pd: tuple[float, float], T2, tau, w) -> np.ndarray:
    """Closed unit attitude loop times the unit-gain side part, shape ``(n, m)``."""
    T_prop, T1, att_tau = att
    G = inner_response(1.0, T_prop, T1, att_tau, w)
    T = closed_inner_response(att_pd[0], att_pd[1], G, w)
    return T * side_response(1.0, T2, tau, w)


def side_features(t, u, y, att_scale: float, setpoint=None
                  ) -> tuple[CycleFeatures, np.ndarray]:
    """Inner features plus the log of the period over the attitude scale.

    Side motion is not scale-free, so the period relative to the attitude loop's time
    scale is a feature too.
    """
    f = cycle_features(t, u, y, setpoint=setpoint)
    return f, np.concatenate([f.x, [np.log(f.period_s / att_scale)]]).astype(np.float32)
