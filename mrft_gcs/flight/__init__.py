"""Live flight: take-off controller, tuning sequence, safety, GCS-side loops, report, plot.

Modules: ``takeoff`` (eq. 21 / climb at a known hover thrust), ``sequence`` (the state
machine), ``config`` (its settings), ``cycles`` (when a relay's cycles are steady; dry-run
runs it too), ``noise`` (noise bands, position smoothing), ``controllers`` (GCS PDs, yaw hold),
``onboard`` (identified gains re-targeted to the autopilot's own loops), ``safety``,
``scoring`` (J against a simulated airframe's true models), ``report``, ``plot``, ``api``.

``tune(connection, profile=...) -> TuneResult`` (:mod:`mrft_gcs.flight.api`) is the
Python API behind ``mrft-tune tune`` and ``mrft-tune demo``.
"""

from mrft_gcs.flight.api import LoopResult, TuneResult, tune
from mrft_gcs.flight.controllers import FlightState, PDLoop, YawHold
from mrft_gcs.flight.noise import ComplementaryFilter, NoiseEstimator
from mrft_gcs.flight.onboard import onboard_gains
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
    "ComplementaryFilter",
    "NoiseEstimator",
    "onboard_gains",
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
