"""``--plot FILE.png``: each loop's identified relay cycles (relay output and response).

matplotlib is imported only here, only when a plot is asked for.
"""

from __future__ import annotations

import os
from pathlib import Path

from mrft_gcs.errors import MissingDependency
from mrft_gcs.flight.api import TuneResult
from mrft_gcs.loops import Loop

__all__ = ["plot_cycles"]

_UNITS = {Loop.ROLL: ("torque", "rad"), Loop.PITCH: ("torque", "rad"),
          Loop.ALTITUDE: ("thrust", "m"), Loop.X: ("-pitch sp, rad", "m"),
          Loop.Y: ("roll sp, rad", "m")}


def plot_cycles(result: TuneResult, path: str | os.PathLike[str]) -> Path:
    """One panel per loop: ``u`` (left axis) and ``y`` (right axis) over the identified cycles."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as err:
        raise MissingDependency("--plot needs matplotlib: pip install matplotlib") from err
    fig, axes = plt.subplots(len(Loop), 1, figsize=(8, 2.2 * len(Loop)), constrained_layout=True)
    for ax, lp in zip(axes, Loop, strict=True):
        lr = result.loops.get(lp)
        u_unit, y_unit = _UNITS[lp]
        if lr is None or lr.cycles is None:
            ax.text(0.5, 0.5, f"{lp.value}: {lr.state if lr else 'not run'} "
                    f"{('- ' + lr.note) if lr and lr.note else ''}"[:110],
                    ha="center", va="center", transform=ax.transAxes, fontsize=8)
            ax.set_axis_off()
            continue
        t, u, y = lr.cycles
        t = t - t[0]
        ax.step(t, u, where="post", color="tab:blue", lw=1)
        ax.set_ylabel(f"u ({u_unit})", color="tab:blue")
        ax2 = ax.twinx()
        ax2.plot(t, y, color="tab:red", lw=1)
        ax2.set_ylabel(f"{lp.value} ({y_unit})", color="tab:red")
        g = lr.gains
        ax.set_title(f"{lp.value}: beta {lr.beta:.3g}, h {lr.h:.3g}, period {lr.period_s:.3f} s, "
                     f"amplitude {lr.amplitude:.3g}" + (f"; Kc {g.Kc:.3g}, Kd {g.Kd:.3g}"
                                                        if g else ""), fontsize=9)
    axes[-1].set_xlabel("time in the identified cycles (s)")
    p = Path(path)
    fig.savefig(p, dpi=110)
    plt.close(fig)
    return p
