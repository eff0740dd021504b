"""The tuning sequence's phases, one room each; :class:`~mrft_gcs.flight.sequence.TuningSequence`
composes them and calls them on every tick.

========================  ===============================================================
module                    holds
========================  ===============================================================
:mod:`.state`             ``Phase``, ``LoopState``, ``LoopTest`` (one loop's test),
                          ``CycleSnapshot`` (the cycles handed to identification)
:mod:`.shared`            ``Shared``: settings, per-loop tests, events, the take-off
                          controller, ground noise, filtered position; the relay
                          supervision every loop shares (run-away, amplitude raise)
:mod:`.liftoff`           ``LiftoffDetector``: when the attitude relays may start
:mod:`.altitude`          ``AltitudeRelay``: the climb's relay, lopsided-cycle restart, PD
:mod:`.attitude`          ``AttitudeRelays``: roll/pitch relays, their sizing, the catch
:mod:`.side`              ``SideRelays``: bounding relay, settling, x/y relays, PDs
========================  ===============================================================

The phases talk only through :class:`~.shared.Shared`; none imports the sequence.
"""

from mrft_gcs.flight.phases.altitude import AltitudeRelay
from mrft_gcs.flight.phases.attitude import AttitudeRelays
from mrft_gcs.flight.phases.liftoff import LiftoffDetector
from mrft_gcs.flight.phases.shared import Shared
from mrft_gcs.flight.phases.side import SideRelays
from mrft_gcs.flight.phases.state import CycleSnapshot, LoopState, LoopTest, Phase

__all__ = [
    "Phase",
    "LoopState",
    "LoopTest",
    "CycleSnapshot",
    "Shared",
    "LiftoffDetector",
    "AltitudeRelay",
    "AttitudeRelays",
    "SideRelays",
]
