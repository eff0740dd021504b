"""Registers every command group on the app (one module per group)."""

from mrft_gcs.cli import demo, design, dryrun, fleet, params, sitl, tune, verify  # noqa: F401
