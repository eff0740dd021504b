"""Autopilot profiles (SPEC 4.2): identified PD gains -> the autopilot's own parameters.

A profile is a TOML file in ``profiles/`` (``px4``, ``ardupilot``, ``sitl``) loaded
with :mod:`tomllib` into frozen dataclasses and validated on load. It says which
actuation path the relay tests use, which custom-mode numbers to switch to, the
default safety limits, and the parameter names each loop's gains land in.

The conversion (SPEC 2, 4.2) rests on one identity. The deployed PD acts on the
loop error ``e`` and the measured rate ``w``: ``u = Kc e - Kd w``. An angle-P
``Kc/Kd`` feeding a rate-P ``Kd`` gives ``u = Kd (Kc/Kd e - w)``, the same thing,
with the rate loop's I and D set to zero. Per loop (g = 9.80665 m/s^2):

roll, pitch (``u``: normalised torque in [-1, 1]; ``Kc`` [1/rad], ``Kd`` [s/rad])
    angle P = Kc/Kd [(rad/s)/rad]; rate P = Kd; rate I = rate D = 0; PX4 rate K = 1.
    ArduPilot's angle P passes through a square-root controller, linear for small
    errors (below ATC_ACCEL_*_MAX / P^2): the relation holds in that region.
x, y (``u``: tilt angle [rad]; ``Kc`` [rad/m], ``Kd`` [rad/(m/s)])
    Both autopilots' velocity loops output an acceleration and tilt = acc/g (small
    angles), so velocity P = g Kd [(m/s^2)/(m/s)], position P = Kc/Kd [1/s],
    velocity I = D = 0. ArduPilot's PSC_* gains before 4.6 are in cm, cm/s and
    cm/s^2, but position and velocity P have units of 1/s either way: no factor.
    PX4 and ArduPilot have one set for x and y: the lower of the two loops' values
    is written for each gain (lower gains: more phase margin on these plants).
altitude (``u``: normalised collective-thrust deviation; ``Kc`` [1/m], ``Kd`` [s/m])
    PX4: thrust = MPC_THR_HOVER (1 + acc/g), so velocity P = Kd g / hover,
    position P = Kc/Kd, velocity I = D = 0.
    ArduPilot (``accel_p`` set): throttle = hover + 0.001 ACCZ_P (a_sp - a) with
    accelerations in cm/s^2, i.e. ``A = 0.1 ACCZ_P`` of throttle per m/s^2; with the
    measured acceleration a = g du / hover fed straight back, du = A/(1 + A g/hover)
    a_sp. So VELZ_P = Kd (1 + A g / hover) / A and POSZ_P = Kc/Kd. Assumes the
    acceleration feedback is fast next to the altitude loop and ACCZ_I small.
"""

from __future__ import annotations

import enum
import math
import os
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from mrft_gcs.errors import UsageError
from mrft_gcs.link.modes import CustomMode
from mrft_gcs.loops import Loop
from mrft_gcs.telemetry import AutopilotFamily

__all__ = [
    "Actuation",
    "PDGains",
    "SafetyLimits",
    "AngleRateParams",
    "CascadeParams",
    "AltitudeParams",
    "AutopilotProfile",
    "PROFILE_DIR",
    "G_M_S2",
    "load_profile",
    "parse_profile",
    "gains_to_params",
    "params_to_gains",
]

G_M_S2 = 9.80665
PROFILE_DIR = Path(__file__).resolve().parent.parent / "profiles"


class Actuation(enum.Enum):
    """How relay tests reach the vehicle."""

    TORQUE = "torque"  # SET_ACTUATOR_CONTROL_TARGET group 0: all five loops from the GCS
    ATTITUDE = "attitude"  # SET_ATTITUDE_TARGET: autopilot keeps its attitude loop


@dataclass(frozen=True)
class PDGains:
    """``u = Kc e - Kd dy/dt`` in the SI units of the loop (see module docstring)."""

    Kc: float
    Kd: float


@dataclass(frozen=True)
class SafetyLimits:
    """Limits that abort a test and land (SPEC 5). Command line overrides them."""

    max_tilt_deg: float = 35.0
    max_altitude_m: float = 5.0
    max_distance_m: float = 5.0
    max_test_duration_s: float = 60.0

    def with_overrides(self, **values: float | None) -> SafetyLimits:
        """Command-line values (None: keep the profile's)."""
        return replace(self, **{k: v for k, v in values.items() if v is not None})


@dataclass(frozen=True)
class AngleRateParams:
    """Angle-P feeding a rate PID (roll or pitch)."""

    angle_p: str
    rate_p: str
    rate_i: str
    rate_d: str
    rate_k: str | None = None  # PX4's overall rate-gain multiplier, set to 1


@dataclass(frozen=True)
class CascadeParams:
    """Position-P feeding a velocity PID whose output is an acceleration (x and y)."""

    pos_p: str
    vel_p: str
    vel_i: str
    vel_d: str


@dataclass(frozen=True)
class AltitudeParams:
    """Altitude cascade; ``accel_p`` set means ArduPilot's acceleration loop is in between."""

    pos_p: str
    vel_p: str
    vel_i: str
    vel_d: str
    hover_thrust: str
    accel_p: str | None = None
    accel_p_value: float = 0.5  # ACCZ_P written (ArduPilot default 0.5)


@dataclass(frozen=True)
class AutopilotProfile:
    """One ``profiles/*.toml``."""

    name: str
    family: AutopilotFamily
    description: str
    actuation: Actuation
    modes: Mapping[str, CustomMode]
    safety: SafetyLimits
    roll: AngleRateParams
    pitch: AngleRateParams
    side: CascadeParams
    altitude: AltitudeParams
    source: str = ""

    def parameter_names(self) -> list[str]:
        """Every parameter a full tune writes or needs (hover thrust), in write order."""
        names: list[str] = []
        for group in (self.roll, self.pitch, self.altitude, self.side):
            for v in vars(group).values():
                if isinstance(v, str) and v not in names:
                    names.append(v)
        return names


# ---------------------------------------------------------------------- loading
_MODE_KEYS = ("offboard", "position", "land")


def _need(table: Mapping[str, Any], key: str, kind: type | tuple[type, ...], where: str) -> Any:
    if key not in table:
        raise UsageError(f"{where}: missing '{key}'")
    value = table[key]
    if not isinstance(value, kind) or isinstance(value, bool):
        raise UsageError(f"{where}: '{key}' has the wrong type ({type(value).__name__})")
    return value


def _pname(table: Mapping[str, Any], key: str, where: str, optional: bool = False) -> str | None:
    if optional and key not in table:
        return None
    name = _need(table, key, str, where)
    if not (1 <= len(name) <= 16 and name.isascii() and name.replace("_", "").isalnum()):
        raise UsageError(f"{where}: '{name}' is not a parameter name (1-16 letters, digits, _)")
    return name


def _positive(table: Mapping[str, Any], key: str, where: str, default: float) -> float:
    value = float(table.get(key, default))
    if not (math.isfinite(value) and value > 0):
        raise UsageError(f"{where}: '{key}' must be a positive number, got {value}")
    return value


def parse_profile(data: Mapping[str, Any], source: str = "<profile>") -> AutopilotProfile:
    """Validate a parsed TOML table into a profile (UsageError naming the field)."""
    ap = _need(data, "autopilot", dict, source)
    w = f"{source} [autopilot]"
    try:
        family = AutopilotFamily(_need(ap, "family", str, w))
        actuation = Actuation(_need(ap, "actuation", str, w))
    except ValueError as err:
        raise UsageError(f"{w}: {err}; family is px4/ardupilot/generic, actuation "
                         f"torque/attitude") from None
    modes_t = _need(data, "modes", dict, source)
    modes = {}
    for key in _MODE_KEYS:
        m = _need(modes_t, key, dict, f"{source} [modes]")
        wm = f"{source} [modes.{key}]"
        main, sub = _need(m, "main", int, wm), int(m.get("sub", 0))
        if not (0 <= main <= 255 and 0 <= sub <= 255):
            raise UsageError(f"{wm}: mode numbers are 0-255")
        modes[key] = CustomMode(str(m.get("name", key.upper())), main, sub)
    st = data.get("safety", {})
    ws = f"{source} [safety]"
    d = SafetyLimits()
    safety = SafetyLimits(*(_positive(st, k, ws, getattr(d, k)) for k in vars(d)))
    if safety.max_tilt_deg >= 90:
        raise UsageError(f"{ws}: max_tilt_deg must be below 90")

    def angle(key: str) -> AngleRateParams:
        t = _need(data, key, dict, source)
        wa = f"{source} [{key}]"
        return AngleRateParams(*(_pname(t, k, wa) for k in ("angle_p", "rate_p", "rate_i",
                                                              "rate_d")),
                               rate_k=_pname(t, "rate_k", wa, optional=True))  # type: ignore[misc]

    st_side = _need(data, "side", dict, source)
    side = CascadeParams(*(_pname(st_side, k, f"{source} [side]")  # type: ignore[arg-type]
                           for k in ("pos_p", "vel_p", "vel_i", "vel_d")))
    alt_t = _need(data, "altitude", dict, source)
    wal = f"{source} [altitude]"
    altitude = AltitudeParams(
        *(_pname(alt_t, k, wal) for k in ("pos_p", "vel_p", "vel_i", "vel_d",  # type: ignore[arg-type]
                                          "hover_thrust")),
        accel_p=_pname(alt_t, "accel_p", wal, optional=True),
        accel_p_value=_positive(alt_t, "accel_p_value", wal, 0.5))
    return AutopilotProfile(
        name=str(ap.get("name", Path(source).stem)), family=family,
        description=str(ap.get("description", "")), actuation=actuation, modes=modes,
        safety=safety, roll=angle("roll"), pitch=angle("pitch"), side=side,
        altitude=altitude, source=source)


def load_profile(name_or_path: str | os.PathLike[str]) -> AutopilotProfile:
    """Load ``profiles/NAME.toml`` (``px4``, ``ardupilot``, ``sitl``) or a TOML path.

    Raises
    ------
    UsageError
        Unknown name, unreadable file, bad TOML or a field that fails validation.
    """
    path = Path(name_or_path)
    if not path.suffix and not path.exists():
        path = PROFILE_DIR / f"{name_or_path}.toml"
    if not path.is_file():
        known = sorted(p.stem for p in PROFILE_DIR.glob("*.toml"))
        raise UsageError(f"no autopilot profile '{name_or_path}': use one of {', '.join(known)} "
                         f"or a path to a .toml file")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError) as err:
        raise UsageError(f"cannot read profile {path}: {err}") from None
    return parse_profile(data, str(path))


# ---------------------------------------------------------------------- conversion
def _ratio(g: PDGains, loop: Loop) -> float:
    if not (math.isfinite(g.Kc) and math.isfinite(g.Kd) and g.Kc > 0 and g.Kd > 0):
        raise UsageError(f"{loop.value}: gains must be positive and finite, got {g}")
    return g.Kc / g.Kd


def _accel_gain(alt: AltitudeParams, accel_p: float | None = None) -> float:
    """ArduPilot ACCZ loop: throttle per m/s^2 (0.001 per cm/s^2 times ACCZ_P)."""
    return 0.1 * (alt.accel_p_value if accel_p is None else accel_p)


def gains_to_params(profile: AutopilotProfile, gains: Mapping[Loop, PDGains],
                    hover_thrust: float) -> dict[str, float]:
    """Parameter values for the loops in ``gains`` (others are left out).

    Parameters
    ----------
    hover_thrust : float
        The vehicle's hover thrust in [0, 1] (``MPC_THR_HOVER`` / ``MOT_THST_HOVER``),
        read from the vehicle; used by the altitude conversion.

    Examples
    --------
    >>> p = load_profile("px4")
    >>> gains_to_params(p, {Loop.ROLL: PDGains(Kc=1.0, Kd=0.25)}, 0.5)["MC_ROLL_P"]
    4.0
    """
    if not (0 < hover_thrust < 1):
        raise UsageError(f"hover thrust must be in (0, 1), got {hover_thrust}")
    out: dict[str, float] = {}
    for loop, ap in ((Loop.ROLL, profile.roll), (Loop.PITCH, profile.pitch)):
        if loop in gains:
            g = gains[loop]
            out[ap.angle_p] = _ratio(g, loop)
            out[ap.rate_p] = g.Kd
            out[ap.rate_i] = 0.0
            out[ap.rate_d] = 0.0
            if ap.rate_k:
                out[ap.rate_k] = 1.0
    if Loop.ALTITUDE in gains:
        g, alt = gains[Loop.ALTITUDE], profile.altitude
        out[alt.pos_p] = _ratio(g, Loop.ALTITUDE)
        if alt.accel_p:
            a = _accel_gain(alt)
            out[alt.accel_p] = alt.accel_p_value
            out[alt.vel_p] = g.Kd * (1 + a * G_M_S2 / hover_thrust) / a
        else:
            out[alt.vel_p] = g.Kd * G_M_S2 / hover_thrust
        out[alt.vel_i] = 0.0
        out[alt.vel_d] = 0.0
    side = [gains[lp] for lp in (Loop.X, Loop.Y) if lp in gains]
    if side:
        ratio = min(_ratio(g, Loop.X) for g in side)
        kd = min(g.Kd for g in side)
        out[profile.side.pos_p] = ratio
        out[profile.side.vel_p] = G_M_S2 * kd
        out[profile.side.vel_i] = 0.0
        out[profile.side.vel_d] = 0.0
    return out


def params_to_gains(profile: AutopilotProfile, values: Mapping[str, float]) -> dict[Loop, PDGains]:
    """The PD gains a set of parameter values amounts to (ignoring I and D terms).

    Loops whose parameters are not all in ``values`` are left out. The altitude loop
    needs the hover-thrust parameter in ``values``; x and y get the shared gains.
    """
    out: dict[Loop, PDGains] = {}
    for loop, ap in ((Loop.ROLL, profile.roll), (Loop.PITCH, profile.pitch)):
        if ap.angle_p in values and ap.rate_p in values:
            kd = values[ap.rate_p] * (values.get(ap.rate_k, 1.0) if ap.rate_k else 1.0)
            out[loop] = PDGains(Kc=values[ap.angle_p] * kd, Kd=kd)
    alt = profile.altitude
    if all(n in values for n in (alt.pos_p, alt.vel_p, alt.hover_thrust)):
        hover = values[alt.hover_thrust]
        if alt.accel_p:
            a = _accel_gain(alt, values.get(alt.accel_p))
            kd = values[alt.vel_p] * a / (1 + a * G_M_S2 / hover)
        else:
            kd = values[alt.vel_p] * hover / G_M_S2
        out[Loop.ALTITUDE] = PDGains(Kc=values[alt.pos_p] * kd, Kd=kd)
    side = profile.side
    if side.pos_p in values and side.vel_p in values:
        kd = values[side.vel_p] / G_M_S2
        out[Loop.X] = out[Loop.Y] = PDGains(Kc=values[side.pos_p] * kd, Kd=kd)
    return out
