"""Names of the control loops the tool identifies and tunes."""

from __future__ import annotations

import enum

__all__ = ["Loop", "LoopKind", "INNER_LOOPS", "SIDE_LOOPS", "SIDE_INNER"]


class LoopKind(enum.Enum):
    """Model family of a loop: which parameter domain and classifier apply."""

    ATTITUDE = "attitude"
    ALTITUDE = "altitude"
    SIDE = "side"


class Loop(enum.Enum):
    """A tuned loop. The value is the key used in reports (README's report schema)."""

    ROLL = "roll"
    PITCH = "pitch"
    ALTITUDE = "altitude"
    X = "x"
    Y = "y"

    @property
    def kind(self) -> LoopKind:
        if self in (Loop.ROLL, Loop.PITCH):
            return LoopKind.ATTITUDE
        if self is Loop.ALTITUDE:
            return LoopKind.ALTITUDE
        return LoopKind.SIDE


INNER_LOOPS = (Loop.ROLL, Loop.PITCH, Loop.ALTITUDE)
SIDE_LOOPS = (Loop.X, Loop.Y)
#: the attitude loop behind each side loop (x north: -pitch, y east: +roll)
SIDE_INNER = {Loop.X: Loop.PITCH, Loop.Y: Loop.ROLL}
