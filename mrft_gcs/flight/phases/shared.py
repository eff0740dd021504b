"""What every phase of the tuning sequence shares, and the supervision every relay shares.

:class:`Shared` holds the settings, the per-loop tests, the report's events, the take-off
controller (the altitude relay runs inside it), the noise measured on the ground and the
filtered position. Its relay supervision is the same for every loop: one cycle-watcher
sample per telemetry sample (:meth:`~Shared.feed`), a run-away caught or restarted and a
relay too small to arm its threshold raised (:meth:`~Shared.watch`, :meth:`~Shared.raise_h`).
"""

from __future__ import annotations

import math

import numpy as np

from mrft_gcs.flight.config import SequenceConfig
from mrft_gcs.flight.controllers import FlightState, catch_pd
from mrft_gcs.flight.cycles import CycleWatcher
from mrft_gcs.flight.noise import ComplementaryFilter, NoiseEstimator
from mrft_gcs.flight.phases.state import LoopState, LoopTest
from mrft_gcs.flight.takeoff import TakeoffController
from mrft_gcs.loops import Loop
from mrft_gcs.relay import MRFT

__all__ = ["Shared"]


class Shared:
    """The state the phases share (one per tune; :class:`TuningSequence` holds it).

    Parameters
    ----------
    config : SequenceConfig
        Read at every call: the tuning API may replace it mid-tune.
    takeoff : TakeoffController
        The climb controller; the altitude relay runs inside it once it has switched.
    """

    def __init__(self, config: SequenceConfig, takeoff: TakeoffController) -> None:
        self.config = config
        self.takeoff = takeoff
        self.loops: dict[Loop, LoopTest] = {
            lp: LoopTest(lp, watch=CycleWatcher(config.cycle_rules(lp))) for lp in Loop}
        self.events: list[str] = []  # for the report's notes (relay amplitude raised...)
        #: per loop, the relay output the vehicle got this tick (a log replay), see feed()
        self.applied: dict[Loop, float] = {}
        self.origin = (0.0, 0.0, 0.0)  # take-off point, heading frame (m)
        self.att_noise = NoiseEstimator(4)  # roll, pitch (rad), their rates (rad/s)
        self.pos_noise = NoiseEstimator(3)  # x, y (filtered), z up (m)
        self.xy_filter = (ComplementaryFilter(config.side_filter_k),
                          ComplementaryFilter(config.side_filter_k))
        self.z_filter = ComplementaryFilter(config.side_filter_k)
        self.xy_f = (0.0, 0.0)
        self.z_f = 0.0

    # ------------------------------------------------------------------ signals
    def filter_position(self, s: FlightState) -> None:
        """x, y and z up smoothed with their own velocities (on each new position sample)."""
        fx, fy = self.xy_filter
        self.xy_f = (fx.update(s.t_pos_s, s.x_m, s.vx_m_s), fy.update(s.t_pos_s, s.y_m, s.vy_m_s))
        self.z_f = self.z_filter.update(s.t_pos_s, s.z_up_m, s.vz_up_m_s)

    def noise_band(self, loop: Loop) -> float:
        """Relay noise band of ``loop`` (its units): ``noise_band_sigmas`` x measured noise."""
        cfg = self.config
        if loop in (Loop.ROLL, Loop.PITCH):
            sig, default = self.att_noise.sigma()[0 if loop is Loop.ROLL else 1], \
                cfg.relay_band_att_rad
        else:
            i = {Loop.X: 0, Loop.Y: 1, Loop.ALTITUDE: 2}[loop]
            sig, default = self.pos_noise.sigma()[i], cfg.relay_band_pos_m
        return float(cfg.noise_band_sigmas * sig) if np.isfinite(sig) else default

    @property
    def inner_done(self) -> bool:
        """Roll and pitch are tuned or left alone."""
        return all(self.loops[lp].state in (LoopState.TUNED, LoopState.LEFT_ALONE)
                   for lp in (Loop.ROLL, Loop.PITCH))

    # ------------------------------------------------------------------ relay supervision
    def relay_of(self, t: LoopTest) -> MRFT | None:
        """The relay of ``t``'s loop (altitude's runs inside the take-off controller)."""
        return self.takeoff.relay if t.loop is Loop.ALTITUDE else t.relay

    def feed(self, t: LoopTest, t_s: float, u: float, y: float, new: bool) -> None:
        """One watcher sample per telemetry sample (ticks between samples repeat the state)."""
        if new and t.state in (LoopState.RELAY, LoopState.IDENTIFYING):
            t.watch.update(t_s, self.applied.get(t.loop, u), y)

    def h_max(self, loop: Loop) -> float:
        """The largest relay amplitude ``loop`` may take."""
        if loop is Loop.ALTITUDE:
            # the thrust must stay clear of zero: u = bias -+ h
            bias = self.loops[Loop.ALTITUDE].bias
            cap = 0.8 * bias if 0 < bias < 1 else self.config.h_max[1]
            if 0 < bias < 1:
                # and every motor clear of zero and of full while the roll and pitch relays
                # run beside it: a torque of 1 is half the motors full, half at zero, so each
                # motor carries half of each torque; a clipped push makes the cycle lopsided
                share = 0.5 * sum(abs(t.bias) + t.h for t in (self.loops[Loop.ROLL],
                                                                self.loops[Loop.PITCH])
                                  if t.state in (LoopState.RELAY, LoopState.IDENTIFYING)
                                  and t.relay is not None)
                cap = min(cap, min(bias, 1.0 - bias) - share)
            return min(self.config.h_max[1], cap)
        return self.config.h_max[0 if loop in (Loop.ROLL, Loop.PITCH) else 2]

    def raise_h(self, t: LoopTest, factor: float,
                why: str = "cycle too small for the measured noise") -> bool:
        """Raise a relay's amplitude (the oscillation is too small for the noise); start over.

        False if it is already as large as it may be (nothing changed).
        """
        relay = self.relay_of(t)
        h = min(self.h_max(t.loop), t.h * max(factor, self.config.h_raise))
        if math.isfinite(t.amp_per_h) and t.amp_per_h > 0:
            # roll/pitch: not past what swings the axis 1.5 x att_amp_max_rad (its measured
            # swing per unit h), as when it was sized
            h = min(h, 1.5 * self.config.att_amp_max_rad / t.amp_per_h)
        if relay is None or h <= t.h * 1.01:
            return False
        self.events.append(f"{t.loop.value}: relay amplitude raised from {t.h:.3g} to {h:.3g} "
                           f"({why})")
        t.h = h
        relay.h[:] = h
        if t.loop is Loop.ALTITUDE:
            self.takeoff.h = h
        t.raises += 1
        t.unarmed = t.switches = 0
        t.probe, t.turns, t.turn_sign = [], [], 0.0  # roll/pitch sizing: periods at this h
        t.restart_detection()
        return True

    def watch(self, t: LoopTest, relay: MRFT, e: float, state_before: float,
              e_rate: float = 0.0) -> None:
        """After a relay step: two switches in a row before the threshold armed raise h.

        A runaway (the error beyond ``runaway_factor`` cycle amplitudes while the relay
        pushes it further out, e.g. after a noise-triggered switch-back, or, once cycles were
        measured, while it still grows: ``e`` and ``e_rate`` of one sign) hands roll and
        pitch to a damping PD until they are back inside their cycle, and restarts the
        others as a plain sign relay, which at once pushes back; the detector starts over.
        A roll/pitch swing still carrying out counts by where it will stop, not where it
        is (``SequenceConfig.catch_torque_factor``).
        """
        st = float(relay.state[0])
        amp = t.status.amplitude
        if not math.isfinite(amp) and t.loop in (Loop.ROLL, Loop.PITCH):
            # just restarted (detector reset): the cycle seen before the run-away still
            # sizes the limit; with the bare floor the relay's own start-up swing would be
            # caught as a run-away again and again
            amp = t.cycle[1]
        floor = self.config.runaway_floor[0 if t.loop in (Loop.ROLL, Loop.PITCH) else
                                          1 if t.loop is Loop.ALTITUDE else 2]
        if not math.isfinite(amp) and t.loop in (Loop.ROLL, Loop.PITCH):
            floor = max(floor, self.config.runaway_floor_startup_rad)
        if t.loop is Loop.ALTITUDE and t.beta > -1:
            # a relay cycle needs band / (1 + beta) a side to arm its switches: with a noisy
            # altitude (a barometer) its working cycles pass the bare floor
            floor = max(floor, self.config.runaway_factor * t.band / (1 + t.beta))
        limit = max(floor, self.config.runaway_factor * amp) if math.isfinite(amp) else floor
        if t.loop in (Loop.ROLL, Loop.PITCH):
            # a disturbed cycle inflates its own amplitude: never let the limit pass the
            # largest tilt the tests command (20 deg), well inside the 35 deg safety limit
            limit = min(limit, self.config.max_tilt_cmd_rad)
        # u pushes y away, or y still moves away (``e_rate``: de/dt, roll and pitch) although
        # u pushes back: GCS stalls can lock a relay into a slow, large mode that swings out
        # on its momentum while u pushes back all along, then drives the return at full h
        # into as large a swing the other way; the damping PD brings the return swing to
        # rest instead. Only once the detector has measured cycles since the relay
        # (re)started, as its own start-up swing also carries past 3 amplitudes while it
        # pushes back (or once a resized roll/pitch relay restarted at rest: its cycle is
        # known, and its start-up swing is no larger)
        outward = e * e_rate > 0 and (math.isfinite(t.status.amplitude) or t.from_rest)
        reach = abs(e)
        if outward and t.loop in (Loop.ROLL, Loop.PITCH):
            per, a = t.cycle if math.isfinite(t.cycle[0]) else (t.status.period_s,
                                                                   t.status.amplitude)
            if math.isfinite(per) and per > 0 and a > 0:  # where the swing will stop
                w0 = 2 * math.pi / per
                reach += e_rate ** 2 / (2 * math.pi * a * w0 ** 2 / 4)
        if reach > limit and (st * e < 0 or outward):
            relay.reset()
            t.from_rest = False
            t.runaways += 1
            if (t.loop in (Loop.ROLL, Loop.PITCH) and not math.isfinite(t.cycle[0])
                    and math.isfinite(t.status.period_s) and t.status.amplitude > 0):
                # no settled cycle yet: the last complete one still sizes a damping PD (a
                # sign relay restarted at the run-away's error swings further out)
                t.cycle = (t.status.period_s, t.status.amplitude)
            if t.loop in (Loop.ROLL, Loop.PITCH) and math.isfinite(t.cycle[0]):
                # A relay is no stabilising controller: restarted after a disturbance (a
                # GCS stall holding one relay level) it feeds each swing into a larger one.
                # A damping PD from the relay's own cycle brings the axis back first.
                t.catch = catch_pd(t.h, *t.cycle)
                self.events.append(f"{t.loop.value}: relay paused, a damping PD caught the "
                                   f"run-away (error {e:+.3g})")
            elif t.loop is Loop.ALTITUDE and self.takeoff.resettle():
                self.events.append(f"altitude: relay stopped (error {e:+.3g} ran away); it "
                                   f"starts again once the climb controller holds the set point")
            else:
                relay.step(e)
                self.events.append(f"{t.loop.value}: relay restarted (error {e:+.3g} ran away)")
            t.unarmed = t.switches = 0
            t.ext = 0.0
            t.restart_detection()
            return
        if state_before != 0 and st != state_before:
            t.switches += 1
            if t.switches > 2 and abs(t.ext) * (1 + t.beta) <= t.band:
                t.unarmed += 1
                if t.unarmed >= 2:
                    self.raise_h(t, self.config.h_raise)
            else:
                t.unarmed = 0
            t.ext = 0.0
        elif st > 0:
            t.ext = max(t.ext, e)
        else:
            t.ext = min(t.ext, e)
