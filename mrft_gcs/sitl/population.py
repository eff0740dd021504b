"""A population of simulated vehicles: airframes drawn at random from a seed.

:func:`random_airframe` draws one multirotor across and a little beyond the paper's
Table I (30 g to 3 kg, peak thrust-to-weight 1.8-6, motor lag 10-80 ms), built from its
physics so that it stays sensible: arm length grows with mass, inertia is ``m l^2`` times
a shape factor, drag follows from the time constants drawn for it. Each vehicle also
draws how its delay splits between actuator, attitude sensor, position sensor and link,
how fast it streams telemetry (50-500 Hz), its onboard loop structure (PX4-like or
ArduPilot-like) and rates (250 Hz-1 kHz), a misestimated hover thrust, a centre-of-mass
bias, and in about a third of the draws one undeclared effect.

:func:`domain_check` says whether a vehicle lies in Table I's domain (its true linear
models in the boxes of :mod:`mrft_gcs.domains`, thrust-to-weight in 1.5-5, telemetry of
200 Hz or more as a relay test needs), so a
benchmark can count in-domain vehicles tuned and out-of-domain ones refused.

>>> a, b = random_airframe(7), random_airframe(7)
>>> a == b
True
>>> 0.03 <= a.mass_kg <= 3.0
True
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from mrft_gcs.domains import D_ALT, D_ATT, D_SIDE
from mrft_gcs.errors import UsageError
from mrft_gcs.sitl.airframe import GRAVITY_M_S2, Airframe, Effects, OnboardSpec

__all__ = ["random_airframe", "domain_check", "DomainCheck", "MASS_RANGE_KG",
           "THRUST_TO_WEIGHT_RANGE", "MOTOR_TAU_RANGE_S", "TELEMETRY_RANGE_HZ",
           "LOOP_RATES_HZ", "TABLE1_THRUST_TO_WEIGHT", "RELAY_TELEMETRY_HZ"]

MASS_RANGE_KG = (0.03, 3.0)
THRUST_TO_WEIGHT_RANGE = (1.8, 6.0)
MOTOR_TAU_RANGE_S = (0.010, 0.080)
TELEMETRY_RANGE_HZ = (50.0, 500.0)
#: onboard attitude loop rates: whole numbers of 1 ms physics steps
LOOP_RATES_HZ = (250.0, 1000.0 / 3.0, 500.0, 1000.0)
#: Table I's peak thrust-to-weight range
TABLE1_THRUST_TO_WEIGHT = (1.5, 5.0)
#: telemetry a relay test needs (mrft_gcs.link.quality.require_relay_capable's default)
RELAY_TELEMETRY_HZ = 200.0
#: share of draws with one undeclared effect
_EFFECT_SHARE = 0.3


def _logu(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def _effect(rng: np.random.Generator, mass_kg: float) -> dict[str, float]:
    """One undeclared effect with a value that matters but leaves the vehicle flyable."""
    name = str(rng.choice(["sensor_lpf", "torque_rate_limit", "motor_saturation",
                           "quadratic_drag", "thrust_curve", "motor_deadzone"]))
    value = {
        "sensor_lpf": _logu(rng, 8.0, 40.0),              # Hz
        "torque_rate_limit": _logu(rng, 4.0, 30.0),       # 1/s
        "motor_saturation": rng.uniform(0.85, 0.97),
        "quadratic_drag": mass_kg * _logu(rng, 0.05, 0.3),  # N s^2/m^2
        "thrust_curve": rng.uniform(0.2, 0.7),
        "motor_deadzone": rng.uniform(0.005, 0.04),
    }[name]
    return {name: round(float(value), 4)}


def random_airframe(seed: int) -> Airframe:
    """A random multirotor, the same for the same ``seed``.

    Parameters
    ----------
    seed : int
        Non-negative; every draw is a pure function of it.

    Returns
    -------
    Airframe
        Named ``random-SEED``, validated; :func:`domain_check` tells whether it is in
        Table I's domain.

    Raises
    ------
    UsageError
        A negative seed.
    """
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise UsageError(f"random vehicle seed {seed!r}: use a whole number >= 0")
    rng = np.random.default_rng([0x5EED, int(seed)])
    m = _logu(rng, *MASS_RANGE_KG)
    frame = "hexa_x" if m > 1.2 and rng.random() < 0.4 else "quad_x"
    # size follows mass (about 0.11 m across at 30 g, 0.52 m at 3 kg)
    arm = 0.18 * m ** (1.0 / 3.0) * _logu(rng, 0.8, 1.25)
    ix = m * arm * arm * _logu(rng, 0.18, 0.4)  # motors and arms dominate the moment
    iy = ix * _logu(rng, 0.85, 1.15)
    iz = (ix + iy) * _logu(rng, 0.8, 1.0)
    tw = _logu(rng, *THRUST_TO_WEIGHT_RANGE)
    # bigger propellers spin up slower, with a wide spread for motor and ESC choice
    motor_tau = float(np.clip(0.02 * (m / 0.03) ** 0.15 * _logu(rng, 0.6, 2.0),
                              *MOTOR_TAU_RANGE_S))
    t1 = _logu(rng, 0.18, 2.2)        # roll/pitch inertia over rotational drag, s
    t1_alt = _logu(rng, 0.18, 2.2)    # mass over vertical drag, s
    t2 = _logu(rng, 0.18, 6.6)        # mass over horizontal drag, s
    rot_drag = (ix / t1, iy / (t1 * _logu(rng, 0.9, 1.1)), iz / _logu(rng, 0.3, 2.0))
    lin_drag = (m / t2, m / (t2 * _logu(rng, 0.9, 1.1)), m / t1_alt)
    # delays: ESC and motor protocol; IMU filtering; position estimate on top of it; link
    act = _logu(rng, 0.001, 0.015)
    att = _logu(rng, 0.0005, 0.012)
    pos = att + _logu(rng, 0.003, 0.12)
    link = float(rng.uniform(0.0, 0.012))
    # most links carry a relay test (>= 200 Hz), some do not and must be refused
    lo, hi = TELEMETRY_RANGE_HZ
    telemetry = float(round(_logu(rng, RELAY_TELEMETRY_HZ, hi) if rng.random() < 0.8
                            else _logu(rng, lo, RELAY_TELEMETRY_HZ)))
    style = "ardupilot" if rng.random() < 0.5 else "px4"
    loop_hz = float(rng.choice(LOOP_RATES_HZ))
    pos_every = int(rng.choice([k for k in (1, 2, 4, 5) if loop_hz / k >= 50.0]))
    if style == "ardupilot":
        # ArduCopter runs its position controller in the main loop, beside the rate loop
        # (SCHED_LOOP_RATE): drawn all the same, so that the draws after it stay the seed's
        pos_every = 1
    onboard = OnboardSpec(
        style=style, loop_hz=loop_hz, position_loop_hz=loop_hz / pos_every,
        dgyro_cutoff_hz=round(_logu(rng, 15.0, 60.0) if style == "px4"
                              else _logu(rng, 10.0, 40.0), 1),
        target_cutoff_hz=round(_logu(rng, 10.0, 40.0), 1) if style == "ardupilot" else 0.0,
        accel_max_rad_s2=round(_logu(rng, 6.0, 31.0), 1) if style == "ardupilot" else 0.0)
    hover_factor = _logu(rng, 0.8, 1.25)
    # centre of mass off the thrust centre by up to 3 % of the arm: a constant torque
    com = (rng.uniform(-0.03, 0.03) * arm, rng.uniform(-0.03, 0.03) * arm)
    effects = _effect(rng, m) if rng.random() < _EFFECT_SHARE else {}
    noise = (_logu(rng, 0.002, 0.01), _logu(rng, 0.0004, 0.002), _logu(rng, 0.0005, 0.005),
             _logu(rng, 0.002, 0.01))
    af = Airframe(
        name=f"random-{seed}", frame=frame, mass_kg=m, inertia_kg_m2=(ix, iy, iz),
        arm_length_m=arm, motor_tau_s=motor_tau, thrust_to_weight=tw,
        yaw_moment_per_thrust_m=0.08 * arm * _logu(rng, 0.8, 1.25),
        rot_drag_n_m_s_rad=rot_drag, lin_drag_n_s_m=lin_drag,
        actuator_delay_s=act, attitude_sensor_delay_s=att, position_sensor_delay_s=pos,
        gyro_noise_rad_s=noise[0], attitude_noise_rad=noise[1], position_noise_m=noise[2],
        velocity_noise_m_s=noise[3], onboard=onboard, link_delay_s=link,
        telemetry_max_hz=telemetry, hover_estimate_factor=hover_factor,
        effects=Effects().updated(effects))
    mx, my, _ = af.max_moments_n_m
    weight = m * GRAVITY_M_S2
    bias = (float(np.clip(weight * com[1] / mx, -0.5, 0.5)),
            float(np.clip(-weight * com[0] / my, -0.5, 0.5)), 0.0)
    af = dataclasses.replace(af, torque_bias=bias)
    af = dataclasses.replace(af, description=_describe(af))
    af.validate()
    return af


def _describe(af: Airframe) -> str:
    ob = af.onboard
    eff = ", ".join(f"{k}={v:g}" for k, v in af.effects.active().items())
    return (f"random {af.frame} {af.mass_kg * 1e3:.0f} g, T/W {af.thrust_to_weight:.2f}, "
            f"motor {af.motor_tau_s * 1e3:.0f} ms, {ob.style}-like onboard at "
            f"{ob.loop_hz:.0f}/{ob.position_loop_hz:.0f} Hz, link {af.link_delay_s * 1e3:.1f} "
            f"ms, telemetry <= {af.telemetry_max_hz:.0f} Hz"
            + (f", undeclared {eff}" if eff else ""))


@dataclass(frozen=True)
class DomainCheck:
    """Whether a vehicle lies in Table I's domain.

    Attributes
    ----------
    in_domain : bool
        Every true linear model in its Table I box, thrust-to-weight in 1.5-5, and
        telemetry fast enough for a relay test (200 Hz).
    reasons : tuple of str
        What lies outside (empty when in the domain).
    effects : tuple of str
        Undeclared effects switched on (not part of the domain test).
    """

    in_domain: bool
    reasons: tuple[str, ...]
    effects: tuple[str, ...]

    @property
    def category(self) -> str:
        """``in-domain``, ``out-of-domain`` or ``hidden-effect`` (in the domain, with one)."""
        if not self.in_domain:
            return "out-of-domain"
        return "hidden-effect" if self.effects else "in-domain"


def domain_check(af: Airframe) -> DomainCheck:
    """Check ``af``'s true linear models against Table I (:mod:`mrft_gcs.domains`).

    >>> from mrft_gcs.sitl import load_airframe
    >>> domain_check(load_airframe("qdrone")).in_domain
    True
    """
    models = af.linear_models()
    reasons: list[str] = []
    for loop, dom in (("roll", D_ATT), ("pitch", D_ATT), ("altitude", D_ALT), ("x", D_SIDE),
                      ("y", D_SIDE)):
        m = models[loop]
        for name, lo, hi in zip(dom.names, dom.low, dom.high, strict=True):
            v = m[name]
            if not lo * (1 - 1e-9) <= v <= hi * (1 + 1e-9):
                reasons.append(f"{loop} {name} {v * 1e3:.1f} ms outside "
                               f"{lo * 1e3:g}-{hi * 1e3:g} ms")
    lo, hi = TABLE1_THRUST_TO_WEIGHT
    if not lo <= af.thrust_to_weight <= hi:
        reasons.append(f"thrust/weight {af.thrust_to_weight:.2f} outside {lo:g}-{hi:g}")
    if af.telemetry_max_hz < RELAY_TELEMETRY_HZ:
        reasons.append(f"telemetry {af.telemetry_max_hz:.0f} Hz, under the "
                       f"{RELAY_TELEMETRY_HZ:g} Hz a relay test needs")
    return DomainCheck(not reasons, tuple(reasons), tuple(af.effects.active()))
