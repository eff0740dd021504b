"""Residual analysis: does the model explain the measured relay cycle, and if not, why?

After each identification the model is simulated under the very relay that ran
(same ``beta``, ``h``, bias and sample time) and its steady cycle compared with
the measured one. A significant residual is traced to one effect of a library of
candidate unmodelled effects (:mod:`~mrft_gcs.residual.effects`), whose parameter
is fitted; the PD is re-designed with it. Entry point: :func:`analyse_residual`
-> :class:`ResidualReport` (``as_dict()`` is the ``residual`` field of README's report schema).
"""

from mrft_gcs.residual.analysis import (
    MIN_REDUCTION,
    RMS_FLOOR,
    CycleErrors,
    EffectFit,
    RelayTest,
    ResidualReport,
    analyse_residual,
)
from mrft_gcs.residual.cycles import CycleWave
from mrft_gcs.residual.effects import EFFECTS, Effect, candidate_effects, effect_by_name

__all__ = [
    "analyse_residual",
    "ResidualReport",
    "RelayTest",
    "EffectFit",
    "CycleErrors",
    "CycleWave",
    "Effect",
    "EFFECTS",
    "candidate_effects",
    "effect_by_name",
    "RMS_FLOOR",
    "MIN_REDUCTION",
]
