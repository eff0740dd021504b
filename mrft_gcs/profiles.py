"""Autopilot profiles (docs/writing-gains.md): identified PD gains -> autopilot parameters.

A profile is a TOML file in ``profiles/`` (``px4``, ``ardupilot``, ``sitl``) loaded
with :mod:`tomllib` into frozen dataclasses and validated on load. It says which
actuation path the relay tests use, which custom-mode numbers to switch to, the
default safety limits, and the parameter names each loop's gains land in.

The conversion (docs/writing-gains.md) rests on one identity. The deployed PD acts on the
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
    accelerations in cm/s^2, i.e. ``A = 0.1 ACCZ_P`` of throttle per m/s^2 (the
    metre-based PSC_D_ACC_P is that 0.1 ACCZ_P itself: ``accel_p_per_m_s2`` 1), plus
    ACCZ_I, error filters on the velocity and acceleration loops and a 2 Hz throttle
    low-pass. With the identified altitude model, POSZ_P and VELZ_P are chosen so that
    this whole cascade equals the PD at the PD's crossover
    (:func:`ardupilot_altitude_cascade`), the throttle filter being in the model when the
    relay flew through it (the profile's ``test_params``). Without a model (dry
    conversions): the measured acceleration a = g du / hover fed straight back gives
    du = A/(1 + A g/hover) a_sp, so VELZ_P = Kd (1 + A g / hover) / A and POSZ_P =
    Kc/Kd, which holds only where the acceleration loop is fast next to the altitude loop.
"""

from __future__ import annotations

import enum
import math
import os
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from mrft_gcs.errors import ParameterError, UsageError
from mrft_gcs.link.modes import CustomMode
from mrft_gcs.loops import Loop
from mrft_gcs.plant import InnerModel
from mrft_gcs.telemetry import AutopilotFamily

if TYPE_CHECKING:
    from mrft_gcs.link.firmware import Firmware

__all__ = [
    "Actuation",
    "PDGains",
    "SafetyLimits",
    "AngleRateParams",
    "CascadeParams",
    "AltitudeParams",
    "RatePathParams",
    "AutopilotProfile",
    "PROFILE_DIR",
    "G_M_S2",
    "load_profile",
    "parse_profile",
    "gains_to_params",
    "params_to_gains",
    "Clamp",
    "ClampedParams",
    "clamp_to_ranges",
    "clamp_note",
    "params_in_range",
    "fit_profile",
    "AltitudeCascade",
    "ardupilot_altitude_cascade",
]

G_M_S2 = 9.80665
PROFILE_DIR = Path(__file__).resolve().parent.parent / "profiles"


class Actuation(enum.Enum):
    """How relay tests reach the vehicle."""

    TORQUE = "torque"  # SET_ACTUATOR_CONTROL_TARGET group 0: all five loops from the GCS
    ATTITUDE = "attitude"  # SET_ATTITUDE_TARGET: autopilot keeps its attitude loop
    #: SET_ATTITUDE_TARGET body rates through a rate loop reduced to feed-forward
    #: (``[rate_path]``, :mod:`mrft_gcs.flight.ratepath`): all five loops from the GCS
    RATE = "rate"


@dataclass(frozen=True)
class PDGains:
    """``u = Kc e - Kd dy/dt`` in the SI units of the loop (see module docstring)."""

    Kc: float
    Kd: float


@dataclass(frozen=True)
class SafetyLimits:
    """Limits that abort a test and land (README, safety). Command line overrides them."""

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
    #: throttle per m/s^2 of acceleration error per unit of ``accel_p``: 0.1 where the
    #: loop works in cm/s^2 (PSC_ACCZ_P), 1 where it works in m/s^2 (PSC_D_ACC_P)
    accel_p_per_m_s2: float = 0.1
    #: ArduPilot's acceleration loop beyond its P, written with the gains so that the
    #: cascade the conversion matches is the one on the vehicle (None: not written, the
    #: value is assumed): I (same units as ``accel_p``), the input filter on its error (Hz)
    accel_i: str | None = None
    accel_i_value: float = 1.0
    accel_filt: str | None = None
    accel_filt_hz: float = 20.0
    #: the velocity PID's input filter on its error (Hz)
    vel_filt: str | None = None
    vel_filt_hz: float = 5.0
    #: the low-pass on the measured acceleration (ArduPilot INS_ACCEL_FILTER, Hz; 0: none)
    accel_meas_filt_hz: float = 0.0
    #: why a tune must not write this cascade's gains ('' : it may): a mapping not yet
    #: proven in the autopilot's own hold mode
    not_written: str = ""


@dataclass(frozen=True)
class RatePathParams:
    """``[rate_path]``: the autopilot's rate loop reduced to a pure feed-forward, so that a
    body-rate set point ``w`` [rad/s] comes out as the normalised torque ``k w``.

    Per axis (roll, pitch, yaw): the feed-forward gain's name and ``k`` [1/(rad/s)], the
    rate P and angle P names (the hand-over writes them in stages), and ``test_params``:
    every value set for the flight (backed up, restored at the end and on any abort).
    """

    ff: tuple[str, str, str]
    k: tuple[float, float, float]
    rate_p: tuple[str, str, str]
    angle_p: tuple[str, str, str]
    test_params: Mapping[str, float]


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
    #: ``name -> (min, max)`` of the values a tune may write (``[param_ranges]``)
    param_ranges: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    #: firmware versions (major, minor), both inclusive, whose parameter names these are;
    #: None: not tied to a version
    versions: tuple[tuple[int, int], tuple[int, int]] | None = None
    #: bundled profiles of the same autopilot with other parameter names (another version)
    alternatives: tuple[str, ...] = ()
    #: ``name -> value`` set before arming so that the relay tests see the plant the
    #: written gains will fly (``[test_params]``); backed up, restored after the flight
    #: and on any abort
    test_params: Mapping[str, float] = field(default_factory=dict)
    #: the body-rate path (None: the autopilot has none, or the profile does not say)
    rate_path: RatePathParams | None = None
    #: seconds of each hold in the comparison of the written gains with the old ones after
    #: the hand-over (``[hold_compare] seconds``, :mod:`mrft_gcs.flight.holdcompare`; 0: off)
    hold_compare_s: float = 0.0

    def fits_version(self, version: tuple[int, ...] | None) -> bool:
        """True if ``version`` is in :attr:`versions` (or either is unknown)."""
        if self.versions is None or version is None:
            return True
        return self.versions[0] <= tuple(version[:2]) <= self.versions[1]

    def versions_text(self) -> str:
        if self.versions is None:
            return "any version"
        (a, b), (c, d) = self.versions
        return f"{a}.{b} to {c}.{d}"

    def parameter_names(self) -> list[str]:
        """Every parameter a full tune writes or needs (hover thrust), in write order."""
        names: list[str] = []
        for group in (self.roll, self.pitch, self.altitude, self.side):
            for key, v in vars(group).items():
                if isinstance(v, str) and v not in names and key != "not_written":
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


def _pname(table: Mapping[str, Any], key: str, where: str) -> str:
    name = _need(table, key, str, where)
    if not (1 <= len(name) <= 16 and name.isascii() and name.replace("_", "").isalnum()):
        raise UsageError(f"{where}: '{name}' is not a parameter name (1-16 letters, digits, _)")
    return name


def _optional_pname(table: Mapping[str, Any], key: str, where: str) -> str | None:
    return _pname(table, key, where) if key in table else None


def _ranges(data: Mapping[str, Any], source: str,
            names: list[str]) -> dict[str, tuple[float, float]]:
    """``[param_ranges]``: ``NAME = [min, max]`` for parameters the profile maps."""
    where = f"{source} [param_ranges]"
    table = data.get("param_ranges", {})
    if not isinstance(table, dict):
        raise UsageError(f"{where}: must be a table of NAME = [min, max]")
    out: dict[str, tuple[float, float]] = {}
    for name, pair in table.items():
        if name not in names:
            raise UsageError(f"{where}: '{name}' is not a parameter of this profile (one of "
                             f"{', '.join(names)})")
        ok = (isinstance(pair, list) and len(pair) == 2
              and all(isinstance(v, int | float) and not isinstance(v, bool)
                      and math.isfinite(v) for v in pair))
        if not ok or not pair[0] < pair[1]:
            raise UsageError(f"{where}: '{name}' must be [min, max], two finite numbers with "
                             f"min < max, got {pair!r}")
        out[name] = (float(pair[0]), float(pair[1]))
    return out


def _versions(ap: Mapping[str, Any], where: str
              ) -> tuple[tuple[int, int], tuple[int, int]] | None:
    """``versions = ["4.3", "4.7"]``: major.minor, both inclusive."""
    if "versions" not in ap:
        return None
    pair = ap["versions"]
    try:
        lo, hi = (tuple(int(n) for n in str(v).split(".")) for v in pair)
        if len(pair) != 2 or len(lo) != 2 or len(hi) != 2 or lo > hi:
            raise ValueError
    except (TypeError, ValueError):
        raise UsageError(f"{where}: 'versions' must be [\"MAJOR.MINOR\", \"MAJOR.MINOR\"], "
                         f"lowest first, got {pair!r}") from None
    return (lo[0], lo[1]), (hi[0], hi[1])


def _positive(table: Mapping[str, Any], key: str, where: str, default: float) -> float:
    value = float(table.get(key, default))
    if not (math.isfinite(value) and value > 0):
        raise UsageError(f"{where}: '{key}' must be a positive number, got {value}")
    return value


def _nonnegative(table: Mapping[str, Any], key: str, where: str, default: float) -> float:
    value = table.get(key, default)
    if isinstance(value, bool) or not isinstance(value, int | float) or not (
            math.isfinite(value) and value >= 0):
        raise UsageError(f"{where}: '{key}' must be a number >= 0, got {value!r}")
    return float(value)


def _test_params(data: Mapping[str, Any], source: str,
                 key: str = "test_params") -> dict[str, float]:
    """``[test_params]``: ``NAME = value`` set for the flight and restored after it."""
    where = f"{source} [{key}]"
    table = data.get(key, {})
    if not isinstance(table, dict):
        raise UsageError(f"{where}: must be a table of NAME = value")
    out: dict[str, float] = {}
    for name, value in table.items():
        _pname({"name": name}, "name", where)
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(
                value):
            raise UsageError(f"{where}: '{name}' must be a finite number, got {value!r}")
        out[name] = float(value)
    return out


def _rate_path(data: Mapping[str, Any], source: str) -> RatePathParams | None:
    """``[rate_path]`` with its ``[rate_path.test_params]`` (None where absent)."""
    table = data.get("rate_path")
    if table is None:
        return None
    where = f"{source} [rate_path]"
    if not isinstance(table, dict):
        raise UsageError(f"{where}: must be a table")

    def three(key: str, kind: Any) -> tuple[Any, Any, Any]:
        v = _need(table, key, list, where)
        if len(v) != 3 or not all(isinstance(x, kind) and not isinstance(x, bool) for x in v):
            raise UsageError(f"{where}: '{key}' must list roll, pitch and yaw")
        return v[0], v[1], v[2]

    names = {key: three(key, str) for key in ("ff", "rate_p", "angle_p")}
    k = tuple(float(x) for x in three("k", int | float))
    if not all(math.isfinite(x) and x > 0 for x in k):
        raise UsageError(f"{where}: 'k' must be positive and finite, got {k}")
    test = _test_params(table, where)
    for name, kk in zip(names["ff"], k, strict=True):
        if test.get(name) != kk:
            raise UsageError(f"{where}: test_params must set {name} to its k {kk:g}")
    return RatePathParams(names["ff"], (k[0], k[1], k[2]), names["rate_p"], names["angle_p"],
                          test)


def parse_profile(data: Mapping[str, Any], source: str = "<profile>") -> AutopilotProfile:
    """Validate a parsed TOML table into a profile (UsageError naming the field)."""
    ap = _need(data, "autopilot", dict, source)
    w = f"{source} [autopilot]"
    try:
        family = AutopilotFamily(_need(ap, "family", str, w))
        actuation = Actuation(_need(ap, "actuation", str, w))
    except ValueError as err:
        raise UsageError(f"{w}: {err}; family is px4/ardupilot/generic, actuation "
                         f"torque/attitude/rate") from None
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
        return AngleRateParams(
            _pname(t, "angle_p", wa), _pname(t, "rate_p", wa), _pname(t, "rate_i", wa),
            _pname(t, "rate_d", wa), rate_k=_optional_pname(t, "rate_k", wa))

    st_side = _need(data, "side", dict, source)
    side = CascadeParams(*(_pname(st_side, k, f"{source} [side]")
                           for k in ("pos_p", "vel_p", "vel_i", "vel_d")))
    alt_t = _need(data, "altitude", dict, source)
    wal = f"{source} [altitude]"
    altitude = AltitudeParams(
        _pname(alt_t, "pos_p", wal), _pname(alt_t, "vel_p", wal), _pname(alt_t, "vel_i", wal),
        _pname(alt_t, "vel_d", wal), _pname(alt_t, "hover_thrust", wal),
        accel_p=_optional_pname(alt_t, "accel_p", wal),
        accel_p_value=_positive(alt_t, "accel_p_value", wal, 0.5),
        accel_p_per_m_s2=_positive(alt_t, "accel_p_per_m_s2", wal, 0.1),
        accel_i=_optional_pname(alt_t, "accel_i", wal),
        accel_i_value=_nonnegative(alt_t, "accel_i_value", wal, 1.0),
        accel_filt=_optional_pname(alt_t, "accel_filt", wal),
        accel_filt_hz=_nonnegative(alt_t, "accel_filt_hz", wal, 20.0),
        vel_filt=_optional_pname(alt_t, "vel_filt", wal),
        vel_filt_hz=_nonnegative(alt_t, "vel_filt_hz", wal, 5.0),
        accel_meas_filt_hz=_nonnegative(alt_t, "accel_meas_filt_hz", wal, 0.0),
        not_written=str(alt_t.get("not_written", "")))
    alternatives = ap.get("alternatives", [])
    if not (isinstance(alternatives, list) and all(isinstance(a, str) for a in alternatives)):
        raise UsageError(f"{w}: 'alternatives' must be a list of profile names")
    prof = AutopilotProfile(
        name=str(ap.get("name", Path(source).stem)), family=family,
        description=str(ap.get("description", "")), actuation=actuation, modes=modes,
        safety=safety, roll=angle("roll"), pitch=angle("pitch"), side=side,
        altitude=altitude, source=source, versions=_versions(ap, w),
        alternatives=tuple(alternatives), test_params=_test_params(data, source),
        rate_path=_rate_path(data, source),
        hold_compare_s=_nonnegative(data.get("hold_compare", {}), "seconds",
                                    f"{source} [hold_compare]", 0.0))
    return replace(prof, param_ranges=_ranges(data, source, prof.parameter_names()))


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
    """ArduPilot's acceleration loop: throttle per m/s^2 (ACCZ_P: 0.001 per cm/s^2 each)."""
    return alt.accel_p_per_m_s2 * (alt.accel_p_value if accel_p is None else accel_p)


@dataclass(frozen=True)
class AltitudeCascade:
    """ArduCopter's altitude cascade matched to a PD on an identified altitude model.

    Attributes
    ----------
    pos_p, vel_p : float
        PSC_POSZ_P [1/s] and PSC_VELZ_P [1/s] (the same numbers in the metre-based names).
    crossover_rad_s : float
        Where the PD's loop ``G (Kc + Kd s)`` crosses 1 [rad/s]; the onboard loop equals it
        there in gain and phase.
    pd_margin_deg, cascade_margin_deg : float
        Phase margins of the PD's loop and of the onboard cascade's loop [deg].
    cascade_crossover_rad_s : float
        Where the onboard loop crosses 1 [rad/s].
    cascade_gain_margin : float
        Factor on the onboard loop's gain that would make it cross -180 deg at unit gain
        above its crossover (inf: it never crosses there).
    low_gain_ratio : float
        ``|L_cascade| / |L_pd|`` at a fifth of the crossover (> 1: the acceleration loop's
        integrator adds low-frequency gain).
    """

    pos_p: float
    vel_p: float
    crossover_rad_s: float
    pd_margin_deg: float
    cascade_margin_deg: float
    cascade_crossover_rad_s: float
    cascade_gain_margin: float
    low_gain_ratio: float


def _lowpass(hz: float, s: np.ndarray) -> np.ndarray:
    return np.ones_like(s) if hz <= 0 else 1.0 / (1.0 + s / (2 * math.pi * hz))


def _crossover(w: np.ndarray, loop: np.ndarray) -> int:
    """Index of the first frequency of ``w`` at which ``|loop|`` falls through 1 (-1: none)."""
    above = np.abs(loop) >= 1.0
    idx = np.flatnonzero(above[:-1] & ~above[1:])
    return int(idx[0]) + 1 if len(idx) else -1


def ardupilot_altitude_cascade(model: InnerModel, gains: PDGains,
                               alt: AltitudeParams) -> AltitudeCascade:
    """PSC_POSZ_P and PSC_VELZ_P whose closed cascade equals ``gains`` at the crossover.

    ArduCopter's altitude controller (AC_PosControl::update_U_controller) is
    ``u = C_a (a_sp - F_m a)``, ``a_sp = V F_v (P (z_sp - z) - v)`` with ``C_a = A (1 +
    I/(P_a s)) F_a`` (``A = accel_p_per_m_s2 ACCZ_P`` throttle per m/s^2, ``F_a`` its error
    filter), ``F_v`` the velocity error filter and ``F_m`` the low-pass on the measured
    acceleration ``a = s^2 z``. Its loop is ``L = G C_a (V F_v (P + s) + s^2 F_m)``
    against the PD's ``G (Kc + Kd s)``. Equal at the PD's crossover ``w``:
    ``V (P + jw) = ((Kc + j w Kd) / C_a(jw) + w^2 F_m(jw)) / F_v(jw)``, one complex
    equation for the two real gains. The throttle low-pass the controller adds (2 Hz) is
    in ``G`` when the relay test flew through the same filter (``test_params``).

    Raises
    ------
    ValueError
        The PD does not cross over, or the match needs a gain <= 0.
    """
    w = np.geomspace(0.05, 500.0, 4000)
    s = 1j * w
    g = model.K * np.exp(-model.tau * s) / (s * (model.T_prop * s + 1) * (model.T1 * s + 1))
    pd = g * (gains.Kc + gains.Kd * s)
    i = _crossover(w, pd)
    if i < 0:
        raise ValueError("the altitude PD's loop never crosses unit gain")
    wc = float(w[i])
    sc = 1j * wc
    a = _accel_gain(alt)
    ratio_i = alt.accel_i_value / alt.accel_p_value  # the I term's zero [rad/s]

    def c_acc(x: Any) -> Any:
        return a * (1 + ratio_i / x) * _lowpass(alt.accel_filt_hz, x)

    fm = _lowpass(alt.accel_meas_filt_hz, np.array([sc]))[0]
    fv = _lowpass(alt.vel_filt_hz, np.array([sc]))[0]
    z = ((gains.Kc + gains.Kd * sc) / c_acc(sc) + wc ** 2 * fm) / fv
    if not (z.imag > 0 and z.real > 0):
        raise ValueError(f"no positive PSC_POSZ_P / PSC_VELZ_P match the altitude PD at "
                         f"{wc:.3g} rad/s (acceleration loop too slow for it)")
    vel_p = float(z.imag / wc)
    pos_p = float(z.real / vel_p)
    cas = g * c_acc(s) * (vel_p * _lowpass(alt.vel_filt_hz, s) * (pos_p + s)
                          + s ** 2 * _lowpass(alt.accel_meas_filt_hz, s))
    j = _crossover(w, cas)
    if j < 0:
        raise ValueError("the matched cascade's loop never crosses unit gain")

    def phase_from(loop: np.ndarray, k: int) -> np.ndarray:
        """Phase [deg] from index k up, unwrapped, starting in (-360, 0]."""
        ph = np.degrees(np.unwrap(np.angle(loop[k:])))
        return ph - 360.0 * math.ceil(ph[0] / 360.0)

    ph = phase_from(cas, j)
    beyond = np.flatnonzero((ph[:-1] > -180) & (ph[1:] <= -180))
    gm = float(1 / np.abs(cas[j + beyond[0] + 1])) if len(beyond) else math.inf
    k5 = int(np.searchsorted(w, wc / 5))
    return AltitudeCascade(pos_p, vel_p, wc, float(180.0 + phase_from(pd, i)[0]),
                           float(180.0 + ph[0]), float(w[j]), gm,
                           float(np.abs(cas[k5]) / np.abs(pd[k5])))


def gains_to_params(profile: AutopilotProfile, gains: Mapping[Loop, PDGains],
                    hover_thrust: float,
                    models: Mapping[Loop, InnerModel] | None = None) -> dict[str, float]:
    """Parameter values for the loops in ``gains`` (others are left out).

    Parameters
    ----------
    hover_thrust : float
        The vehicle's hover thrust in [0, 1] (``MPC_THR_HOVER`` / ``MOT_THST_HOVER``),
        read from the vehicle; used by the altitude conversion.
    models : mapping, optional
        Identified models; with the altitude model, a profile with an acceleration loop
        (``accel_p``: ArduPilot) gets the cascade matched at the crossover
        (:func:`ardupilot_altitude_cascade`, with its acceleration I and filters written
        too); without it, the fast-acceleration-loop approximation of the module docstring.

    Raises
    ------
    UsageError
        Gains not positive and finite, or no cascade matches the altitude PD.

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
        model = (models or {}).get(Loop.ALTITUDE)
        if alt.accel_p and model is not None:
            try:
                cas = ardupilot_altitude_cascade(model, g, alt)
            except ValueError as err:
                raise UsageError(f"altitude: {err}") from None
            out[alt.pos_p], out[alt.vel_p] = cas.pos_p, cas.vel_p
            out[alt.accel_p] = alt.accel_p_value
            for name, value in ((alt.accel_i, alt.accel_i_value),
                                (alt.accel_filt, alt.accel_filt_hz),
                                (alt.vel_filt, alt.vel_filt_hz)):
                if name:
                    out[name] = value
        elif alt.accel_p:
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


# ---------------------------------------------------------------------- ranges
#: what each profile key is, in words; I and D terms the design sets to zero
_STAGES = {"angle_p": "angle", "rate_p": "rate", "rate_k": "rate", "pos_p": "position",
           "vel_p": "velocity", "accel_p": "acceleration", "hover_thrust": "hover thrust",
           "rate_i": "rate I", "rate_d": "rate D", "vel_i": "velocity I", "vel_d": "velocity D",
           "accel_i": "acceleration I", "accel_filt": "acceleration filter",
           "vel_filt": "velocity filter"}


def _roles(profile: AutopilotProfile) -> dict[str, tuple[tuple[Loop, ...], str]]:
    """``name -> (loops it acts on, profile key)``."""
    out: dict[str, tuple[tuple[Loop, ...], str]] = {}
    for group, loops in ((profile.roll, (Loop.ROLL,)), (profile.pitch, (Loop.PITCH,)),
                         (profile.altitude, (Loop.ALTITUDE,)), (profile.side, (Loop.X, Loop.Y))):
        for key, name in vars(group).items():
            if key in _STAGES and isinstance(name, str):
                out.setdefault(name, (loops, key))
    return out


@dataclass(frozen=True)
class Clamp:
    """A computed value moved into the profile's range ``[lo, hi]``."""

    name: str
    wanted: float
    written: float
    lo: float
    hi: float
    loops: tuple[Loop, ...] = ()  # the loops the parameter acts on


@dataclass(frozen=True)
class ClampedParams:
    """Parameter values to write, inside the profile's ranges (:func:`params_in_range`).

    ``notes[i]`` explains ``clamps[i]``; ``gains`` are the PD gains the written values
    amount to (:func:`params_to_gains`), per loop written.
    """

    values: dict[str, float]
    clamps: tuple[Clamp, ...]
    notes: tuple[str, ...]
    gains: dict[Loop, PDGains]


def clamp_to_ranges(profile: AutopilotProfile,
                    values: Mapping[str, float]) -> tuple[dict[str, float], list[Clamp]]:
    """``values`` with each one that has a range in the profile put inside it.

    Names without a range pass unchanged; the order of ``values`` is kept.

    Examples
    --------
    >>> p = replace(load_profile("px4"), param_ranges={"MPC_Z_P": (0.1, 1.5)})
    >>> out, clamps = clamp_to_ranges(p, {"MPC_Z_P": 2.0, "MPC_XY_P": 3.0})
    >>> out, clamps[0].wanted
    ({'MPC_Z_P': 1.5, 'MPC_XY_P': 3.0}, 2.0)
    """
    roles = _roles(profile)
    out = dict(values)
    clamps: list[Clamp] = []
    for name, value in values.items():
        if name not in profile.param_ranges:
            continue
        lo, hi = profile.param_ranges[name]
        written = min(max(value, lo), hi)
        if written != value:
            out[name] = written
            clamps.append(Clamp(name, value, written, lo, hi, roles.get(name, ((), ""))[0]))
    return out, clamps


def clamp_note(profile: AutopilotProfile, clamp: Clamp, designed: Mapping[Loop, PDGains],
               in_effect: Mapping[Loop, PDGains]) -> str:
    """One line on a clamped value: the range, what was written, what it does to the loop.

    ``designed`` and ``in_effect`` are the PD gains of the unclamped and the written
    values (:func:`params_to_gains`); the first of ``clamp.loops`` found in both is quoted.
    """
    loops, key = _roles(profile).get(clamp.name, (clamp.loops, ""))
    where = " and ".join(lp.value for lp in loops)
    stage = _STAGES.get(key, "")
    if key.endswith(("_i", "_d")):
        effect = f"{where} {stage} term {clamp.written:g} where the PD design has {clamp.wanted:g}"
    elif clamp.written < clamp.wanted:
        effect = f"{where} {stage} loop slower than designed"
    else:
        effect = f"{where} {stage} loop faster than designed, with less phase margin"
    for lp in loops:
        d, e = designed.get(lp), in_effect.get(lp)
        if d is not None and e is not None and d != e:
            effect += (f"; in effect Kc {e.Kc:.4g}, Kd {e.Kd:.4g} instead of Kc {d.Kc:.4g}, "
                       f"Kd {d.Kd:.4g}")
            break
    side = "above" if clamp.wanted > clamp.hi else "below"
    return (f"{clamp.name}: the tuned {clamp.wanted:.4g} is {side} the profile's range "
            f"{clamp.lo:g} to {clamp.hi:g}; {clamp.written:g} written ({' '.join(effect.split())})")


def params_in_range(profile: AutopilotProfile, gains: Mapping[Loop, PDGains],
                    hover_thrust: float,
                    models: Mapping[Loop, InnerModel] | None = None) -> ClampedParams:
    """:func:`gains_to_params`, clamped into the profile's ranges, with a note per clamp.

    What a tune writes (and dry-run reports): a value outside its range is replaced by
    the nearer bound instead of failing the write on a vehicle that refuses it.

    Examples
    --------
    >>> p = replace(load_profile("px4"), param_ranges={"MC_ROLL_P": (0.0, 3.0)})
    >>> r = params_in_range(p, {Loop.ROLL: PDGains(Kc=1.0, Kd=0.25)}, 0.5)
    >>> r.values["MC_ROLL_P"], r.gains[Loop.ROLL]
    (3.0, PDGains(Kc=0.75, Kd=0.25))
    >>> r.notes[0].split(";")[0]
    "MC_ROLL_P: the tuned 4 is above the profile's range 0 to 3"
    """
    wanted = gains_to_params(profile, gains, hover_thrust, models)
    values, clamps = clamp_to_ranges(profile, wanted)
    hover = {profile.altitude.hover_thrust: hover_thrust}
    designed = params_to_gains(profile, {**wanted, **hover})
    in_effect = params_to_gains(profile, {**values, **hover})
    notes = tuple(clamp_note(profile, c, designed, in_effect) for c in clamps)
    # a loop nothing was clamped on keeps its gains (the altitude cascade matched at the
    # crossover does not invert to them by the fast-acceleration-loop formula)
    moved = {lp for c in clamps for lp in c.loops}
    return ClampedParams(values, tuple(clamps), notes,
                         {lp: (g if lp in moved else PDGains(gains[lp].Kc, gains[lp].Kd))
                          for lp, g in in_effect.items() if lp in gains})


# ---------------------------------------------------------------------- firmware
def _is_bundled(profile: AutopilotProfile) -> bool:
    return bool(profile.source) and Path(profile.source).resolve().parent == PROFILE_DIR


def fit_profile(requested: AutopilotProfile, firmware: Firmware,
                has_param: Callable[[str], bool]) -> tuple[AutopilotProfile, str]:
    """The profile whose parameter names the vehicle in front of us has, and a note why.

    ``requested`` and its ``alternatives`` (bundled profiles of the same autopilot with
    other names, e.g. ArduCopter's PSC_POSZ_P before and PSC_D_POS_P after the PSC_*
    renaming) are tried in order: those whose ``versions`` hold the firmware's version
    first, each confirmed by asking the vehicle for the parameter that differs
    (``has_param(name)``). A profile without alternatives is taken as it is.

    Raises
    ------
    UsageError
        The profile is for another autopilot than the one that answered.
    ParameterError
        None of the candidates' parameters is on the vehicle.
    """
    fam, fw_fam = requested.family, firmware.family
    known = (AutopilotFamily.PX4, AutopilotFamily.ARDUPILOT)
    if fam in known and fw_fam in known and fam is not fw_fam:
        bundled = sorted(p.stem for p in PROFILE_DIR.glob("*.toml")
                         if p.stem.startswith(fw_fam.value))
        raise UsageError(f"the vehicle is {firmware.name} but profile {requested.name} is for "
                         f"{fam.value}: use --profile {' or '.join(bundled) or fw_fam.value}")
    candidates = [requested]
    for name in requested.alternatives:
        alt = load_profile(name)
        if alt.family is fam and all(alt.name != c.name for c in candidates):
            candidates.append(alt)
    if len(candidates) == 1:
        note = ""
        if not requested.fits_version(firmware.version):
            note = (f"profile {requested.name} was written for {requested.versions_text()}, "
                    f"the vehicle runs {firmware.name}")
        return requested, note
    candidates.sort(key=lambda c: not c.fits_version(firmware.version))  # stable: keeps order
    how = "AUTOPILOT_VERSION" if firmware.version else "no version reported"
    for cand in candidates:
        probe = cand.altitude.pos_p
        if not has_param(probe):
            continue
        why = f"{firmware.name} ({how}); the vehicle has {probe}"
        if cand is not requested:
            why += f", not {requested.altitude.pos_p}"
        if not cand.fits_version(firmware.version):
            why += f" (profile written for {cand.versions_text()})"
        if cand is requested:
            return cand, f"parameter names of profile {cand.name}: {why}"
        return cand, f"profile {cand.name} instead of {requested.name}: {why}"
    probes = ", ".join(f"{c.altitude.pos_p} ({c.name})" for c in candidates)
    raise ParameterError(f"{firmware.name}: the vehicle has none of {probes}: name its "
                         f"parameters in a profile of your own (--profile FILE.toml)")
