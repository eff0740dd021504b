"""``mrft-tune demo``: start the bundled SITL and tune it end to end."""

from __future__ import annotations

from mrft_gcs.cli import app
from mrft_gcs.errors import UsageError


@app.command()
def demo() -> None:
    """Start the bundled simulated vehicle (SITL) and tune it end to end over UDP.

    Example:  mrft-tune demo
    """
    raise UsageError(
        "the demo needs the bundled SITL and live tuning, which are not built yet in this "
        "version; meanwhile try 'mrft-tune design pd --K 2 --T-prop 0.05 --T1 0.5 --tau 0.01'"
    )
