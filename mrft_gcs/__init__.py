"""mrft-gcs: identify and tune multirotor loops with MRFT + neural networks over MAVLink.

The numerical core is made of pure functions on numpy arrays returning frozen
dataclasses (:mod:`mrft_gcs.plant`, :mod:`mrft_gcs.simulate`,
:mod:`mrft_gcs.pd_design`); runtime identification
is :mod:`mrft_gcs.identify`; the offline design of the bundled classifiers is
:mod:`mrft_gcs.design` (never imported by the runtime). The scripting API, one function per
command::

    import mrft_gcs
    result = mrft_gcs.tune("udp:127.0.0.1:14540", "px4")       # mrft-tune tune
    fleet = mrft_gcs.tune_fleet("fleet.toml")                  # mrft-tune fleet
    check = mrft_gcs.verify_figure8("udp:127.0.0.1:14540")     # mrft-tune verify
    replay = mrft_gcs.dry_run("flight.tlog")                   # mrft-tune dry-run

These are imported on first use, so ``import mrft_gcs`` stays light.
"""

from mrft_gcs.errors import MrftError
from mrft_gcs.loops import Loop, LoopKind

__all__ = ["MrftError", "Loop", "LoopKind", "__version__", "tune", "tune_fleet",
           "verify_figure8", "dry_run"]
__version__ = "0.1.0"

_LAZY = {
    "tune": ("mrft_gcs.flight.api", "tune"),
    "tune_fleet": ("mrft_gcs.fleet", "tune_fleet"),
    "verify_figure8": ("mrft_gcs.verify", "verify_figure8"),
    "dry_run": ("mrft_gcs.dryrun", "dry_run"),
}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        module, attr = _LAZY[name]
        return getattr(importlib.import_module(module), attr)
    raise AttributeError(f"module 'mrft_gcs' has no attribute {name!r}")
