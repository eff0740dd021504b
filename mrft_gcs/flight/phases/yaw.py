"""The yaw relay (rate path): MRFT on the heading, then its identified PD.

Yaw has the attitude model's structure (a torque into an angle through motor lag, body drag
and delay), so its relay cycle is identified by the attitude classifier. Until the relay
starts, and wherever it gives up, the heading is held by the hold it was given (on the rate
path: the vehicle's own yaw gains). The relay starts :attr:`YawRules.start_after_s` after the
first airborne tick (once the heading is at rest), next to the altitude and roll/pitch
relays (the zero-gain window of the rate path closes only once yaw is done too); it is sized
once towards :attr:`YawRules.amp_goal_rad` (on cycle :attr:`YawRules.size_on_cycle`, or
sooner where a cycle swings too far), and its zero follows a cycle that drifts off the set
point (:attr:`YawRules.centre_share`), so that it stays an MRFT cycle. A
heading error beyond :attr:`YawRules.abort_rad` or no steady cycle within
:attr:`YawRules.max_s` hands yaw back to the hold, with the reason (:attr:`YawRelay.why`).

:meth:`YawRelay.step` runs on the setpoint stream's thread (called as the sequence's yaw hold
is), :meth:`YawRelay.take` and :meth:`YawRelay.apply` on the thread that identifies.
"""

from __future__ import annotations

import enum
import math
import threading
from dataclasses import dataclass

import numpy as np

from mrft_gcs.flight.config import SequenceConfig
from mrft_gcs.flight.controllers import PDLoop, YawHold, wrap_pi
from mrft_gcs.flight.cycles import CycleWatcher
from mrft_gcs.flight.phases.state import CycleSnapshot
from mrft_gcs.identify import Identification
from mrft_gcs.loops import Loop
from mrft_gcs.pd_design import PD
from mrft_gcs.relay import MRFT

__all__ = ["YawRules", "YawRelay", "YawState", "YawOutcome", "IDENTIFY_AS"]

#: the loop whose classifier identifies yaw (the attitude one: the same model structure)
IDENTIFY_AS = Loop.ROLL


@dataclass(frozen=True)
class YawRules:
    """How the yaw relay runs (angles in rad, torques normalised, times in s)."""

    #: after the first airborne tick: the climb's own transient passes first. Not later: the
    #: x/y tests that follow roll and pitch turn the heading too (ArduCopter SITL: its yaw
    #: relay needed a mean 0.1 of torque from ~5.5 s after lift-off and lost its cycle)
    start_after_s: float = 0.75
    #: first relay amplitude; sized once, within [h_min, h_max]
    h_start: float = 0.2
    h_min: float = 0.01
    h_max: float = 0.3
    #: the heading swing the relay is sized towards
    amp_goal_rad: float = math.radians(1.5)
    #: resized where a cycle swings outside [1/ratio, ratio] x the goal: at once where it
    #: swings past ``ratio`` x the goal, otherwise on cycle ``size_on_cycle`` (the first
    #: cycle of a relay started just after lift-off is no measure: ArduCopter SITL's swung
    #: 0.01-0.4 deg against 0.6 on the next at the same h)
    resize_ratio: float = 1.8
    size_on_cycle: int = 2
    #: the relay's zero follows its cycle: where a cycle's centre lies further than this
    #: share of its swing from the relay's zero, the zero moves to that distance. Yaw barely
    #: damps its rate and the relay restores the heading only weakly (by 1 + beta), so a
    #: turn left from the start carries the cycle off the set point; a cycle that no longer
    #: crosses its zero is no MRFT (the relay's extremes are measured from zero) and drifts
    #: on until far off (ArduCopter SITL: 0.3-0.5 deg a cycle, 3-3.4 deg off in 4 s). The
    #: share left keeps some of the relay's pull back towards the set point
    centre_share: float = 0.5
    #: a heading error that ends the test (back to the hold)
    abort_rad: float = math.radians(25.0)
    #: seconds from the relay's due start without a steady cycle that end the test
    max_s: float = 8.0
    #: relay noise band (rad): heading noise is far below the cycle
    band_rad: float = 0.0005
    #: the relay (re)starts once the hold brought the heading this near its set point, this
    #: slowly turning
    settle_rad: float = math.radians(1.0)
    settle_rate_rad_s: float = math.radians(2.0)
    settle_max_s: float = 1.5
    #: a cycle off its set point whose centre moved this share of its swing since the cycle
    #: before has drifted; re-biased at most this many times. Off by default: on ArduCopter
    #: SITL the centres of the first cycles moved as they grew, and the re-bias that took
    #: their mean torque (-0.07 against a true ~0) lost the cycle; its cycles were identified
    #: off centre as they came (identification reads the bias from the cycle)
    drift_share: float = 0.5
    max_rebias: int = 0


@dataclass(frozen=True)
class YawOutcome:
    """What came of yaw's relay test on the rate path (the report's ``loops.yaw``).

    Attributes
    ----------
    state : str
        ``tuned`` (gains written) or ``held`` (the vehicle's own yaw gains kept).
    reason : str or None
        Why yaw was held (None where tuned).
    beta, h, bias, band : float
        The relay's settings (normalised yaw command; band in rad).
    period_s, amplitude : float
        Of the identified cycle (s, rad); NaN where none was identified.
    identification : Identification or None
        The attitude classifier's result on yaw's cycles.
    gains : PD or None
        The gains the autopilot closes with the written parameters (normalised yaw command
        per rad and per rad/s: angle P times rate P, rate P); None where none are written.
    written : dict
        Parameter -> value written (empty where held).
    pm_predicted_deg, crossover_rad_s : float
        The written gains' phase margin and crossover on ArduCopter's yaw cascade as
        modelled (NaN where none are written).
    steady_after_s : float
        Steady cycles after the take-off command (s; NaN: none came).
    max_error_rad, zero_moved_rad : float
        Largest heading error while the relay ran, and how far its zero followed the cycle
        off the set point (rad).
    note : str
        The report's line on yaw.
    """

    state: str
    reason: str | None
    beta: float
    h: float
    bias: float
    band: float
    period_s: float
    amplitude: float
    identification: Identification | None
    gains: PD | None
    written: dict[str, float]
    pm_predicted_deg: float
    crossover_rad_s: float
    steady_after_s: float
    max_error_rad: float
    zero_moved_rad: float
    note: str


class YawState(enum.Enum):
    HOLD = "hold"  # the given hold, before the relay
    SETTLE = "settle"  # the hold again, until the heading is near its set point
    RELAY = "relay"
    READY = "ready"  # steady cycles waiting for identification (the relay keeps running)
    TUNED = "tuned"  # the identified PD (times the ground station's factor)
    HELD = "held"  # gave up: the given hold, with the reason


class YawRelay:
    """The sequence's yaw controller, an MRFT on the heading between two holds.

    Parameters
    ----------
    hold : YawHold
        Holds the heading before the relay and after a give-up.
    beta : float
        MRFT beta (the attitude classifier's).
    rules : YawRules
    config : SequenceConfig
        Its attitude cycle rules decide when the cycle is steady.
    """

    def __init__(self, hold: YawHold, beta: float, rules: YawRules | None = None,
                 config: SequenceConfig | None = None) -> None:
        self.hold = hold
        self.beta = beta
        self.rules = rules or YawRules()
        cfg = config or SequenceConfig()
        self.watch = CycleWatcher(cfg.cycle_rules(IDENTIFY_AS))
        self.state = YawState.HOLD
        self.why = ""  # why yaw went back to the hold (HELD)
        self.h = self.rules.h_start
        self.bias = 0.0
        self.relay: MRFT | None = None
        self.pd: PDLoop | None = None
        self.snapshot: CycleSnapshot | None = None
        self.resized = False
        self.rebiased = 0
        self.t_first_s = math.nan  # first airborne tick
        self.t_relay_s = math.nan
        self.t_ready_s = math.nan  # steady cycles handed over
        self.max_error_rad = 0.0  # largest heading error while the relay ran
        self.zero_rad = 0.0  # the relay's zero: its heading error where it cycles about
        self.max_zero_rad = 0.0  # the largest |zero_rad| (how far the cycle was followed)
        self.events: list[str] = []
        self._t_last_s = -math.inf
        self._t_settle_s = math.nan  # the hold began to settle the heading
        self._centre = math.nan  # the last cycle's mean heading (rad)
        self._lock = threading.Lock()

    @property
    def done(self) -> bool:
        """Identified or given up: nothing more to wait for."""
        return self.state in (YawState.TUNED, YawState.HELD)

    def _give_up(self, why: str) -> None:
        self.state, self.why, self.relay = YawState.HELD, why, None

    def give_up(self, why: str) -> None:
        """Back to the hold (identification refused the cycles, the tests moved on)."""
        with self._lock:
            if self.state is not YawState.TUNED:
                self._give_up(why)

    def step(self, ref: float, y: float, rate: float, t_s: float = math.nan) -> float:
        """Normalised yaw torque for this tick (heading set point and heading in rad, yaw
        rate in rad/s, ``t_s`` the attitude sample's time; called once airborne)."""
        with self._lock:
            e = wrap_pi(ref - y)
            if self.pd is not None:
                return self.pd.step(0.0, -e, rate)
            if self.state is YawState.HELD or not math.isfinite(t_s):
                return self.hold.step(ref, y, rate)
            r = self.rules
            if not math.isfinite(self.t_first_s):
                self.t_first_s = t_s
            if (self.state is not YawState.READY
                    and t_s - self.t_first_s > r.start_after_s + r.max_s):
                self._give_up(f"no steady relay cycle within {r.max_s:g} s")
            if self.state in (YawState.HOLD, YawState.SETTLE, YawState.HELD):
                u = self.hold.step(ref, y, rate)
                if self.state is YawState.HELD or t_s - self.t_first_s < r.start_after_s:
                    return u
                if not math.isfinite(self._t_settle_s):
                    self._t_settle_s = t_s
                # at rest (a relay started mid-swing drifts off), and near the set point
                # unless the hold cannot bring it there (a torque bias its P leaves)
                if abs(rate) < r.settle_rate_rad_s and (
                        abs(e) < r.settle_rad or t_s - self._t_settle_s > r.settle_max_s):
                    self._start(t_s)
                return u
            assert self.relay is not None
            self.max_error_rad = max(self.max_error_rad, abs(e))
            if abs(e) > r.abort_rad:
                self._give_up(f"the heading swung {math.degrees(abs(e)):.0f} deg off during "
                              f"its relay (limit {math.degrees(r.abort_rad):.0f})")
                return self.hold.step(ref, y, rate)
            u = float(self.relay.step(e - self.zero_rad)[0])
            if t_s <= self._t_last_s:  # ticks between telemetry samples repeat the state
                return u
            self._t_last_s = t_s
            cycles = self.watch.status.cycles
            status = self.watch.update(t_s, u, -e)
            if status.cycles > cycles:
                self._follow(e, status.amplitude)
            if self.state is YawState.RELAY:
                if self._size(status.cycles, status.amplitude):
                    return self.hold.step(ref, y, rate)
                if status.cycles > cycles and self._drifting(status.amplitude):
                    return self.hold.step(ref, y, rate)
                if self.watch.steady and (c := self.watch.cycles()) is not None:
                    ts, us, ys = c
                    self.snapshot = CycleSnapshot(IDENTIFY_AS, ts, us, ys, self.beta, self.h,
                                                  self.bias, status)
                    self.state, self.t_ready_s = YawState.READY, t_s
            return u

    def _start(self, t_s: float) -> None:
        """The relay from here (the heading settled near its set point), biased at the
        hold's trim: no torque until a cycle measured the one that holds the heading (the
        hold's mean output is no measure of it: without an I term it also carries P times
        the error left and D times the turn, a +0.04 bias that centred ArduCopter SITL's
        cycles 1-2 deg off their set point)."""
        self.bias = self.hold.trim
        self.relay = MRFT(self.beta, self.h, bias=self.bias, band=self.rules.band_rad)
        self.zero_rad = 0.0
        self.watch.restart()
        self.state, self._t_settle_s, self._centre = YawState.RELAY, math.nan, math.nan
        if not math.isfinite(self.t_relay_s):
            self.t_relay_s = t_s

    def _drifting(self, amp: float) -> bool:
        """A cycle centred off the set point by more than its swing whose centre moved by
        more than :attr:`YawRules.drift_share` of its swing since the cycle before: its
        relay's bias is not the torque that holds the heading (roll and pitch relays running
        next to it move that torque). The bias is set to the cycle's mean torque (the plant
        integrates: over a full cycle the mean torque is the holding one; also the hold's
        trim) and the relay starts over from the set point, up to :attr:`YawRules.max_rebias`
        times; after that the cycles are identified as they are
        (identification reads the bias from the cycle). True: started over."""
        if self.rebiased >= self.rules.max_rebias:
            return False
        ts, us, ys = self.watch.last_cycles(1)
        if ys.size < 4 or not amp > 4 * self.rules.band_rad:
            return False
        mean, last = float(np.mean(ys)), self._centre
        self._centre = mean
        # off centre alone is no drift: on a plant that barely damps its rate the cycle's
        # centre is where its first swing left it (neutral; ArduCopter SITL's sat 1 deg off
        # at a 0.8 deg swing, and its mean torque was the bias already); a centre that moves
        # on from cycle to cycle is
        if not (math.isfinite(last) and abs(mean) > amp
                and abs(mean - last) > self.rules.drift_share * amp):
            return False
        dt = np.diff(ts)
        bias = float(np.sum(us[:-1] * dt) / np.sum(dt))
        self.rebiased += 1
        self.events.append(f"yaw: relay bias {self.bias:+.3g} -> {bias:+.3g} (a cycle centred "
                           f"{math.degrees(mean):+.1f} deg off its set point, swing "
                           f"{math.degrees(amp):.1f} deg: the mean torque of the cycle)")
        # the hold brings the heading back at that torque (an MRFT on an integrating plant
        # cycles wherever it is: a right bias alone does not re-centre it), then the relay
        # starts over from rest at the set point
        self.bias = self.hold.trim = bias
        self.state, self.relay = YawState.SETTLE, None
        return True

    def _follow(self, e: float, amp: float) -> None:
        """At a cycle boundary (the relay just switched up, heading error ``e``): the
        relay's zero moved to within :attr:`YawRules.centre_share` of the last cycle's swing
        from its centre, and the relay's state as if it had switched about that zero."""
        relay, share = self.relay, self.rules.centre_share
        # re-biasing (where on) answers an off-centre cycle instead, while it may
        if relay is None or not (share >= 0 and amp > 0) or self.rebiased < self.rules.max_rebias:
            return
        _, _, ys = self.watch.last_cycles(1)
        if ys.size < 2 or not relay.state[0] > 0:
            return
        off = -0.5 * float(np.max(ys) + np.min(ys)) - self.zero_rad  # centre from the zero
        if abs(off) <= share * amp:
            return
        self.zero_rad += off - math.copysign(share * amp, off)
        self.max_zero_rad = max(self.max_zero_rad, abs(self.zero_rad))
        # what the relay set on its switch up, measured from the new zero (its extreme
        # starts at the switch, or at zero where the switch came below it)
        x = e - self.zero_rad
        relay.ext[:] = max(x, 0.0)
        relay.entry[:] = x

    def _size(self, cycles: int, amp: float) -> bool:
        """Once: h towards the goal swing (the swing is proportional to h), the relay
        restarted from the hold; on the first cycle that swings too far, or on cycle
        :attr:`YawRules.size_on_cycle`. True: restarted."""
        r = self.rules
        if self.resized or cycles < 1 or not amp > 0:
            return False
        ratio = r.amp_goal_rad / amp
        if cycles < r.size_on_cycle and ratio >= 1.0 / r.resize_ratio:
            return False  # still growing, and not too far yet
        self.resized = True
        if 1.0 / r.resize_ratio <= ratio <= r.resize_ratio:
            return False
        h = min(r.h_max, max(r.h_min, self.h * ratio))
        if abs(h - self.h) < 0.01 * self.h:
            return False
        self.events.append(f"yaw: relay sized on its cycle {cycles} ({math.degrees(amp):.2g} deg "
                           f"at h {self.h:.3g}): amplitude {self.h:.3g} -> {h:.3g}")
        self.h = h
        self.state, self.relay = YawState.SETTLE, None
        return True

    def take(self) -> CycleSnapshot | None:
        """The steady cycles, once, for identification (None: none waiting)."""
        with self._lock:
            if self.state is YawState.READY and self.snapshot is not None:
                snap, self.snapshot = self.snapshot, None
                return snap
            return None

    def apply(self, Kc: float, Kd: float) -> None:
        """Fly the PD ``Kc``, ``Kd`` (normalised torque per rad, per rad/s) from the next
        tick, about the relay's bias, within the hold's limits."""
        with self._lock:
            self.pd = PDLoop(Kc, Kd, self.bias, self.hold.lo, self.hold.hi)
            self.state, self.relay = YawState.TUNED, None
