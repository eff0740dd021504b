"""The one exception family of mrft-gcs.

Library code never prints or exits: it raises a subclass of :class:`MrftError`
whose message says what went wrong *and what to do*. The CLI turns it into a
one-line message and the class's ``exit_code`` in exactly one place
(:func:`mrft_gcs.cli.main`).

Exit codes (documented in README):

====  ==========================================================
0     success
1     unexpected internal error (a bug: please report it)
2     bad usage or bad input file (profile, fleet file, log)
3     link problem: wrong connection string, silent vehicle
4     parameter write failed (rolled back where possible), or the written
      gains held worse than the old ones and were reverted
5     safety abort (limit hit, telemetry lost, Ctrl-C): landed
6     identification failed (no steady oscillation, no relay test)
7     missing optional dependency (install the named extra)
8     some vehicles of a fleet failed
130   interrupted, or a take-off / write question answered no
====  ==========================================================
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # for the annotation only: the flight package builds on this module
    from mrft_gcs.flight.api import TuneResult

__all__ = [
    "MrftError",
    "UsageError",
    "InputFileError",
    "LinkError",
    "ParameterError",
    "GainsReverted",
    "SafetyAbort",
    "IdentificationError",
    "SetpointNotCrossed",
    "CyclesTooSmall",
    "MissingDependency",
    "FleetError",
]


class MrftError(Exception):
    """Base class: a failure the user can act on. ``str(err)`` is one line.

    Attributes
    ----------
    exit_code : int
        The CLI's exit code for this class of failure (table above).
    partial_result : TuneResult or None
        Set by :func:`mrft_gcs.flight.api.tune` on a failure after it connected: what
        the tune did so far (its report is written from it); None otherwise.
    """

    exit_code: int = 1
    partial_result: TuneResult | None = None

    def __init__(self, message: str) -> None:
        super().__init__(" ".join(message.split()))


class UsageError(MrftError):
    """Bad arguments or a bad configuration file (profile, fleet, vehicle)."""

    exit_code = 2


class InputFileError(MrftError):
    """A log or data file that is missing, malformed, truncated or empty."""

    exit_code = 2


class LinkError(MrftError):
    """Wrong connection string, vehicle that never answers, link too slow."""

    exit_code = 3


class ParameterError(MrftError):
    """A parameter that could not be written or did not read back."""

    exit_code = 4


class GainsReverted(ParameterError):
    """The written gains held worse in the autopilot's own hold mode than the values they
    replaced: those values were written back (read back) and the vehicle holds on them."""


class SafetyAbort(MrftError):
    """A safety limit, telemetry loss or Ctrl-C ended the test; landing was commanded."""

    exit_code = 5


class PilotTookOver(SafetyAbort):
    """The flight mode left the tool's offboard mode (an RC take-over or a firmware failsafe):
    streaming stopped, nothing written, and no landing commanded (the pilot has the vehicle)."""


class IdentificationError(MrftError):
    """No steady relay oscillation found, or the classifier could not decide."""

    exit_code = 6


class SetpointNotCrossed(IdentificationError):
    """The relay cycles do not cross the set point every half-cycle: the relay is biased
    too far for the test; a live tune starts the relay over from the set point."""


class CyclesTooSmall(IdentificationError):
    """The relay cycles are too small for the measurement noise to identify from; a live
    tune raises the relay amplitude (within its limit) before it waits for new cycles."""


class MissingDependency(MrftError):
    """An optional dependency is needed (the message names the extra to install)."""

    exit_code = 7


class FleetError(MrftError):
    """One or more vehicles of a fleet failed (each is reported on its own)."""

    exit_code = 8
