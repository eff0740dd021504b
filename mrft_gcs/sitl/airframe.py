"""Airframe profiles of the simulated vehicle: TOML files loaded into frozen dataclasses.

A profile lives in ``profiles/vehicles/NAME.toml`` and describes one multirotor: mass,
inertia, geometry, propulsion, drag, delays, sensor noise, biases and the switchable
*unmodelled effects*. :meth:`Airframe.linear_models` turns it into the true small-signal
models of docs/method.md, the ground truth against which a tune is scored.

Conventions
-----------
World frame NED (x north, y east, z down), body frame FRD (x forward, y right, z down).
Normalised commands: roll/pitch/yaw torque ``u`` in [-1, 1], where 1 is the largest moment the
motors give about that axis (half the motors at full command, the other half at zero), and
collective thrust in [0, 1], where 1 is full thrust of every motor.

Linear models (small signal, effects off)::

    roll, pitch, altitude:  G(s) = K e^{-tau s} / (s (T_prop s + 1)(T1 s + 1))
    x, y:                   G(s) = K e^{-tau s} / (s (T2 s + 1))

* roll/pitch: input the torque command ``u``, output the angle in rad.
  ``K = M_max / b_rot``, ``T1 = I / b_rot``, ``T_prop = motor_tau_s``,
  ``tau = actuator_delay_s + attitude_sensor_delay_s``.
* altitude: input the collective thrust command (deviation from hover), output the altitude
  in m, up positive. ``K = n T_motor_max / b_z``, ``T1 = m / b_z``,
  ``tau = actuator_delay_s + position_sensor_delay_s``.
* x, y: input the attitude angle (output of the closed attitude loop, as measured), output the
  position in m. Sign convention at yaw 0: a nose-down pitch (``-theta``) moves +x (north), a
  right-wing-down roll (``+phi``) moves +y (east); so the x model's input is ``-pitch`` and the
  y model's input is ``+roll``. ``K = g m / b_xy = g T2``, ``T2 = m / b_xy``,
  ``tau = position_sensor_delay_s - attitude_sensor_delay_s`` (the delay the position
  measurement adds on top of the measured angle).
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mrft_gcs.errors import UsageError

__all__ = [
    "Airframe",
    "Effects",
    "OnboardSpec",
    "ONBOARD_STYLES",
    "EFFECT_NAMES",
    "GRAVITY_M_S2",
    "load_airframe",
    "available_vehicles",
    "vehicles_dir",
    "motor_layout",
]

GRAVITY_M_S2 = 9.80665

#: Unmodelled effects: name -> (value that switches it off, unit / meaning).
EFFECT_NAMES: dict[str, tuple[float, str]] = {
    "motor_saturation": (1.0, "largest per-motor command, in (0, 1]; 1 = off"),
    "torque_rate_limit": (0.0, "largest change of a normalised torque command, 1/s; 0 = off"),
    "sensor_lpf": (0.0, "first-order low-pass on every sensor, cutoff in Hz; 0 = off"),
    "quadratic_drag": (0.0, "extra translational drag c |v| v, c in N s^2/m^2; 0 = off"),
    "thrust_curve": (0.0, "thrust = (1-a) c + a c^2 per motor, a in [0, 1]; 0 = off"),
    "com_offset": (0.0, "centre of mass offset along body +x and +y, m (input bias); 0 = off"),
    "motor_deadzone": (0.0, "dead band on normalised torque commands, in [0, 0.5); 0 = off"),
}


@dataclass(frozen=True)
class Effects:
    """Switchable unmodelled effects (all off by default); see :data:`EFFECT_NAMES`."""

    motor_saturation: float = 1.0
    torque_rate_limit: float = 0.0
    sensor_lpf: float = 0.0
    quadratic_drag: float = 0.0
    thrust_curve: float = 0.0
    com_offset: float = 0.0
    motor_deadzone: float = 0.0

    def active(self) -> dict[str, float]:
        """The effects that are switched on, name -> value."""
        return {n: getattr(self, n) for n, (off, _) in EFFECT_NAMES.items()
                if getattr(self, n) != off}

    def updated(self, values: dict[str, float]) -> Effects:
        """A copy with ``values`` applied, validated (raises :class:`UsageError`)."""
        clean: dict[str, float] = {}
        for name, value in values.items():
            if name not in EFFECT_NAMES:
                raise UsageError(f"unknown effect '{name}'; known effects: "
                                 f"{', '.join(EFFECT_NAMES)}")
            try:
                v = float(value)
            except (TypeError, ValueError):
                raise UsageError(f"effect {name}={value!r} is not a number") from None
            if not math.isfinite(v):
                raise UsageError(f"effect {name}={value!r} must be finite")
            clean[name] = v
        eff = dataclasses.replace(self, **clean)
        eff._validate()
        return eff

    def _validate(self) -> None:
        checks = [
            (0.0 < self.motor_saturation <= 1.0, "motor_saturation must be in (0, 1]"),
            (self.torque_rate_limit >= 0.0, "torque_rate_limit must be >= 0"),
            (self.sensor_lpf >= 0.0, "sensor_lpf must be >= 0 Hz"),
            (self.quadratic_drag >= 0.0, "quadratic_drag must be >= 0"),
            (0.0 <= self.thrust_curve <= 1.0, "thrust_curve must be in [0, 1]"),
            (abs(self.com_offset) <= 0.2, "com_offset must be within +-0.2 m"),
            (0.0 <= self.motor_deadzone < 0.5, "motor_deadzone must be in [0, 0.5)"),
        ]
        for ok, msg in checks:
            if not ok:
                raise UsageError(f"bad effect value: {msg}")


#: Onboard cascade structures the simulated autopilot can run (see :class:`OnboardSpec`).
ONBOARD_STYLES = ("px4", "ardupilot")


@dataclass(frozen=True)
class OnboardSpec:
    """How the simulated autopilot closes its loops: structure, rates and filters.

    Not parameters a ground station can read: firmware internals that decide the loop the
    written gains end up in (:func:`mrft_gcs.flight.scoring.score_written`).

    Attributes
    ----------
    style : str
        ``"px4"``: rate loop ``K (P e + I - D d(rate)/dt) + FF rate_sp``, D on the measured
        rate. ``"ardupilot"``: a square-root angle controller (linear for errors below
        ``accel_max / P^2``), the rate target low-passed at ``target_cutoff_hz``, rate loop
        ``P e + I + D de/dt + FF target`` with D on the error (ArduPilot's AC_PID), no K.
    loop_hz : float
        Attitude and rate loop rate (the motor command is held between updates), Hz.
    position_loop_hz : float
        Position and velocity loop rate (attitude set point and thrust held between), Hz.
    dgyro_cutoff_hz : float
        Low-pass on the rate loop's D term (PX4 IMU_DGYRO_CUTOFF, ArduPilot FLTD), Hz.
    target_cutoff_hz : float
        ArduPilot's rate target filter (FLTT), Hz; 0 = off.
    accel_max_rad_s2 : float
        ArduPilot's ATC_ACCEL_R/P_MAX, the square-root controller's limit; 0 = linear.
    """

    style: str = "px4"
    loop_hz: float = 1000.0
    position_loop_hz: float = 1000.0
    dgyro_cutoff_hz: float = 30.0
    target_cutoff_hz: float = 0.0
    accel_max_rad_s2: float = 0.0

    def validate(self) -> None:
        """Raise :class:`UsageError` for a structure the simulator cannot run."""
        if self.style not in ONBOARD_STYLES:
            raise UsageError(f"onboard style '{self.style}': use one of {ONBOARD_STYLES}")
        if not 10.0 <= self.position_loop_hz <= self.loop_hz <= 1000.0:
            raise UsageError("onboard loop rates: need 10 <= position_loop_hz <= loop_hz "
                             "<= 1000 Hz")
        if not (self.dgyro_cutoff_hz > 0 and self.target_cutoff_hz >= 0
                and self.accel_max_rad_s2 >= 0):
            raise UsageError("onboard filters: dgyro_cutoff_hz > 0, target_cutoff_hz >= 0, "
                             "accel_max_rad_s2 >= 0")


def motor_layout(frame: str, arm_length_m: float) -> tuple[tuple[float, float, float], ...]:
    """Motor positions and spin: ``((x_m, y_m, spin), ...)`` in the body frame FRD.

    ``spin`` is +1 for a propeller turning counter-clockwise seen from above (its reaction
    torque yaws the body clockwise, i.e. positive yaw in FRD) and -1 otherwise.
    """
    angles_spins: tuple[tuple[float, int], ...]
    if frame == "quad_x":
        angles_spins = ((45.0, 1), (225.0, 1), (315.0, -1), (135.0, -1))  # PX4 quad-X order
    elif frame == "hexa_x":
        angles_spins = tuple((30.0 + 60.0 * i, 1 if i % 2 == 0 else -1) for i in range(6))
    else:
        raise UsageError(f"unknown frame '{frame}'; use 'quad_x' or 'hexa_x'")
    out = []
    for deg, spin in angles_spins:
        a = math.radians(deg)
        x, y = arm_length_m * math.cos(a), arm_length_m * math.sin(a)
        out.append((0.0 if abs(x) < 1e-12 else x, 0.0 if abs(y) < 1e-12 else y, float(spin)))
    return tuple(out)


@dataclass(frozen=True)
class Airframe:
    """A simulated multirotor, SI units in the field names.

    Attributes
    ----------
    name : str
        Profile name.
    frame : str
        ``"quad_x"`` or ``"hexa_x"``.
    mass_kg : float
    inertia_kg_m2 : tuple of 3 float
        Principal moments of inertia about body x, y, z.
    arm_length_m : float
        Centre-to-motor distance.
    motor_tau_s : float
        First-order time constant of motor speed.
    thrust_to_weight : float
        Peak thrust of all motors over weight.
    yaw_moment_per_thrust_m : float
        Propeller reaction torque per newton of thrust.
    rot_drag_n_m_s_rad : tuple of 3 float
        Linear rotational drag about body x, y, z.
    lin_drag_n_s_m : tuple of 3 float
        Linear translational drag along body x, y, z (air-relative velocity).
    actuator_delay_s, attitude_sensor_delay_s, position_sensor_delay_s : float
        Pure delays of motor commands, attitude/rate measurement, position/velocity measurement.
    gyro_noise_rad_s, attitude_noise_rad, position_noise_m, velocity_noise_m_s : float
        Standard deviations of white measurement noise.
    torque_bias : tuple of 3 float
        Constant normalised torque added to roll, pitch, yaw commands (forced bias ``u0``).
    effects : Effects
        Unmodelled effects (off by default).
    description : str
    onboard : OnboardSpec
        The autopilot's loop structure and rates (default: PX4-style, everything at 1 kHz).
    link_delay_s : float
        One-way delay of the MAVLink link, each direction, s.
    telemetry_max_hz : float
        Fastest rate the vehicle streams a message at, Hz.
    hover_estimate_factor : float
        The autopilot's hover-thrust estimate (``MPC_THR_HOVER``) over the true one.
    """

    name: str
    frame: str
    mass_kg: float
    inertia_kg_m2: tuple[float, float, float]
    arm_length_m: float
    motor_tau_s: float
    thrust_to_weight: float
    yaw_moment_per_thrust_m: float
    rot_drag_n_m_s_rad: tuple[float, float, float]
    lin_drag_n_s_m: tuple[float, float, float]
    actuator_delay_s: float
    attitude_sensor_delay_s: float
    position_sensor_delay_s: float
    gyro_noise_rad_s: float = 0.0
    attitude_noise_rad: float = 0.0
    position_noise_m: float = 0.0
    velocity_noise_m_s: float = 0.0
    torque_bias: tuple[float, float, float] = (0.0, 0.0, 0.0)
    effects: Effects = field(default_factory=Effects)
    description: str = ""
    onboard: OnboardSpec = field(default_factory=OnboardSpec)
    link_delay_s: float = 0.0
    telemetry_max_hz: float = 1000.0
    hover_estimate_factor: float = 1.0

    # ----------------------------------------------------------------- derived
    @property
    def motors(self) -> tuple[tuple[float, float, float], ...]:
        """Motor positions and spins, see :func:`motor_layout`."""
        return motor_layout(self.frame, self.arm_length_m)

    @property
    def n_motors(self) -> int:
        return len(self.motors)

    @property
    def motor_thrust_max_n(self) -> float:
        """Peak thrust of one motor, N."""
        return self.thrust_to_weight * self.mass_kg * GRAVITY_M_S2 / self.n_motors

    @property
    def hover_thrust(self) -> float:
        """Collective command that balances gravity (linear thrust curve)."""
        return 1.0 / self.thrust_to_weight

    @property
    def max_moments_n_m(self) -> tuple[float, float, float]:
        """Moment at normalised command 1 about body x, y, z, N m."""
        t = self.motor_thrust_max_n
        ms = self.motors
        roll = 0.5 * t * sum(abs(y) for _, y, _ in ms)
        pitch = 0.5 * t * sum(abs(x) for x, _, _ in ms)
        yaw = 0.5 * t * self.yaw_moment_per_thrust_m * len(ms)
        return roll, pitch, yaw

    def linear_models(self) -> dict[str, dict[str, float]]:
        """True small-signal models of the five tuned loops (see the module docstring).

        Returns
        -------
        dict
            ``{"roll"|"pitch"|"altitude": {"K", "T_prop", "T1", "tau"},
            "x"|"y": {"K", "T2", "tau"}}``; times in s.
        """
        mx, my, _ = self.max_moments_n_m
        bx, by, _ = self.rot_drag_n_m_s_rad
        ix, iy, _ = self.inertia_kg_m2
        lbx, lby, lbz = self.lin_drag_n_s_m
        tau_att = self.actuator_delay_s + self.attitude_sensor_delay_s
        tau_alt = self.actuator_delay_s + self.position_sensor_delay_s
        tau_side = self.position_sensor_delay_s - self.attitude_sensor_delay_s
        m, g = self.mass_kg, GRAVITY_M_S2
        return {
            "roll": {"K": mx / bx, "T_prop": self.motor_tau_s, "T1": ix / bx, "tau": tau_att},
            "pitch": {"K": my / by, "T_prop": self.motor_tau_s, "T1": iy / by, "tau": tau_att},
            "altitude": {"K": self.n_motors * self.motor_thrust_max_n / lbz,
                         "T_prop": self.motor_tau_s, "T1": m / lbz, "tau": tau_alt},
            "x": {"K": g * m / lbx, "T2": m / lbx, "tau": tau_side},
            "y": {"K": g * m / lby, "T2": m / lby, "tau": tau_side},
        }

    def with_effects(self, values: dict[str, float]) -> Airframe:
        """A copy with effects overridden (command line beats profile)."""
        return dataclasses.replace(self, effects=self.effects.updated(values))

    def quiet(self) -> Airframe:
        """A copy without noise and bias (for checks against the linear models)."""
        return dataclasses.replace(self, gyro_noise_rad_s=0.0, attitude_noise_rad=0.0,
                                   position_noise_m=0.0, velocity_noise_m_s=0.0,
                                   torque_bias=(0.0, 0.0, 0.0))

    def validate(self) -> None:
        """Raise :class:`UsageError` if a value is out of its physical range."""
        def pos(name: str, v: float) -> None:
            if not (math.isfinite(v) and v > 0):
                raise UsageError(f"vehicle profile '{self.name}': {name} must be > 0, got {v}")

        motor_layout(self.frame, 1.0)
        for name in ("mass_kg", "arm_length_m", "motor_tau_s", "thrust_to_weight"):
            pos(name, getattr(self, name))
        for name in ("inertia_kg_m2", "rot_drag_n_m_s_rad", "lin_drag_n_s_m"):
            vals = getattr(self, name)
            if len(vals) != 3:
                raise UsageError(f"vehicle profile '{self.name}': {name} needs 3 values")
            for v in vals:
                pos(name, v)
        if self.thrust_to_weight <= 1.0:
            raise UsageError(f"vehicle profile '{self.name}': thrust_to_weight must be > 1")
        for name in ("actuator_delay_s", "attitude_sensor_delay_s", "position_sensor_delay_s",
                     "gyro_noise_rad_s", "attitude_noise_rad", "position_noise_m",
                     "velocity_noise_m_s", "yaw_moment_per_thrust_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise UsageError(f"vehicle profile '{self.name}': {name} must be >= 0, got {v}")
        if self.position_sensor_delay_s < self.attitude_sensor_delay_s:
            raise UsageError(f"vehicle profile '{self.name}': position_sensor_delay_s must be "
                             "at least attitude_sensor_delay_s")
        if len(self.torque_bias) != 3 or any(abs(b) > 0.5 for b in self.torque_bias):
            raise UsageError(f"vehicle profile '{self.name}': torque_bias needs 3 values "
                             "within +-0.5")
        self.effects._validate()
        self.onboard.validate()
        if not (0.0 <= self.link_delay_s <= 0.5 and 1.0 <= self.telemetry_max_hz <= 1000.0
                and 0.5 <= self.hover_estimate_factor <= 2.0):
            raise UsageError(f"vehicle profile '{self.name}': link_delay_s must be in "
                             "[0, 0.5], telemetry_max_hz in [1, 1000], hover_estimate_factor "
                             "in [0.5, 2]")


# --------------------------------------------------------------------------- loading
def vehicles_dir() -> Path:
    """The folder of bundled vehicle profiles (``<repo>/profiles/vehicles``)."""
    return Path(__file__).resolve().parents[2] / "profiles" / "vehicles"


def available_vehicles() -> list[str]:
    """Names of the bundled vehicle profiles."""
    d = vehicles_dir()
    return sorted(p.stem for p in d.glob("*.toml")) if d.is_dir() else []


_SECTIONS: dict[str, dict[str, str]] = {
    # toml section -> {toml key: Airframe field}
    "": {"name": "name", "description": "description", "frame": "frame"},
    "body": {"mass_kg": "mass_kg", "inertia_kg_m2": "inertia_kg_m2",
             "arm_length_m": "arm_length_m"},
    "propulsion": {"motor_tau_s": "motor_tau_s", "thrust_to_weight": "thrust_to_weight",
                   "yaw_moment_per_thrust_m": "yaw_moment_per_thrust_m"},
    "drag": {"rot_drag_n_m_s_rad": "rot_drag_n_m_s_rad", "lin_drag_n_s_m": "lin_drag_n_s_m"},
    "delays": {"actuator_s": "actuator_delay_s", "attitude_sensor_s": "attitude_sensor_delay_s",
               "position_sensor_s": "position_sensor_delay_s"},
    "noise": {"gyro_rad_s": "gyro_noise_rad_s", "attitude_rad": "attitude_noise_rad",
              "position_m": "position_noise_m", "velocity_m_s": "velocity_noise_m_s"},
    "biases": {"torque": "torque_bias"},
}


def _resolve(name_or_path: str | Path) -> Path:
    p = Path(name_or_path)
    if p.suffix == ".toml" or p.exists() or len(p.parts) > 1:
        if not p.is_file():
            raise UsageError(f"vehicle profile file '{p}' not found")
        return p
    cand = vehicles_dir() / f"{p.name}.toml"
    if not cand.is_file():
        raise UsageError(f"unknown vehicle '{name_or_path}'; available: "
                         f"{', '.join(available_vehicles()) or '(none)'}, or give a .toml path")
    return cand


def _from_dict(data: dict[str, Any], default_name: str) -> Airframe:
    kwargs: dict[str, Any] = {}
    for section, keys in _SECTIONS.items():
        table = data if section == "" else data.get(section, {})
        if not isinstance(table, dict):
            raise UsageError(f"vehicle profile: [{section}] must be a table")
        allowed = set(keys)
        if section == "":
            allowed |= set(_SECTIONS) | {"effects"}
        unknown = set(table) - allowed
        if unknown:
            where = f"[{section}]" if section else "top level"
            raise UsageError(f"vehicle profile: unknown key(s) {sorted(unknown)} at {where}; "
                             f"allowed: {sorted(keys)}")
        for key, fld in keys.items():
            if key in table:
                v = table[key]
                kwargs[fld] = tuple(float(x) for x in v) if isinstance(v, list) else v
    kwargs.setdefault("name", default_name)
    missing = [f.name for f in dataclasses.fields(Airframe)
               if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
               and f.name not in kwargs]
    if missing:
        raise UsageError(f"vehicle profile '{kwargs['name']}': missing {missing}")
    try:
        af = Airframe(**kwargs)
        eff = data.get("effects", {})
        if not isinstance(eff, dict):
            raise UsageError("vehicle profile: [effects] must be a table")
        af = af.with_effects(eff)
        af.validate()
    except (TypeError, ValueError) as exc:
        raise UsageError(f"vehicle profile '{kwargs['name']}': {exc}") from None
    return af


def load_airframe(name_or_path: str | Path) -> Airframe:
    """Load and validate a vehicle profile.

    Parameters
    ----------
    name_or_path : str or Path
        A bundled name (``"qdrone"``, ``"racer250"``, ``"f550"``) or a path to a TOML file.

    Raises
    ------
    UsageError
        Unknown name (the message lists the available ones), unreadable or invalid file.

    Examples
    --------
    >>> af = load_airframe("qdrone")
    >>> af.mass_kg, af.n_motors
    (1.0, 4)
    """
    path = _resolve(name_or_path)
    try:
        with path.open("rb") as fh:
            data = tomllib.load(fh)
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise UsageError(f"cannot read vehicle profile '{path}': {exc}") from None
    return _from_dict(data, path.stem)
