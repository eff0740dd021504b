"""An independent physics backend for the SITL: the rigid body, rotors and motors of RotorPy.

RotorPy (Folk et al., MIT licence, ``pip install rotorpy==3.0.0``, in the ``test`` extra)
is a maintained multirotor simulator written by another team. With ``--physics rotorpy``
the SITL keeps its own onboard software (:mod:`mrft_gcs.sitl.onboard`), sensor delays,
noise, link and MAVLink server, and replaces :class:`mrft_gcs.sitl.physics.Multirotor`
with :class:`RotorpyMultirotor`: RotorPy's ``Multirotor.step`` integrates its 6-DOF body,
first-order rotor-speed lag, thrust ``k_eta w^2``, rotor drag and induced inflow
(``k_d``, ``k_z``), parasitic drag, translational lift and its ground contact, from one of
RotorPy's own parameter sets (:data:`ROTORPY_VEHICLES`).

Commands map as the bundled physics defines them: collective thrust 1 is every rotor at
``rotor_speed_max``, a torque command 1 the largest moment about that axis (half the rotors
at full thrust, half at zero), handed to RotorPy as collective thrust and body moments
(its ``cmd_ctbm`` abstraction, which allocates them to rotor speeds and clips those).
Frames: RotorPy's world is z up and its body x forward, y left, z up; both turn into NED /
FRD by a half turn about x.

The truth a tune is scored on is :func:`rotorpy_airframe`'s ``airframe``: an
:class:`~mrft_gcs.sitl.airframe.Airframe` whose linear models are RotorPy's dynamics
linearised at hover (rotor drag and inflow give the rotational and translational damping,
the rotor lag the propulsion time constant); it also carries the project's side of the
vehicle (delays, noise, onboard loop structure and rates).

>>> spec = rotorpy_airframe("crazyfliebrushless")      # doctest: +SKIP
>>> round(spec.airframe.linear_models()["roll"]["T1"], 3)  # doctest: +SKIP
0.46
"""

from __future__ import annotations

import dataclasses
import importlib
import math
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

import numpy as np

from mrft_gcs.errors import MissingDependency, UsageError
from mrft_gcs.sitl.airframe import Airframe, OnboardSpec
from mrft_gcs.sitl.physics import Multirotor, _Delay, quat_from_euler, shaped_torques

__all__ = ["ROTORPY_VEHICLES", "DEFAULT_ROTORPY_VEHICLE", "PHYSICS_BACKENDS", "RotorpySpec",
           "rotorpy_airframe", "rotorpy_params", "RotorpyMultirotor", "rotorpy_vehicle",
           "ROTORPY_PIN"]

#: the release this backend is written and checked against (the ``test`` extra pins it)
ROTORPY_PIN = "3.0.0"
#: RotorPy's own quadrotor parameter sets this backend flies (``rotorpy.vehicles.NAME_params``)
ROTORPY_VEHICLES = ("crazyfliebrushless", "crazyflie", "hummingbird")
DEFAULT_ROTORPY_VEHICLE = "crazyfliebrushless"
#: ``native``: the project's own physics (the default); ``rotorpy``: this module
PHYSICS_BACKENDS = ("native", "rotorpy")
#: effects applied to the commands or the sensors, which any physics can carry
_EFFECTS_OK = frozenset({"sensor_lpf", "torque_rate_limit", "motor_deadzone"})
_GROUND_Z_M = 0.001  # RotorPy's own ground test (z up)
#: onboard loop rate and physics step: two evaluations of RotorPy's dynamics cost 0.2-0.5 ms
#: of CPU, so 250 Hz is what keeps a real-time SITL beside a GCS on a shared host
_LOOP_HZ = 250.0


def _rotorpy(module: str) -> Any:
    try:
        return importlib.import_module(f"rotorpy.{module}")
    except ImportError as exc:
        raise MissingDependency(
            f"--physics rotorpy needs RotorPy ({exc.name or 'rotorpy'} is missing): "
            f"pip install 'mrft-gcs[test]' (or rotorpy=={ROTORPY_PIN})") from None


def rotorpy_params(name: str) -> dict[str, Any]:
    """A copy of RotorPy's parameter set ``name`` (``quad_params`` of its module).

    Raises
    ------
    UsageError
        ``name`` is not one of :data:`ROTORPY_VEHICLES`.
    MissingDependency
        RotorPy is not installed.
    """
    if name not in ROTORPY_VEHICLES:
        raise UsageError(f"unknown RotorPy vehicle '{name}'; with --physics rotorpy use one of "
                         f"{', '.join(ROTORPY_VEHICLES)}")
    src = _rotorpy(f"vehicles.{name}_params").quad_params
    out = dict(src)
    out["rotor_pos"] = {k: np.array(v, dtype=float) for k, v in src["rotor_pos"].items()}
    return out


@dataclass(frozen=True)
class RotorpySpec:
    """One RotorPy vehicle: its parameters and the matching :class:`Airframe`.

    Attributes
    ----------
    name : str
        RotorPy parameter set (``crazyfliebrushless``, ...).
    params : Mapping
        RotorPy's ``quad_params`` as flown (scaled where a seed drew it).
    airframe : Airframe
        Hover linearisation of ``params`` (the truth for scoring) and the project's side of
        the vehicle: delays, noise, link, onboard loop structure and rates.
    """

    name: str
    params: Mapping[str, Any]
    airframe: Airframe


def _hover_speed(p: Mapping[str, Any]) -> float:
    """Rotor speed that holds the weight, rad/s (RotorPy's own g)."""
    return math.sqrt(p["mass"] * 9.81 / (p["num_rotors"] * p["k_eta"]))


def _geometry(p: Mapping[str, Any]) -> np.ndarray:
    pos = np.array([np.asarray(v, float) for v in p["rotor_pos"].values()])
    if p["num_rotors"] != 4 or pos.shape != (4, 3) or not np.allclose(
            np.abs(pos[:, 0]), np.abs(pos[:, 1]), rtol=1e-6) or np.any(pos[:, 2] != 0):
        raise UsageError("the RotorPy backend flies quad-X parameter sets (4 rotors at 45 deg "
                         "in the rotor plane)")
    return pos


def _linearised(p: Mapping[str, Any]) -> dict[str, Any]:
    """Airframe fields from RotorPy's model at hover (small signal, FRD)."""
    pos = _geometry(p)
    n = int(p["num_rotors"])
    w0 = _hover_speed(p)
    kd, kz = float(p.get("k_d", 0.0)), float(p.get("k_z", 0.0))
    sx2, sy2 = float(np.sum(pos[:, 0] ** 2)), float(np.sum(pos[:, 1] ** 2))
    f_max = p["k_eta"] * p["rotor_speed_max"] ** 2
    # induced inflow k_z on the rotor's vertical airspeed (w x r) damps roll and pitch;
    # rotor drag k_d on its in-plane airspeed damps yaw and horizontal motion
    rot = (w0 * kz * sy2, w0 * kz * sx2, w0 * kd * (sx2 + sy2))
    lin = (n * w0 * kd, n * w0 * kd, n * w0 * kz)
    if min(rot + lin) <= 0:
        raise UsageError("this RotorPy parameter set has no rotor drag or inflow (k_d, k_z): "
                         "its hover has no damping, so it has no linear model to score on")
    from mrft_gcs.sitl.airframe import GRAVITY_M_S2

    return {
        "frame": "quad_x", "mass_kg": float(p["mass"]),
        "inertia_kg_m2": (float(p["Ixx"]), float(p["Iyy"]), float(p["Izz"])),
        "arm_length_m": float(np.linalg.norm(pos[0])), "motor_tau_s": float(p["tau_m"]),
        # per-motor peak thrust exactly k_eta w_max^2 (the project's g, not RotorPy's)
        "thrust_to_weight": n * f_max / (p["mass"] * GRAVITY_M_S2),
        "yaw_moment_per_thrust_m": float(p["k_m"] / p["k_eta"]),
        "rot_drag_n_m_s_rad": rot, "lin_drag_n_s_m": lin,
    }


def _logu(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def rotorpy_airframe(name: str | None = None, seed: int | None = None) -> RotorpySpec:
    """RotorPy's parameter set ``name`` with the project's delays, noise and onboard loops.

    Parameters
    ----------
    name : str, optional
        One of :data:`ROTORPY_VEHICLES`; default :data:`DEFAULT_ROTORPY_VEHICLE`, or, with a
        seed, the set ``ROTORPY_VEHICLES[seed % 3]``.
    seed : int, optional
        Draw the vehicle from this seed: mass and inertia scaled together (0.85-1.2),
        rotor lag (0.8-1.25) and top speed (0.95-1.05) around the set's values, and
        the project's side as :func:`mrft_gcs.sitl.random_airframe` draws it (delay split,
        link, telemetry 200-500 Hz, PX4- or ArduPilot-like onboard at 250 Hz, noise,
        hover misestimate); no undeclared effects. ``None``: the set as shipped, a PX4-like
        onboard at 250 Hz and fixed small delays.

    Raises
    ------
    UsageError
        Unknown name or a negative seed.
    MissingDependency
        RotorPy is not installed.
    """
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int | np.integer)
                             or seed < 0):
        raise UsageError(f"random vehicle seed {seed!r}: use a whole number >= 0")
    if name is None:
        name = DEFAULT_ROTORPY_VEHICLE if seed is None else ROTORPY_VEHICLES[seed % 3]
    p = rotorpy_params(name)
    if seed is None:
        extra: dict[str, Any] = dict(
            name=f"rotorpy-{name}", actuator_delay_s=0.004, attitude_sensor_delay_s=0.002,
            position_sensor_delay_s=0.012, gyro_noise_rad_s=0.004, attitude_noise_rad=0.0008,
            position_noise_m=0.0008, velocity_noise_m_s=0.004,
            onboard=OnboardSpec(style="px4", loop_hz=_LOOP_HZ, position_loop_hz=_LOOP_HZ))
    else:
        rng = np.random.default_rng([0x0707, int(seed)])
        s = _logu(rng, 0.85, 1.2)
        p["mass"] *= s
        for k in ("Ixx", "Iyy", "Izz"):
            p[k] *= s
        p["tau_m"] *= _logu(rng, 0.8, 1.25)
        p["rotor_speed_max"] *= rng.uniform(0.95, 1.05)
        att = _logu(rng, 0.0005, 0.008)
        style = "ardupilot" if rng.random() < 0.5 else "px4"
        extra = dict(
            name=f"rotorpy-{name}-{seed}", actuator_delay_s=_logu(rng, 0.001, 0.01),
            attitude_sensor_delay_s=att, position_sensor_delay_s=att + _logu(rng, 0.004, 0.06),
            link_delay_s=float(rng.uniform(0.0, 0.006)),
            telemetry_max_hz=float(round(_logu(rng, 200.0, 500.0))),
            gyro_noise_rad_s=_logu(rng, 0.002, 0.008), attitude_noise_rad=_logu(rng, 4e-4, 2e-3),
            position_noise_m=_logu(rng, 5e-4, 3e-3), velocity_noise_m_s=_logu(rng, 2e-3, 8e-3),
            hover_estimate_factor=_logu(rng, 0.85, 1.15),
            onboard=OnboardSpec(
                style=style, loop_hz=_LOOP_HZ,
                position_loop_hz=_position_hz(style, float(rng.choice([1, 2, 5]))),
                dgyro_cutoff_hz=round(_logu(rng, 20.0, 50.0), 1),
                target_cutoff_hz=round(_logu(rng, 15.0, 40.0), 1) if style == "ardupilot"
                else 0.0,
                accel_max_rad_s2=round(_logu(rng, 8.0, 30.0), 1) if style == "ardupilot"
                else 0.0))
    af = Airframe(**_linearised(p), **extra)
    ob = af.onboard
    af = dataclasses.replace(af, description=(
        f"RotorPy {name} physics (rotorpy {ROTORPY_PIN}): {af.mass_kg * 1e3:.0f} g, "
        f"T/W {af.thrust_to_weight:.2f}, rotor lag {af.motor_tau_s * 1e3:.0f} ms; "
        f"{ob.style}-like onboard at {ob.loop_hz:.0f}/{ob.position_loop_hz:.0f} Hz"))
    af.validate()
    return RotorpySpec(name, MappingProxyType(p), af)


def _position_hz(style: str, every: float) -> float:
    """The position loop's rate: every ``every`` rate-loop ticks on a PX4-like vehicle (its
    EKF2 rate); ArduCopter runs its position controller in the main loop, at its rate."""
    return _LOOP_HZ if style == "ardupilot" else _LOOP_HZ / every


class RotorpyMultirotor(Multirotor):
    """:class:`~mrft_gcs.sitl.physics.Multirotor`'s interface on RotorPy's dynamics.

    The command shaping (clip, dead band, rate limit, torque bias), the actuator delay and
    the sensors (delays, noise, low-pass) are the bundled physics'; between them RotorPy's
    model advances one step of ``dt_s`` with the command held: its allocation and rotor-speed
    limits (``get_cmd_motor_speeds``), its state derivative (``_s_dot_fn``: wrench,
    rigid body, rotor lag), its quaternion normalisation and ground contact.

    Parameters
    ----------
    spec : RotorpySpec
    dt_s : float
        Step, s (one onboard loop period, 4 ms, in the SITL).
    seed : int
        Sensor-noise seed.
    wind_m_s : (3,) float
        Constant wind, NED.
    integrator : str
        ``"rk2"`` (default): one explicit trapezoid step on RotorPy's derivative with the rotor
        lag solved exactly (2 evaluations a step); ``"rotorpy"``: RotorPy's own
        ``Multirotor.step`` (adaptive RK23, about twice the CPU; a real-time SITL on a busy
        host falls behind with it).

    Raises
    ------
    UsageError
        An effect that belongs to the bundled physics' motors or body (only
        ``sensor_lpf``, ``torque_rate_limit`` and ``motor_deadzone`` carry over).
    """

    def __init__(self, spec: RotorpySpec, dt_s: float, seed: int = 0,
                 wind_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0),
                 integrator: str = "rk2") -> None:
        if integrator not in ("rk2", "rotorpy"):
            raise UsageError(f"integrator '{integrator}': use 'rk2' or 'rotorpy'")
        self.integrator = integrator
        af = spec.airframe
        bad = sorted(set(af.effects.active()) - _EFFECTS_OK)
        if bad:
            raise UsageError(f"effect(s) {bad} are not available with --physics rotorpy; "
                             f"use {', '.join(sorted(_EFFECTS_OK))}")
        p = dict(spec.params)
        self.params = MappingProxyType(p)
        self._n_rot = int(p["num_rotors"])
        self._thrust_max = self._n_rot * p["k_eta"] * p["rotor_speed_max"] ** 2
        self._moment_max = af.max_moments_n_m
        self._w_hover = _hover_speed(p)
        rp = _rotorpy("vehicles.multirotor")
        self.rp = rp.Multirotor(p, control_abstraction="cmd_ctbm", aero=True,
                                enable_ground=True,
                                integrator_kwargs={"method": "RK23", "first_step": dt_s})
        self._g = float(self.rp.g)
        self._state: dict[str, np.ndarray] = {}
        super().__init__(af, dt_s=dt_s, seed=seed, wind_m_s=wind_m_s)

    # ------------------------------------------------------------------ state
    def reset(self, position_ned: tuple[float, float, float] = (0.0, 0.0, 0.0),
              yaw: float = 0.0, airborne: bool = False) -> None:
        """As :meth:`Multirotor.reset`: on the ground at rest, or in the air at hover."""
        self.rng = np.random.default_rng(self.seed)
        self.t = 0.0
        px, py, pz = (float(v) for v in position_ned)
        if not airborne:
            pz = 0.0
        w, x, y, z = quat_from_euler(0.0, 0.0, yaw)
        wn, we, wd = self.wind
        self._state = {
            "x": np.array([px, -py, -pz]), "v": np.zeros(3),
            "q": np.array([x, -y, -z, w]),  # RotorPy's order (i, j, k, w), z up
            "w": np.zeros(3), "wind": np.array([wn, -we, -wd]),
            "rotor_speeds": np.full(self._n_rot, self._w_hover if airborne else 0.0)}
        hover = (self._g * self.af.mass_kg, 0.0, 0.0, 0.0) if airborne else (0.0,) * 4
        self.motor_cmd = hover
        self._torque_prev: tuple[float, ...] = (0.0, 0.0, 0.0)
        self._yaw_unwrapped = yaw
        self._act_delay = _Delay(self._steps(self.af.actuator_delay_s), hover)
        self._sync(self._state["v"])
        att, posv = self._true_channels()
        self._att_delay = _Delay(self._steps(self.af.attitude_sensor_delay_s), att)
        self._pos_delay = _Delay(self._steps(self.af.position_sensor_delay_s), posv)
        self.meas_att, self.meas_posv = att, posv

    def _sync(self, v_before: np.ndarray) -> None:
        """NED / FRD copies of RotorPy's state, and the specific force over the last step."""
        s = self._state
        px, py, pz = s["x"].tolist()
        vx, vy, vz = s["v"].tolist()
        qi, qj, qk, qw = s["q"].tolist()
        p, q, r = s["w"].tolist()
        self._p, self._v = [px, -py, -pz], [vx, -vy, -vz]
        self._q, self._w = [qw, qi, -qj, -qk], [p, -q, -r]
        self.on_ground = pz <= _GROUND_Z_M
        # specific force = acceleration - gravity, in body axes (what an accelerometer reads)
        ax, ay, az = ((s["v"] - v_before) / self.dt).tolist()
        fx, fy, fz = ax, -ay, -az - self._g
        w, x, y, z = self._q
        # R^T f with R the body-to-NED rotation of (w, x, y, z)
        self._sf = (
            (1 - 2 * (y * y + z * z)) * fx + 2 * (x * y + w * z) * fy + 2 * (x * z - w * y) * fz,
            2 * (x * y - w * z) * fx + (1 - 2 * (x * x + z * z)) * fy + 2 * (y * z + w * x) * fz,
            2 * (x * z + w * y) * fx + 2 * (y * z - w * x) * fy + (1 - 2 * (x * x + y * y)) * fz)

    # ------------------------------------------------------------------- step
    def step(self, roll: float, pitch: float, yaw: float, thrust: float) -> None:
        """Advance one step with normalised commands (held for ``dt_s``)."""
        eff, dt = self.af.effects, self.dt
        tq = shaped_torques(roll, pitch, yaw, self._torque_prev, eff, dt)
        self._torque_prev = tq
        b, mm = self._bias, self._moment_max
        cmd = (min(max(thrust, 0.0), 1.0) * self._thrust_max,
               (tq[0] + b[0]) * mm[0], (tq[1] + b[1]) * mm[1], (tq[2] + b[2]) * mm[2])
        self.motor_cmd = cmd
        f, mx, my, mz = self._act_delay.push(cmd)
        v_before = self._state["v"]
        # FRD moments to RotorPy's body axes (y left, z up)
        control = {"cmd_thrust": f, "cmd_moment": np.array([mx, -my, -mz])}
        if self.integrator == "rotorpy":
            self._state = self.rp.step(self._state, control, dt)
        else:
            self._state = self._rk2(control, dt)
        self.t += dt
        self._sync(v_before)
        self._sense()

    def _rk2(self, control: dict[str, Any], dt: float) -> dict[str, np.ndarray]:
        """``rp.step`` with its adaptive solver replaced by one trapezoid step."""
        rp = self.rp
        cmd = np.clip(rp.get_cmd_motor_speeds(self._state, control), rp.rotor_speed_min,
                      rp.rotor_speed_max)
        s0 = rp._pack_state(self._state)
        k1 = rp._s_dot_fn(0.0, s0, cmd)
        # the rotor lag is linear with the command held: its exact end point, not Euler's
        rotors = cmd + (s0[16:] - cmd) * math.exp(-dt / rp.tau_m)
        s1 = s0 + dt * k1
        s1[16:] = rotors
        k2 = rp._s_dot_fn(dt, s1, cmd)
        s1 = s0 + 0.5 * dt * (k1 + k2)
        s1[16:] = rotors
        state: dict[str, np.ndarray] = rp._unpack_state(s1)
        state["q"] = state["q"] / np.linalg.norm(state["q"])
        if rp._enable_ground and rp._on_ground(state):
            state = rp._handle_vehicle_on_ground(state)
        return state

    @property
    def rotor_speeds_rad_s(self) -> np.ndarray:
        """RotorPy's rotor speeds, rad/s, shape (4,)."""
        return np.array(self._state["rotor_speeds"])


def rotorpy_vehicle(spec: RotorpySpec, seed: int = 0,
                    wind_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0),
                    integrator: str = "rk2"):  # -> SimVehicle
    """A :class:`~mrft_gcs.sitl.vehicle.SimVehicle` on RotorPy physics, stepped once per
    onboard loop period."""
    from mrft_gcs.sitl.vehicle import SimVehicle

    dt = 1.0 / spec.airframe.onboard.loop_hz
    phys = RotorpyMultirotor(spec, dt_s=dt, seed=seed, wind_m_s=wind_m_s,
                             integrator=integrator)
    return SimVehicle(spec.airframe, seed=seed, wind_m_s=wind_m_s, dt_s=dt, physics=phys)
