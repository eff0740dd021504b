"""Figures of a tune and a dry-run (``--plot``): relay tests, predicted steps, Bode plots.

:mod:`.curves` computes what is drawn (pure numerics); :mod:`.figures` draws it with
matplotlib, imported only when a figure is made.
"""

from mrft_gcs.plots.curves import LoopCurves, loop_curves
from mrft_gcs.plots.figures import LoopPanel, plot_dry_run, plot_tune, render_panels

__all__ = ["LoopCurves", "loop_curves", "LoopPanel", "plot_dry_run", "plot_tune",
           "render_panels"]
