"""One driver of the tuning sequence, over any :class:`~mrft_gcs.flight.source.VehicleSource`.

:class:`SequenceDriver` holds what every run of :class:`~mrft_gcs.flight.sequence.TuningSequence`
does around it, in two parts:

- :meth:`~SequenceDriver.tick`, once per ground-station tick: on the ground the sample
  feeds the noise estimate (the relays' bands) and the idle set point goes out; in flight
  the safety limits are checked and the sequence steps. A live tune runs it on the set-point
  stream's thread, so it never waits for identification.
- :meth:`~SequenceDriver.supervise`, as often as the caller likes: steady cycles are
  identified (the identification callable), a refused identification waits for the next
  cycles (cycles that miss the set point start the relay over, cycles too small for the
  noise raise its amplitude first), a numerical failure is
  retried up to :data:`NUMERIC_RETRIES` times, side tests start with relay settings from
  their attitude identification, and a relay that never settles stops the test.

:meth:`~SequenceDriver.run` calls both inline, tick by tick (the simulated vehicle, a log
replay, which can follow the logged commands: docs/pipeline.md). The live tune
(:func:`mrft_gcs.flight.tune`) calls ``tick`` from the stream and ``supervise`` from its
main thread.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

from mrft_gcs.errors import CyclesTooSmall, IdentificationError, SetpointNotCrossed
from mrft_gcs.flight.controllers import FlightState, wrap_pi
from mrft_gcs.flight.safety import RELAY_GUARD_LEAD_S, SafetyMonitor
from mrft_gcs.flight.sequence import (
    AUTOPILOT_ATTITUDE,
    SIDE_INNER,
    CycleSnapshot,
    LoopState,
    Phase,
    TuningSequence,
)
from mrft_gcs.flight.source import Setpoint, VehicleSource, idle_setpoint, state_time_s
from mrft_gcs.flight.timeliness import HostTooSlow, TimelinessMonitor, host_advice
from mrft_gcs.identify import Identification, Method, RelaySettings, relay_settings
from mrft_gcs.identify.closed_loop import side_relay_settings
from mrft_gcs.identify.live import Identifier, closed_loop_summary, measured_attitude_loop
from mrft_gcs.loops import Loop, LoopKind
from mrft_gcs.plant import PD
from mrft_gcs.profiles import Actuation, SafetyLimits
from mrft_gcs.telemetry import AttitudeTarget, EndOfStream, RateTarget

__all__ = ["SequenceDriver", "NUMERIC_RETRIES"]

#: the phases in which the ground station closes the loops (stalls stop them) and those in
#: which relays run (the relay guard watches them)
_FLOWN = frozenset({Phase.TAKEOFF, Phase.INNER_MRFT, Phase.SIDE_MRFT, Phase.HOVER})
_RELAYS = frozenset({Phase.TAKEOFF, Phase.INNER_MRFT, Phase.SIDE_MRFT})

#: identifications of one loop that may fail on a numerical error (ValueError,
#: ArithmeticError) and be retried on the next cycles before the tune stops
NUMERIC_RETRIES = 2


class SequenceDriver:
    """Runs one :class:`TuningSequence`: per-tick stepping and the identification around it.

    Parameters
    ----------
    seq : TuningSequence
    identify : callable
        ``f(loop, snapshot, inner) -> Identification`` (the bundled classifiers, a test
        double, or a wrapper that runs them in a worker process).
    attitude_loop : callable
        ``f(snapshot) -> Identification``: the autopilot's closed attitude loop measured
        from a side relay's cycles (attitude path only).
    relay : dict, optional
        Relay settings per loop kind that replace the classifiers' (side: else asked with
        the attitude identification).
    limits : SafetyLimits, optional
        Checked on every tick in flight (:class:`SafetyMonitor`, made at :meth:`start`).
    max_relay_s : float, optional
        A relay running longer without steady cycles stops the test
        (:class:`IdentificationError`); None: no limit.
    notes : list of str, optional
        Where the notes on retried identifications go (the tune's report notes).
    timeliness : TimelinessMonitor, optional
        Checked on every tick in flight: a stalled loop stops the tests
        (:class:`~mrft_gcs.flight.timeliness.HostTooSlow`). The live tune feeds it from the
        link and the stream; :meth:`run` feeds it on the source's clock (a tick per state,
        a sample per new state).
    """

    def __init__(self, seq: TuningSequence, identify: Identifier, *,
                 attitude_loop: Callable[[CycleSnapshot], Identification] = measured_attitude_loop,
                 relay: dict[LoopKind, RelaySettings] | None = None,
                 limits: SafetyLimits | None = None, max_relay_s: float | None = None,
                 notes: list[str] | None = None,
                 timeliness: TimelinessMonitor | None = None) -> None:
        self.seq = seq
        self.timeliness = timeliness
        self.identify = identify
        self.attitude_loop = attitude_loop
        self.relay = relay or {}
        self.limits = limits
        self.max_relay_s = max_relay_s
        self.monitor: SafetyMonitor | None = None
        self.idle = idle_setpoint(seq.config.actuation is Actuation.ATTITUDE)
        #: the report's notes on retried identifications (appended to ``notes`` if given)
        self.notes: list[str] = notes if notes is not None else []
        #: (loop, error text) of every identification that was retried
        self.retries: list[tuple[Loop, str]] = []
        self.numeric_failures: dict[Loop, int] = {}
        #: a replay's identifications waiting for the tick the live tune applied them on
        self._held: dict[Loop, tuple[Identification, FlightState | None]] = {}
        #: side tests start only while this says so (the rate path: once the identified
        #: roll and pitch gains fly onboard)
        self.side_gate: Callable[[], bool] = lambda: True
        #: what the roll/pitch notes say flew the side tests where the autopilot's attitude
        #: loop did (measured from the side relays' cycles)
        self.autopilot_attitude_note = AUTOPILOT_ATTITUDE
        #: how far ahead the relay guard looks (s): the link's round trip and a telemetry
        #: period where they are known (:class:`~mrft_gcs.flight.safety.SafetyMonitor`)
        self.guard_lead_s = RELAY_GUARD_LEAD_S

    # ------------------------------------------------------------------ per tick
    def start(self, s: FlightState) -> None:
        """The take-off command: the safety origin and the sequence start at ``s``."""
        if self.limits is not None:
            self.monitor = SafetyMonitor(self.limits, (s.x_m, s.y_m, s.z_up_m),
                                         state_time_s(s), lead_s=self.guard_lead_s)
        if self.timeliness is not None:
            self.timeliness.forget()  # stalls on the ground were the pre-arm check's
        self.seq.start(s)

    def tick(self, s: FlightState | None, applied: Setpoint | None = None) -> Setpoint:
        """The set point answering ``s`` (idle with no state yet, or on the ground).

        ``applied``: the command the vehicle actually got for ``s`` (a log replay: the
        logged one); the sequence's cycle detectors then watch it instead of the
        sequence's own output (:meth:`loop_inputs`).

        Raises
        ------
        LimitExceeded
            ``s`` is beyond a safety limit.
        RelayTooLarge
            A relay test tilts ``s`` close to the tilt limit.
        DriftTooLarge
            A relay test carries ``s`` well towards the distance limit.
        HostTooSlow
            The ground station's loop stalled (``timeliness``).
        """
        seq = self.seq
        if s is None:
            return self.idle
        if seq.phase is Phase.PREFLIGHT:
            seq.observe(s)  # on the ground: the noise that sets the relays' bands
            return self.idle
        if self.monitor is not None:
            self.monitor.check(s)
            if seq.phase in _RELAYS:
                self.monitor.relay_guard(s, f"{seq.phase.value} relay test")
                self.monitor.drift_guard(s, f"{seq.phase.value} relay test")
        if self.timeliness is not None and seq.phase in _FLOWN:
            why = self.timeliness.trouble(relays=seq.phase in _RELAYS)
            if why is not None:
                raise HostTooSlow(f"the ground station could not keep the {seq.phase.value} "
                                  f"loop on time: {why}; tests stopped early, landing "
                                  f"commanded; {host_advice()}")
        return seq.step(s, None if applied is None else self.loop_inputs(s, applied))

    def loop_inputs(self, s: FlightState, applied: Setpoint) -> dict[Loop, float]:
        """Each loop's input in ``applied``, in the units of its relay's output.

        Roll, pitch and altitude are in the command itself (torque, thrust). x and y are
        the tilt set points: on the attitude path in the command; on the torque path behind
        the ground station's attitude PDs, so they are recovered by inverting the PD of
        their attitude loop (where it is tuned and its output was not clipped) and the
        rotation by the heading (see :meth:`TuningSequence.step`).
        """
        seq = self.seq
        out: dict[Loop, float] = {Loop.ALTITUDE: applied.thrust}
        if isinstance(applied, RateTarget):
            return out  # torques as rates: the torques need the channel's gain and rotation
        if isinstance(applied, AttitudeTarget):
            w, x, y, z = applied.q_wxyz
            ref = {Loop.ROLL: math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y)),
                   Loop.PITCH: math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))}
        else:
            out[Loop.ROLL], out[Loop.PITCH] = applied.roll, applied.pitch
            ref = {}
            for lp, u, angle, rate in ((Loop.ROLL, applied.roll, s.roll_rad, s.p_rad_s),
                                       (Loop.PITCH, applied.pitch, s.pitch_rad, s.q_rad_s)):
                pd = seq.loops[lp].pd
                if pd is not None and pd.Kc > 0 and pd.lo < u < pd.hi:
                    ref[lp] = angle + (u - pd.trim + pd.Kd * rate) / pd.Kc
        if len(ref) == 2:
            d = wrap_pi(s.yaw_rad - seq.yaw_ref)
            c, n = math.cos(d), math.sin(d)
            out[Loop.X] = -n * ref[Loop.ROLL] - c * ref[Loop.PITCH]
            out[Loop.Y] = c * ref[Loop.ROLL] - n * ref[Loop.PITCH]
        return out

    # ------------------------------------------------------------------ supervision
    def supervise(self) -> None:
        """Identify steady cycles, start side tests, stop a relay that never settles.

        Raises
        ------
        IdentificationError
            A relay ran ``max_relay_s`` without steady cycles, or one loop's identification
            failed on a numerical error more than :data:`NUMERIC_RETRIES` times.
        """
        seq = self.seq
        for snap in seq.ready():
            self.identify_one(snap)
        if seq.side_waiting and self.side_gate():
            self.start_side()
        for lp, t in seq.loops.items():
            if t.runaways >= seq.config.max_runaways and t.state is LoopState.RELAY:
                raise IdentificationError(
                    f"{lp.value}: the relay ran away {t.runaways} times without a steady "
                    f"cycle (the vehicle drifts on each one's lean); the tests stop and it "
                    f"lands: check the balance (centre of mass) and the motors, or tune this "
                    f"vehicle by hand (a response this slow is outside the classifiers' range)")
        if self.max_relay_s is not None:
            for lp in Loop:
                age = seq.relay_age_s(lp)
                if age > self.max_relay_s:
                    raise IdentificationError(
                        f"{lp.value}: no steady relay oscillation after {age:.0f} s: check for "
                        f"vibration, wind or a loose airframe, or raise the relay amplitude")

    def identify_one(self, snap: CycleSnapshot) -> None:
        """Identify ``snap`` and switch its loop to the PD, or retry by the rules."""
        done = self._identified(snap)
        if done is not None:
            self._apply(*done)

    def _identified(self, snap: CycleSnapshot) -> tuple[Loop, Identification] | None:
        """``snap`` identified, or None where the rules retried it."""
        seq = self.seq
        inner = None
        try:
            if snap.loop in SIDE_INNER:
                inner = seq.loops[SIDE_INNER[snap.loop]].identification
                scale = seq.config.gcs_attitude_pd_scale
                if inner is not None and scale != 1.0:  # the inner PD the side relay flew
                    g = inner.gains
                    inner = dataclasses.replace(inner, gains=PD(scale**2 * g.Kc, scale * g.Kd))
                if seq.config.actuation is Actuation.ATTITUDE:
                    # the autopilot's attitude loop flew the side relay (also once the rate
                    # path wrote the identified gains): measured from its cycles
                    inner = self.attitude_loop(snap)
            ident = self.identify(snap.loop, snap, inner)
        except IdentificationError as err:
            self.notes.append(f"{snap.loop.value}: identification retried ({err})")
            self.retries.append((snap.loop, str(err)))
            seq.retry(snap.loop, restart=isinstance(err, SetpointNotCrossed),
                      larger=isinstance(err, CyclesTooSmall))
            return None
        except (ValueError, ArithmeticError) as err:
            # a numerical failure inside identification (numpy's LinAlgError is a
            # ValueError): as a rule the cycles that caused it were disturbed ones, so the
            # relay runs on and the next cycles are tried; a failure that repeats is a fault
            n = self.numeric_failures[snap.loop] = self.numeric_failures.get(snap.loop, 0) + 1
            what = f"{type(err).__name__}: {err}"
            if n > NUMERIC_RETRIES:
                raise IdentificationError(
                    f"{snap.loop.value}: identification failed {n} times on a numerical "
                    f"error ({what}); the test stopped and the vehicle lands: "
                    f"please report it with the session's .tlog") from err
            self.notes.append(f"{snap.loop.value}: identification retried after a numerical "
                              f"error ({what})")
            self.retries.append((snap.loop, what))
            seq.retry(snap.loop)
            return None
        if inner is not None and inner.diagnostics.method is Method.CLOSED_LOOP:
            att = seq.loops[SIDE_INNER[snap.loop]]
            att.note = f"{self.autopilot_attitude_note}; {closed_loop_summary(inner, snap.loop)}"
            ident = dataclasses.replace(ident, inner=inner)
        return snap.loop, ident

    def _apply(self, loop: Loop, ident: Identification) -> None:
        self.seq.apply(loop, ident)
        if self.seq.side_waiting and self.side_gate():  # as supervise() does right after
            self.start_side()

    def start_side(self) -> None:
        """Start the side tests that can start, each with its relay settings."""
        seq = self.seq
        settings: dict[Loop, RelaySettings] = {}
        for lp in seq.side_ready():
            inner_lp = SIDE_INNER[lp]
            inner = seq.loops[inner_lp].identification
            if seq.config.actuation is Actuation.ATTITUDE:
                # the autopilot's attitude loop is measured from this very relay's cycles
                settings[lp] = self.relay.get(LoopKind.SIDE) or side_relay_settings()
                continue
            if inner is None:
                seq.leave_alone(lp, f"{lp.value} needs the identified {inner_lp.value} loop for "
                                f"the side-motion identification, and it was not identified")
                continue
            settings[lp] = self.relay.get(LoopKind.SIDE) or relay_settings(LoopKind.SIDE, inner)
        seq.start_side(settings)

    # ------------------------------------------------------------------ replay timing
    def _supervise_held(self) -> None:
        """:meth:`supervise` for a replay: identifications are made at once but held until
        the logged commands show the live tune switched that loop to its PD (its main
        thread took 10-100 ms), so the replay's relays stay those that flew."""
        seq = self.seq
        for snap in seq.ready():
            done = self._identified(snap)
            if done is not None:
                self._held[done[0]] = (done[1], seq.state)
        if not self._held and seq.side_waiting and self.side_gate():
            self.start_side()

    def _release_held(self, s: FlightState, applied: Setpoint) -> None:
        """Apply each held identification whose loop the logged command no longer drives
        with its relay (its input is off both relay levels), or held over a second."""
        if not self._held:
            return
        seq = self.seq
        inputs = self.loop_inputs(s, applied)
        for lp, (ident, since) in list(self._held.items()):
            t = seq.loops[lp]
            relay = seq.takeoff.relay if lp is Loop.ALTITUDE else t.relay
            u = inputs.get(lp)
            off = relay is None or (u is not None and min(
                abs(u - float(relay.bias[0]) - k * float(relay.h[0])) for k in (1.0, -1.0))
                > 1e-5)
            late = since is not None and state_time_s(s) - state_time_s(since) > 1.0
            if off or late:
                del self._held[lp]
                self._apply(lp, ident)

    # ------------------------------------------------------------------ inline
    def run(self, source: VehicleSource, *, ground_until_s: float = -math.inf,
            ground_ticks: int | None = None,
            stop: Callable[[FlightState], bool] | None = None,
            on_tick: Callable[[FlightState, Setpoint], None] | None = None,
            follow_applied: bool = False) -> FlightState | None:
        """Fly the sequence over ``source`` tick by tick, ``tick`` and ``supervise`` inline.

        On the ground until the source's clock reaches ``ground_until_s`` (idle set points,
        the noise measured), then the take-off command on the next state; or, with
        ``ground_ticks`` (a replay: :meth:`ReplayVehicle.takeoff_tick`), that many ticks on
        the ground and the take-off command on the last of them, as the live tune gave
        it. Then one tick per state until ``stop(state)`` (default: the sequence hovers on
        its PDs) or the source ends (:class:`EndOfStream`). ``on_tick(state, setpoint)``
        runs before each set point goes out. ``follow_applied`` (a replay, whose
        ``applied`` answers the current state): the cycle detectors watch the applied
        command (:meth:`tick`), and each identification waits for the tick the logged
        commands show it applied on (:meth:`_supervise_held`).
        Returns the last state (None: the source ended on the ground).

        Raises
        ------
        LimitExceeded, IdentificationError
            As :meth:`tick` and :meth:`supervise`.
        """
        seq = self.seq
        stop = stop or (lambda _s: seq.phase is Phase.HOVER)
        seen = -math.inf

        def state(s: FlightState | None) -> FlightState | None:
            nonlocal seen
            if self.timeliness is not None:  # on the source's clock
                if s is not None and state_time_s(s) > seen:
                    seen = state_time_s(s)
                    self.timeliness.sample(source.time_s, seen)
                self.timeliness.tick(source.time_s)
            return s

        try:
            last: FlightState | None = None
            if ground_ticks is not None:
                for _ in range(ground_ticks):
                    last = state(source.next_state()) or last
                    source.send(self.tick(last))
            else:
                while source.time_s < ground_until_s:
                    source.send(self.tick(state(source.next_state())))
            while last is None:
                last = state(source.next_state())
                if last is None:
                    source.send(self.idle)
            self.start(last)
            while True:
                s = state(source.next_state())
                if s is None:
                    continue
                applied = source.applied() if follow_applied else None
                if applied is not None:
                    self._release_held(s, applied)
                sp = self.tick(s, applied)
                if on_tick is not None:
                    on_tick(s, sp)
                source.send(sp)
                if applied is not None:
                    self._supervise_held()
                else:
                    self.supervise()
                if stop(s):
                    return s
        except EndOfStream:
            return seq.state
