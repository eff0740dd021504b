"""Test helpers: fly a TuningSequence on the in-process SimVehicle, and a truth identifier.

``truth_identifier`` is a test double, not a classifier: it ignores the cycle and returns
the airframe's true linear model with its optimal PD, so the sequence, the hand-over to
PDs, the side tests and the write-back can be tested before the bundled classifiers exist.
"""

from __future__ import annotations

import math

import numpy as np

from mrft_gcs.errors import IdentificationError, SetpointNotCrossed
from mrft_gcs.flight.controllers import FlightState
from mrft_gcs.flight.scoring import true_response
from mrft_gcs.flight.sequence import Phase, TuningSequence
from mrft_gcs.identify import Identification, RelaySettings
from mrft_gcs.identify.live import measured_attitude_loop
from mrft_gcs.loops import Loop, LoopKind
from mrft_gcs.pd_design import optimal_pd
from mrft_gcs.plant import InnerModel, SideModel
from mrft_gcs.profiles import Actuation
from mrft_gcs.sitl import SimVehicle, load_airframe
from mrft_gcs.sitl.onboard import FlightMode
from mrft_gcs.telemetry import AttitudeTarget

#: Relay settings of the tests (the truth identifier ignores the cycle): the bundled
#: classifiers' beta, so the tests fly the cycles a real tune flies.
ATT_RELAY = RelaySettings(beta=-0.7, h=0.05)
ALT_RELAY = RelaySettings(beta=-0.7, h=0.10746)
SIDE_RELAY = RelaySettings(beta=-0.7, h=0.08)


def truth_identifier(vehicle: str):
    """``f(loop, snapshot, inner_ident) -> Identification`` from the true models."""
    models = load_airframe(vehicle).linear_models()

    def ident(loop: Loop, snap, inner: Identification | None = None) -> Identification:
        m = models[loop.value]
        if loop in (Loop.X, Loop.Y):
            G, w = true_response(models, loop, inner.gains if inner else None)
            model = SideModel(m["K"], m["T2"], m["tau"])
            kind = LoopKind.SIDE
        else:
            G, w = true_response(models, loop)
            model = InnerModel(m["K"], m["T_prop"], m["T1"], m["tau"])
            kind = LoopKind.ATTITUDE if loop in (Loop.ROLL, Loop.PITCH) else LoopKind.ALTITUDE
        pd = optimal_pd(G, w).pd
        return Identification(kind, model, 0, 1.0, snap.beta, snap.h, snap.status.period_s,
                              snap.status.amplitude, pd)

    return ident


def state_of(v: SimVehicle) -> FlightState:
    a, p = v.physics.meas_att, v.physics.meas_posv
    t = v.time_s
    return FlightState(t, a[0], a[1], a[2], a[3], a[4], a[5], t, p[0], p[1], -p[2], p[3], p[4],
                       -p[5])


def fly(seq: TuningSequence, vehicle: str = "qdrone", seed: int = 0, max_s: float = 40.0,
        identifier=None, hover_s: float = 2.0, effects=None, stalls=None):
    """Run the sequence at 250 Hz on the in-process vehicle; returns (vehicle, max tilt deg).

    ``stalls=(ms, every_s)``: the ground station stalls now and then (a busy machine, a
    Wi-Fi hiccup) for up to ``ms`` (uniform 50-100 % of it) about every ``every_s``
    (50-150 % of it); the vehicle keeps the last setpoint meanwhile, as an autopilot
    does. Drawn from ``seed``.
    """
    af = load_airframe(vehicle)
    if effects:
        af = af.with_effects(effects)
    v = SimVehicle(af, seed=seed)
    ident = identifier or truth_identifier(vehicle)
    ap = v.autopilot
    ap.set_actuator_controls(0, 0, 0, 0)
    assert ap.set_mode(FlightMode.OFFBOARD).name == "ACCEPTED"
    ap.arm(True)
    for _ in range(100):  # 0.4 s on the ground: the noise that sets the relay bands
        v.run(0.004)
        seq.observe(state_of(v))
    seq.start(state_of(v))
    max_tilt = 0.0
    t_done = math.inf
    rng = np.random.default_rng(seed)
    next_stall = stalls[1] if stalls else math.inf
    retries = getattr(seq, "retries", None)
    if retries is None:
        retries = seq.retries = []  # (loop, error) of identifications that were retried
    while v.time_s < max_s:
        s = state_of(v)
        sp = seq.step(s)
        max_tilt = max(max_tilt, math.degrees(s.tilt_rad))
        if isinstance(sp, AttitudeTarget):  # attitude path: the autopilot's attitude loop
            ap.set_attitude_target(sp.q_wxyz, sp.thrust)
        else:
            ap.set_actuator_controls(sp.roll, sp.pitch, sp.yaw, sp.thrust)
        for snap in seq.ready():
            inner = None
            try:
                if snap.loop in (Loop.X, Loop.Y):
                    inner = seq.loops[Loop.PITCH if snap.loop is Loop.X else
                                      Loop.ROLL].identification
                    if inner is None and seq.config.actuation is Actuation.ATTITUDE:
                        inner = measured_attitude_loop(snap)
                seq.apply(snap.loop, ident(snap.loop, snap, inner))
            except IdentificationError as err:  # as the tune does: wait for the next cycles
                retries.append((snap.loop, str(err)))
                seq.retry(snap.loop, restart=isinstance(err, SetpointNotCrossed))
        if seq.side_waiting:
            seq.start_side({Loop.X: SIDE_RELAY, Loop.Y: SIDE_RELAY})
        if seq.phase is Phase.HOVER and not math.isfinite(t_done):
            t_done = v.time_s
        if v.time_s > t_done + hover_s:
            break
        ticks = 4
        if v.time_s > next_stall:
            ticks = 4 * max(1, int(stalls[0] / 4 * rng.uniform(0.5, 1.0)))
            next_stall = v.time_s + stalls[1] * rng.uniform(0.5, 1.5)
        for _ in range(ticks):
            v.step()
    return v, max_tilt


__all__ = ["truth_identifier", "fly", "state_of", "ATT_RELAY", "ALT_RELAY", "SIDE_RELAY", "np"]
