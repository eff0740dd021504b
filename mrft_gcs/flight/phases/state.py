"""The tuning sequence's state: where it stands (:class:`Phase`), each loop's progress
(:class:`LoopState`) and test (:class:`LoopTest`), and the cycles handed to identification
(:class:`CycleSnapshot`). Every phase reads and writes these; none holds logic."""

from __future__ import annotations

import enum
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from mrft_gcs.flight.controllers import PDLoop
from mrft_gcs.flight.cycles import CycleRules, CycleWatcher
from mrft_gcs.identify import CycleDetector, CycleStatus, Identification
from mrft_gcs.loops import SIDE_INNER, Loop
from mrft_gcs.relay import MRFT

__all__ = [
    "Phase",
    "LoopState",
    "LoopTest",
    "CycleSnapshot",
    "AUTOPILOT_ATTITUDE",
    "SIDE_INNER",
]

_NAN = float("nan")
#: why roll and pitch are left alone on the attitude path (the report's note)
AUTOPILOT_ATTITUDE = ("attitude path: the autopilot keeps its own attitude loop "
                      "(SET_ATTITUDE_TARGET), so roll and pitch are not tested or written")
_TILT_SAMPLES = 30_000  # 30 s of ATTITUDE at 1 kHz: as long as the cycle detector keeps data


class Phase(enum.Enum):
    """Where the tuning sequence stands."""

    PREFLIGHT = "preflight"
    TAKEOFF = "take-off"
    INNER_MRFT = "inner MRFT"
    SIDE_MRFT = "side MRFT"
    HOVER = "hover"
    LANDING = "landing"
    DONE = "done"
    ABORTED = "aborted"


class LoopState(enum.Enum):
    """One loop's progress."""

    WAITING = "waiting"
    RELAY = "oscillating"
    IDENTIFYING = "identifying"
    TUNED = "tuned"
    LEFT_ALONE = "left alone"


@dataclass(frozen=True)
class CycleSnapshot:
    """The steady relay cycles handed to identification (arrays of shape (m,))."""

    loop: Loop
    t_s: np.ndarray
    u: np.ndarray
    y: np.ndarray
    beta: float
    h: float
    bias: float
    status: CycleStatus
    #: the relay's set point in the units of ``y`` (altitude, x, y: the point the relay
    #: oscillates about); None for roll and pitch, whose set point moves with the bounding
    #: relay. Identification refuses cycles that do not cross it every half-cycle.
    setpoint: float | None = None
    #: x and y: the measured tilt along the axis (rad, the sign of ``u``: x ``-pitch``, y
    #: ``+roll`` in the take-off heading frame) from ATTITUDE, interpolated onto ``t_s``:
    #: with ``u`` it measures the closed attitude loop the side relay drove (attitude path)
    tilt: np.ndarray | None = None


@dataclass
class LoopTest:
    """Mutable per-loop state of the sequence (read by displays under the sequence lock)."""

    loop: Loop
    state: LoopState = LoopState.WAITING
    beta: float = _NAN
    h: float = _NAN
    bias: float = 0.0
    relay: MRFT | None = None
    #: the relay's cycles: when they are steady, which to identify (:mod:`.cycles`)
    watch: CycleWatcher = field(default_factory=lambda: CycleWatcher(CycleRules()))
    pd: PDLoop | None = None
    identification: Identification | None = None
    snapshot: CycleSnapshot | None = None
    t_relay_start_s: float = _NAN
    t_tuned_s: float = _NAN
    note: str = ""
    u: float = 0.0
    band: float = _NAN
    ext: float = 0.0  # extreme error since the relay's last switch
    unarmed: int = 0  # switches made before the threshold could arm (relay too small)
    raises: int = 0  # times the relay amplitude was raised
    switches: int = 0  # relay switches since the relay (re)started
    #: cycles seen when identification last refused them (too small for the noise): the
    #: next try waits for a newer cycle; and when the first of such refusals in a row was
    retry_from: int = 0
    retry_base: int = -1
    center: float = 0.0  # side relays: the position the relay oscillates about (m)
    settling: bool = False  # side relays: bringing the axis to rest before the relay starts
    presettle: bool = False  # side loops: held at rest while waiting for the altitude test
    #: side relays: (t_att_s, measured tilt along the axis) while the relay runs
    tilt: deque = field(default_factory=lambda: deque(maxlen=_TILT_SAMPLES))
    #: roll/pitch: the last steady-looking cycle's (period s, amplitude rad), and the
    #: damping PD (Kc, Kd) that holds the axis while a run-away is caught (None: relay)
    cycle: tuple[float, float] = (_NAN, _NAN)
    catch: tuple[float, float] | None = None
    #: roll/pitch: the amplitude the relay takes once its first period is measured and
    #: whether that is done; (t, u, y, rate) since the relay's first switch (its periods run
    #: from one turn of the axis to the next the same way); the turns seen in it; the
    #: measured swing per unit of h (rad); times resized; the catch hands back inside this
    #: share of the cycle's envelope (a resized relay restarts nearly at rest)
    h_goal: float = _NAN
    sized: bool = True
    probe: list = field(default_factory=list)
    turns: list = field(default_factory=list)
    turn_sign: float = 0.0
    probe_switches: int = 0
    pushed_away: int = 0  # roll/pitch: times the relay was turned round early (see attitude.py)
    runaways: int = 0  # run-aways caught or restarted (Shared.watch)
    from_rest: bool = False  # roll/pitch: the relay restarted at rest after it was resized
    amp_per_h: float = _NAN
    resizes: int = 0
    catch_release: float = 1.0
    t_catch_s: float = _NAN
    catch_flips: int = 0  # roll/pitch: the catch's swings from one limit to the other
    catch_sign: float = 0.0  # and the side of the last limit it sat at
    t_rest_s: float = _NAN  # roll/pitch: since when the catch has held the axis at rest
    bias_votes: list = field(default_factory=list)  # mean torque of the last periods
    #: roll/pitch before sizing: the torque-bias fit is done (see attitude.py); the relay's
    #: commands (t, u) since its start, the rates (t, rad/s) once off the ground, and the
    #: relay switches seen
    centred: bool = False
    centre_cmd: list = field(default_factory=list)
    centre_rate: list = field(default_factory=list)
    centre_switches: int = 0
    #: roll/pitch before the first period: the h the fit's predicted swing asks for, taken
    #: at the next turn of the axis (nan: none)
    h_planned: float = _NAN
    t_h_planned_s: float = _NAN
    #: roll/pitch before the first period: (t, relay state, de/dt)
    probe_rate: deque = field(default_factory=lambda: deque(maxlen=400))

    @property
    def status(self) -> CycleStatus:
        """What the cycle watcher has seen of the relay's cycles."""
        return self.watch.status

    @status.setter
    def status(self, value: CycleStatus) -> None:
        self.watch.status = value

    @property
    def detector(self) -> CycleDetector:
        """The cycle watcher's detector."""
        return self.watch.detector

    @detector.setter
    def detector(self, value: CycleDetector) -> None:
        self.watch.detector = value

    def restart_detection(self) -> None:
        """Forget the cycles seen so far: the relay starts over."""
        self.watch.restart()
        self.retry_from, self.retry_base = 0, -1
