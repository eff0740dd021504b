"""``--plot FILE.png`` of a tune: kept for callers of :func:`plot_cycles`.

The figure itself (per loop the relay cycles, the predicted step response and the
open-loop Bode plot of the written gains with their margins) is drawn by
:func:`mrft_gcs.plots.plot_tune`; matplotlib is imported only when a plot is asked for.
"""

from __future__ import annotations

import os
from pathlib import Path

from mrft_gcs.flight.api import TuneResult

__all__ = ["plot_cycles"]


def plot_cycles(result: TuneResult, path: str | os.PathLike[str]) -> Path | None:
    """Write the tune's figure to ``path``; None (nothing written) if no loop ran."""
    from mrft_gcs.plots import plot_tune

    return plot_tune(result, path)
