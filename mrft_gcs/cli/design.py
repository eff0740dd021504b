"""``mrft-tune design ...``: the offline pipeline behind ``models/``."""

from __future__ import annotations

import typer

from mrft_gcs.cli import app

design_app = typer.Typer(help="Offline design: optimal PD, discretisation, phases, zeta, classifiers.",
                         no_args_is_help=True)
app.add_typer(design_app, name="design")
