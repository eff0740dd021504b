"""How the tuning sequence flies: one frozen options object, :class:`SequenceConfig`.

Each field says why it has its value; the measurements behind the choices are in
``docs/takeoff-and-sequence.md`` ("Why the settings are what they are"). Change a
field with :func:`dataclasses.replace`; nothing changes a config in place.
"""

from __future__ import annotations

from dataclasses import dataclass

from mrft_gcs.flight.cycles import CycleRules
from mrft_gcs.flight.takeoff import TABLE_V, TakeoffSettings
from mrft_gcs.loops import Loop, LoopKind
from mrft_gcs.profiles import Actuation

__all__ = ["SequenceConfig"]

_KINDS = (LoopKind.ATTITUDE, LoopKind.ALTITUDE, LoopKind.SIDE)


@dataclass(frozen=True)
class SequenceConfig:
    """How the sequence flies; units in the names.

    Tuples of three are per loop kind (attitude, altitude, side). ``hover_thrust_guess``
    (the autopilot's estimate, normalised thrust) turns the take-off into a climb on a PD
    about it, with the altitude relay started at rest and biased at it
    (:mod:`mrft_gcs.flight.takeoff`); without it, eq. 21 with Table V.
    """

    actuation: Actuation = Actuation.TORQUE
    z_ref_m: float = 1.0
    takeoff: TakeoffSettings = TABLE_V
    hover_thrust_guess: float | None = None
    #: the climb's brake (``TakeoffSettings.brake_m``) only once roll and pitch are tuned: a
    #: braked climb starts the altitude relay sooner, and its thrust swing then disturbs
    #: the attitude relays still running
    brake_after_attitude: bool = True
    #: largest tilt the tests command (rad), well inside the safety limit
    max_tilt_cmd_rad: float = 0.35
    airborne_m: float = 0.03
    #: lift-off as the attitude sees it: after the take-off command, a roll/pitch rate beyond
    #: ``liftoff_rate_sigmas`` x its ground noise (at least ``liftoff_rate_floor_rad_s``) or
    #: an angle off its ground value by more than the relay's noise band starts the attitude
    #: relays; a centre-of-mass offset tilts the vehicle before the (delayed) altitude shows
    #: ``airborne_m``
    liftoff_rate_sigmas: float = 5.0
    liftoff_rate_floor_rad_s: float = 0.05
    #: ... once the thrust command is this share of the hover guess (0.1 without one): below
    #: it, motion is vibration, not lift-off
    liftoff_thrust_share: float = 0.7
    #: cycles handed to identification (the classifier input averages up to four)
    identify_cycles: int = 4
    #: ... except altitude and x/y (altitude, side), which the tune waits for: one cycle
    #: sooner; fewer side cycles gave unstable gains
    identify_cycles_alt_side: tuple[int, int] = (3, 3)
    #: periods (and amplitudes) that must agree before a loop's cycles are identified. The
    #: two side relays run at once and disturb each other, so their cycles beat; the cycles
    #: handed over are still checked for steadiness by the harmonic fit's spread
    #: (:data:`mrft_gcs.identify.runtime.FIT_MAX_SD`)
    steady_periods: tuple[int, int, int] = (3, 2, 2)
    #: from this many cycles on (None: never) a loop's periods and amplitudes may spread by
    #: ``relaxed_tol`` instead of ``period_tol`` and 8 %: a late ground-station tick holds a
    #: relay switch, which kicks nearly every short roll/pitch cycle
    relax_after_cycles: tuple[int | None, int | None, int | None] = (8, None, None)
    relaxed_tol: tuple[float, float] = (0.08, 0.16)
    #: periods agree within this fraction, or 2.5 telemetry intervals if that is more: over
    #: a real link an otherwise steady cycle's period wobbles by a few per cent
    period_tol: float = 0.05
    #: a relay whose error passes ``runaway_factor`` x its cycle amplitude (and the floor:
    #: rad for attitude, m for altitude and side) while still pushing it out is restarted
    runaway_factor: float = 3.0
    #: a relay that ran away this many times without a steady cycle stops the tests: the
    #: vehicle drifts on each run-away's lean (a slow out-of-domain vehicle went 5 m on 9)
    max_runaways: int = 5
    runaway_floor: tuple[float, float, float] = (0.1, 0.15, 0.3)
    #: altitude: the run-away floor grows to ``runaway_factor`` x the smallest cycle that arms
    #: the relay's switches in the measured noise (``band / (1 + beta)`` a side); past this
    #: (m) the altitude is too noisy for the relay test, which is refused at the take-off
    #: command: cycles that need over 10 cm a side to arm ran away at the largest altitude h
    #: (their unarmed halves switch late, on the relay's noise guard, and the cycle grows)
    runaway_floor_alt_max_m: float = 0.3
    #: roll/pitch before any cycle is known (rad): a relay's start-up swings are larger than
    #: its steady cycle, and restarting one as a sign relay swings it further out
    runaway_floor_startup_rad: float = 0.25
    #: roll/pitch run-away catch: a swing still carrying out is caught where it will *stop*
    #: (error plus rate^2 / 2 a, with a = pi A w0^2 / 4 the plant's acceleration per h from
    #: the relay's cycle) rather than where it is, and the damping PD may use this many times
    #: the relay amplitude: h alone (what the relay pushes back with) stops a stalled swing
    #: too late
    catch_torque_factor: float = 3.0
    #: the catch's PD is halved each time its output swings this many times from one limit
    #: to the other: it was sized on a first period that understated the plant's gain (too
    #: stiff for the loop's delay, it chatters at its limits and never hands back)
    catch_chatter_flips: int = 4
    #: factor on the identified attitude PDs while they run on the GCS (during the side
    #: tests and the hover): on Kd, and its square on Kc (the loop is nearly a double
    #: integrator, whose crossover follows Kd: the PD's zero moves down with it and its lead
    #: at the crossover stays; both scaled alike, the zero stays and the lead shrinks). The
    #: written gains are never scaled
    gcs_attitude_pd_scale: float = 1.0
    #: relay noise band = this many standard deviations of the signal's noise, measured on
    #: the ground before the take-off (the classifiers were trained with 4 sigma)
    noise_band_sigmas: float = 4.0
    #: bands used when too few ground samples were seen to measure the noise
    relay_band_att_rad: float = 0.003
    relay_band_pos_m: float = 0.003
    #: the relay amplitude is raised (x ``h_raise``, up to ``h_max``: attitude torque,
    #: altitude thrust, side tilt in rad) when the oscillation is too small for the noise:
    #: switches before the MRFT threshold clears the band, or noise over ``max_noise_ratio``
    #: of the amplitude (the classifiers were trained with up to 3 %)
    h_raise: float = 1.6
    h_max: tuple[float, float, float] = (0.3, 0.25, 0.2)
    max_noise_ratio: float = 0.025
    #: cycles identification refused as too small for the noise are retried on each next
    #: cycle; once this many whole new sets of cycles were refused too, the amplitude is
    #: raised (:meth:`~mrft_gcs.flight.sequence.TuningSequence.retry`). A raise at once was
    #: slower (its first cycles, still growing, were refused as well); after two sets a
    #: side axis of 1 s cycles waited 6 s on cycles that a third of the time passed by chance
    refused_sets_before_raise: int = 1
    #: smallest steady amplitude of the roll/pitch relays (normalised torque): the
    #: classifiers' default (Table V: 0.05) gives cycles too small to clear the noise band
    h_att_min: float = 0.12
    #: the roll/pitch relays start at this amplitude, and their first period measures how
    #: far the axis swings per unit of h and the torque that holds it on average (a
    #: centre-of-mass offset: the mean relay output over one period, as the plant
    #: integrates). The relay then takes ``h_att_min`` (or a raised amplitude), but no more
    #: than swings the axis ``att_amp_max_rad``, and that mean torque as its bias when it
    #: exceeds ``att_bias_min`` of h: a fixed large h swings light, agile vehicles too far,
    #: and a start below a likely centre-of-mass torque cannot turn the axis back
    h_att_start: float = 0.06
    #: ... and never below this (a torque a motor dead band or the noise would swamp)
    h_att_floor: float = 0.02
    #: a relay pushing back for this long while the axis still speeds away is beaten by a
    #: torque bias (longer than the push-back takes to act through delays and motor lag)
    att_bias_window_s: float = 0.25
    #: per axis; both at once tilt about 10 deg, and the cycle still clears the noise the
    #: raise rule asks for
    att_amp_max_rad: float = 0.12
    att_bias_min: float = 0.2
    #: a larger mean torque is no centre-of-mass offset (3 % of the arm is 0.01-0.05) but a
    #: disturbed period, and is not taken as the bias
    att_bias_max: float = 0.1
    #: roll/pitch: before it is sized, the relay is centred on the torque bias fitted to its
    #: first swings (from lift-off by ``att_centre_z_m``) where the fit explains this share
    #: of the rate's variance (0: off) and pins the bias within ``att_centre_se`` of h
    att_centre_r2: float = 0.9
    att_centre_se: float = 0.03
    att_centre_z_m: float = 0.02
    #: ... and its h is lowered before the first period where the fit predicts a swing over
    #: this (rad, per axis; 0: off): both relays swing at once, so 1.5 x
    #: ``att_amp_max_rad`` keeps the tilt near 60 % of a 35 deg limit
    att_pred_amp_rad: float = 0.18
    #: later periods may resize a relay this many times (each restarts its detection)
    att_max_resizes: int = 3
    #: a resized relay restarts once its axis is within this share of the expected cycle's
    #: amplitude and peak rate (for three periods at most; then the run-away catch's full
    #: envelope): a relay restarted off its set point swings out to twice its cycle and can
    #: lock into a lopsided cycle
    att_restart_envelope: float = 0.1
    #: ... except a relay whose h only shrinks (its bias kept): the smaller h is taken at the
    #: turn of the axis its period or swing ended on, with no restart. A restart waited
    #: 0.9 s on average (up to three periods) for the catch to bring the axis to rest
    att_resize_at_turn: bool = True
    #: roll/pitch: a change of the set point (the bounding relay's 0.05 rad steps) reaches a
    #: running relay at its next switch into the half-cycle whose swing it enlarges
    #: (:meth:`~mrft_gcs.flight.phases.attitude.AttitudeRelays.step`); False: at once, as
    #: it was, which switched the relay early into short cycles that cost a run-away catch
    #: and the relay's steady periods
    att_ref_at_switch: bool = True
    #: the same for the x/y relays (tilt, rad): the side classifiers' own value. Each side
    #: relay switch steps the attitude set point by 2 h, which the freshly tuned attitude PD
    #: overshoots; a larger h tilts the vehicle further under ground-station stalls. A
    #: noisy position estimate raises it (``h_raise``)
    h_side_min: float = 0.08
    #: gain of the complementary filter (position + velocity) on x, y and altitude for the
    #: relays and their identification (1 = raw position)
    side_filter_k: float = 0.05
    #: before a side relay starts, the axis is brought to rest by a soft PD (tilt per m and
    #: per m/s) until its speed is below ``settle_speed_m_s`` (at most ``settle_max_s``); the
    #: relay then oscillates about that point: an MRFT on the side cascade started off its
    #: centre or moving can lock into a slow, drifting cycle the classifier never saw
    settle_pd: tuple[float, float] = (0.3, 0.4)
    settle_speed_m_s: float = 0.03
    settle_max_s: float = 2.0
    #: largest tilt command of that soft PD (rad): an axis is handed to it from the bounding
    #: relay as soon as its attitude loop is tuned, possibly moving at 1 m/s, which unclipped
    #: is a large step on the freshly tuned attitude PD while the other axis still runs its
    #: relay (the bounding relay itself commands at most 0.1 rad)
    settle_max_tilt_rad: float = 0.1
    #: a side relay starts on its high level (:meth:`~mrft_gcs.flight.phases.side.
    #: SideRelays.step`): its first cycle is counted from half a period after the start
    #: instead of a whole one; False: on the sign of its first error
    side_start_high: bool = True

    def cycle_rules(self, loop: Loop) -> CycleRules:
        """When ``loop``'s relay cycles are steady and how many are identified."""
        i = _KINDS.index(loop.kind)
        n = self.identify_cycles
        if loop.kind is not LoopKind.ATTITUDE:
            n = min(n, self.identify_cycles_alt_side[i - 1])
        return CycleRules(n_periods=self.steady_periods[i], identify_cycles=n,
                          period_tol=self.period_tol, relax_after=self.relax_after_cycles[i],
                          relaxed_tol=self.relaxed_tol)
