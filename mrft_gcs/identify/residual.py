"""The residual analysis of an identification, for the report's ``residual``."""

from __future__ import annotations

import dataclasses

from mrft_gcs.identify.result import Identification, ResidualSummary
from mrft_gcs.loops import LoopKind
from mrft_gcs.residual.analysis import RelayTest, analyse_residual

__all__ = ["attach_residual"]


def attach_residual(ident: Identification, t, u, y, *, bias: float = 0.0, band: float = 0.0,
                    hover: float = 0.5) -> Identification:
    """The identification with its residual analysis (the report's ``residual``).

    Simulates the identified model under the relay that ran and compares with the
    measured cycles (:func:`mrft_gcs.residual.analyse_residual`); takes a second or
    so, so call it after the tests, not inside the relay loop. Side-motion models
    are not analysed yet: their residual fields are NaN, with the reason in ``note``.
    """
    if ident.kind is LoopKind.SIDE:
        return dataclasses.replace(
            ident, residual=ResidualSummary(note="side-motion residuals not analysed"))
    try:
        rep = analyse_residual(ident.model, RelayTest(ident.beta, ident.h, bias), t, u, y,
                               kind=ident.kind, hover=hover, band=band)
    except Exception as exc:  # noqa: BLE001 - the tune stands; say why the residual is missing
        return dataclasses.replace(
            ident, residual=ResidualSummary(note=f"residual analysis failed: {exc}"))
    return dataclasses.replace(ident, residual=ResidualSummary(
        float(rep.rms_before), float(rep.rms_after), rep.effect,
        {str(k): float(v) for k, v in rep.effect_params.items()}))
