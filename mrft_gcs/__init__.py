"""mrft-gcs: identify and tune multirotor loops with MRFT + neural networks over MAVLink.

The numerical core is made of pure functions on numpy arrays returning frozen
dataclasses; see the modules :mod:`mrft_gcs.plant`, :mod:`mrft_gcs.simulate`,
:mod:`mrft_gcs.pd_design` and :mod:`mrft_gcs.discretize`.
"""

from mrft_gcs.errors import MrftError
from mrft_gcs.loops import Loop, LoopKind

__all__ = ["MrftError", "Loop", "LoopKind", "__version__"]
__version__ = "0.1.0"
