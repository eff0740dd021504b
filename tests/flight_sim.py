"""Test helpers: fly a TuningSequence on the in-process SimVehicle, and a truth identifier.

The flight is :class:`mrft_gcs.flight.driver.SequenceDriver` over
:class:`mrft_gcs.sitl.lockstep.LockstepVehicle`, the code a live tune and a replay run.
``truth_identifier`` (from :mod:`mrft_gcs.sitl.lockstep`) is a test double, not a
classifier: it returns the airframe's true linear model with its optimal PD, so the
sequence, the hand-over to PDs, the side tests and the write-back can be tested before the
bundled classifiers exist.
"""

from __future__ import annotations

import functools
import math
import sys
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import numpy as np

from mrft_gcs.flight.driver import SequenceDriver
from mrft_gcs.flight.sequence import Phase, SequenceConfig, TuningSequence
from mrft_gcs.flight.source import VehicleMode
from mrft_gcs.flight.timeliness import HostTooSlow
from mrft_gcs.loops import LoopKind
from mrft_gcs.sitl import SimVehicle, load_airframe
from mrft_gcs.sitl.lockstep import (
    TRUTH_RELAYS,
    LockstepVehicle,
    PeriodicStalls,
    state_of,
    truth_identifier,
)

#: Relay settings of the tests (the truth identifier ignores the cycle)
ATT_RELAY = TRUTH_RELAYS[LoopKind.ATTITUDE]
ALT_RELAY = TRUTH_RELAYS[LoopKind.ALTITUDE]
SIDE_RELAY = TRUTH_RELAYS[LoopKind.SIDE]


T = TypeVar("T")


def lockstep_with_events(monkeypatch, seed: int, **cfg) -> tuple[dict, list[str]]:
    """The population benchmark's lockstep tune of random vehicle ``seed`` (its link delays)
    with ``cfg`` overriding the sequence's defaults; its record and the sequence's events."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import tune_population as tp

    seqs: list[TuningSequence] = []

    def sequence(*args, **kw):
        seqs.append(TuningSequence(*args, **kw))
        return seqs[-1]

    monkeypatch.setattr(tp, "SequenceConfig", functools.partial(SequenceConfig, **cfg))
    monkeypatch.setattr(tp, "TuningSequence", sequence)
    return tp.run_lockstep(seed), seqs[0].events


def again_if_host_stalled(flight: Callable[[], T]) -> T:
    """Run ``flight`` (a live tune on a fresh SITL); where the tool refused because this
    machine starved its loop (:class:`HostTooSlow`, the right answer on a busy host, and
    not what the test is about), warn and fly it once more. A second refusal fails."""
    try:
        return flight()
    except HostTooSlow as err:
        warnings.warn(f"the host stalled the live loop, flying once more: {err}", stacklevel=2)
        return flight()


def fly(seq: TuningSequence, vehicle: str = "qdrone", seed: int = 0, max_s: float = 40.0,
        identifier=None, hover_s: float = 2.0, effects=None, stalls=None):
    """Run the sequence at 250 Hz on the in-process vehicle; returns (vehicle, max tilt deg).

    ``stalls=(ms, every_s)``: the ground station stalls now and then (a busy machine, a
    Wi-Fi hiccup) for up to ``ms`` (uniform 50-100 % of it) about every ``every_s``
    (50-150 % of it); the vehicle keeps the last setpoint meanwhile, as an autopilot
    does. Drawn from ``seed``. Identifications that were retried are in ``seq.retries``
    as (loop, error text).
    """
    af = load_airframe(vehicle)
    if effects:
        af = af.with_effects(effects)
    v = SimVehicle(af, seed=seed)
    src = LockstepVehicle(v, stalls=PeriodicStalls(stalls[0], stalls[1],
                                                   np.random.default_rng(seed))
                          if stalls else None)
    drv = SequenceDriver(seq, identifier or truth_identifier(vehicle),
                         relay={LoopKind.SIDE: SIDE_RELAY})
    seq.retries = drv.retries  # type: ignore[attr-defined]
    src.send(drv.idle)
    src.set_mode(VehicleMode.OFFBOARD)
    src.arm()
    max_tilt = 0.0
    t_done = math.inf

    def tilt(s, _sp) -> None:
        nonlocal max_tilt
        max_tilt = max(max_tilt, math.degrees(s.tilt_rad))

    def stop(_s) -> bool:
        nonlocal t_done
        if seq.phase is Phase.HOVER and not math.isfinite(t_done):
            t_done = v.time_s
        return v.time_s > t_done + hover_s or v.time_s >= max_s

    # 0.4 s on the ground: the noise that sets the relay bands
    drv.run(src, ground_until_s=v.time_s + 0.4, stop=stop, on_tick=tilt)
    return v, max_tilt


__all__ = ["truth_identifier", "fly", "state_of", "ATT_RELAY", "ALT_RELAY", "SIDE_RELAY", "np"]


def fly_roll_check(v, hover_thrust: float, gains, model, level_ticks: int = 125):
    """The in-air check of roll gains ``gains`` (a PD) flown on an in-process vehicle ``v``
    (its physics and onboard PX4-style cascade; telemetry and set points at 250 Hz), after
    ``level_ticks`` level ticks; the plan predicts on ``model``. Returns ``(plan, check)``."""
    from mrft_gcs.flight.inair import (
        CHECK_AMPLITUDE_RAD,
        SquareWaveProbe,
        check_margin,
        plan_check,
    )
    from mrft_gcs.loops import Loop
    from mrft_gcs.sitl.onboard import FlightMode
    from mrft_gcs.sitl.physics import quat_from_euler

    v.reset((0.0, 0.0, -3.0), airborne=True)
    ap = v.autopilot
    for name, value in {"MC_ROLL_P": gains.Kc / gains.Kd, "MC_ROLLRATE_P": gains.Kd,
                        "MC_ROLLRATE_I": 0.0, "MC_ROLLRATE_D": 0.0,
                        "MC_ROLLRATE_K": 1.0}.items():
        assert ap.params.set(name, value)
    level = quat_from_euler(0.0, 0.0, 0.0)
    ap.set_attitude_target(level, hover_thrust)
    ap.set_mode(FlightMode.OFFBOARD)
    ap.arm(True)
    for _ in range(level_ticks):
        ap.set_attitude_target(level, hover_thrust)
        v.run(0.004)
    plan = plan_check(model, gains, CHECK_AMPLITUDE_RAD)
    probe = SquareWaveProbe({Loop.ROLL: plan})
    while not probe.done:
        att = v.physics.meas_att
        r, p = probe.step(v.time_s, v.time_s, att[0], att[1])
        ap.set_attitude_target(quat_from_euler(r, p, 0.0), hover_thrust)
        v.run(0.004)
    return plan, check_margin(plan, *probe.points()[Loop.ROLL])


def identified_side(af, loop, inner):
    """A side loop of airframe ``af`` as identified behind the ground station's attitude PD
    (``inner``'s gains): its true model with the optimal PD on that cascade."""
    from mrft_gcs.identify import Identification
    from mrft_gcs.loops import LoopKind
    from mrft_gcs.pd_design import frequency_grid, optimal_pd
    from mrft_gcs.plant import SideModel, closed_inner_response, inner_response, side_response

    ms = af.linear_models()[loop.value]
    sm, mi = SideModel(ms["K"], ms["T2"], ms["tau"]), inner.model
    w = frequency_grid(mi.T_prop, mi.T1, mi.tau, extra_T=(sm.T2, sm.tau))
    gi = inner_response(mi.K, mi.T_prop, mi.T1, mi.tau, w)
    G = (closed_inner_response(inner.gains.Kc, inner.gains.Kd, gi, w)
         * side_response(sm.K, sm.T2, sm.tau, w))[0]
    return Identification(LoopKind.SIDE, sm, 0, 1.0, -0.8, 0.1, 1.0, 0.1, optimal_pd(G, w).pd)
