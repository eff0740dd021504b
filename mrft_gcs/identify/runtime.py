"""Runtime identification with the bundled ONNX classifiers (filled in by the classifier work)."""

from __future__ import annotations

from mrft_gcs.errors import IdentificationError

__all__ = ["identify", "relay_settings"]


def _missing():
    return IdentificationError(
        "no bundled classifier models found in models/: regenerate them with "
        "'mrft-tune design train' (needs pip install -e '.[design]')"
    )


def relay_settings(kind, inner=None):
    raise _missing()


def identify(kind, t, u, y, *, beta, h, bias=0.0, inner=None):
    raise _missing()
