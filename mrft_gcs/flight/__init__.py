"""Live flight: take-off controller, tuning sequence, safety, GCS-side loops, report, plot.

``tune(connection, profile=...) -> TuneResult`` (:mod:`mrft_gcs.flight.api`) is the
Python API behind ``mrft-tune tune`` and ``mrft-tune demo``.
"""

from mrft_gcs.flight.api import LoopResult, TuneResult, tune
from mrft_gcs.flight.controllers import FlightState, PDLoop, YawHold
from mrft_gcs.flight.safety import LimitExceeded, SafetyMonitor
from mrft_gcs.flight.sequence import LoopState, Phase, SequenceConfig, TuningSequence
from mrft_gcs.flight.takeoff import TABLE_V, TakeoffController, TakeoffSettings

__all__ = [
    "tune",
    "TuneResult",
    "LoopResult",
    "FlightState",
    "PDLoop",
    "YawHold",
    "LimitExceeded",
    "SafetyMonitor",
    "LoopState",
    "Phase",
    "SequenceConfig",
    "TuningSequence",
    "TABLE_V",
    "TakeoffController",
    "TakeoffSettings",
]
