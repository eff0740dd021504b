"""Fleet tuning: several vehicles from one file, concurrently (one thread per vehicle) or in turn.

A fleet file is TOML::

    [defaults]                      # optional; every key may be overridden per vehicle
    profile = "px4"
    altitude_m = 1.0
    backup_dir = "fleet-runs"       # each vehicle gets its own sub-folder (name)

    [[vehicle]]
    name = "alpha"
    connect = "udp:127.0.0.1:14540"
    profile = "sitl"                # autopilot profile
    actuation = "torque"            # optional: torque | attitude
    loops = ["altitude", "roll", "pitch"]   # optional: default all the path can tune
    max_tilt_deg = 30.0             # optional safety overrides (SafetyLimits fields)
    baud = 921600                   # optional, serial links only
    signing_key = "alpha.key"       # optional MAVLink 2 signing key file
    heartbeat_timeout_s = 5.0       # optional
    dry_link = false                # connect and check only, do not fly

Each vehicle runs :func:`mrft_gcs.flight.api.tune` on its own link. A failure (no heartbeat,
aborted test, parameter that will not stick, or any other error) ends that vehicle only; it is
recorded with its error and exit code and the others go on. :func:`tune_fleet` never raises
for a vehicle's failure: the caller reads :attr:`FleetResult.failed` (the CLI turns it into
exit code 8, :class:`~mrft_gcs.errors.FleetError`).
"""

from __future__ import annotations

import math
import os
import threading
import time
import tomllib
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mrft_gcs.errors import LinkError, MrftError, UsageError
from mrft_gcs.flight.api import requested_loops, tune
from mrft_gcs.flight.report import report_dict
from mrft_gcs.link.connection import parse_connection_string
from mrft_gcs.loops import Loop
from mrft_gcs.profiles import Actuation, SafetyLimits, load_profile

__all__ = ["VehicleSpec", "FleetSpec", "VehicleOutcome", "FleetResult", "StatusFn",
           "load_fleet", "parse_fleet", "tune_fleet"]

_LIMIT_KEYS = tuple(vars(SafetyLimits()))
_KEYS = {"name", "connect", "profile", "actuation", "altitude_m", "backup_dir", "dry_link",
         "loops", "baud", "signing_key", "heartbeat_timeout_s", *_LIMIT_KEYS}
_LOOP_NAMES = tuple(lp.value for lp in Loop)


@dataclass(frozen=True)
class VehicleSpec:
    """One vehicle of a fleet file (units in the names; ``None``: the tune's default).

    ``loops`` are :class:`~mrft_gcs.loops.Loop` values; ``None`` tunes every loop the
    actuation path can tune.
    """

    name: str
    connect: str
    profile: str = "px4"
    actuation: str | None = None
    altitude_m: float = 1.0
    backup_dir: str = "."
    dry_link: bool = False
    limits: Mapping[str, float] = field(default_factory=dict)
    loops: tuple[str, ...] | None = None
    baud: int | None = None
    signing_key: str | None = None
    heartbeat_timeout_s: float = 5.0


@dataclass(frozen=True)
class FleetSpec:
    vehicles: tuple[VehicleSpec, ...]
    source: str = "<fleet>"


def _positive(where: str, key: str, val: Any) -> float:
    if isinstance(val, bool) or not isinstance(val, int | float) or not (
            math.isfinite(val) and val > 0):
        raise UsageError(f"{where}: '{key}' must be a positive number, got {val!r}")
    return float(val)


def _loops(where: str, val: Any, actuation: Actuation) -> tuple[str, ...]:
    """Loop names checked as :func:`mrft_gcs.flight.api.tune` checks them (in Loop order)."""
    if not isinstance(val, list) or not val or not all(isinstance(n, str) for n in val):
        raise UsageError(f"{where}: 'loops' must be a non-empty list of loop names "
                         f"({', '.join(_LOOP_NAMES)})")
    try:
        chosen = requested_loops(val, actuation)
    except UsageError as err:
        raise UsageError(f"{where}: 'loops': {err}") from None
    return tuple(lp.value for lp in Loop if lp in chosen)


def _vehicle(merged: Mapping[str, Any], where: str, default_name: str) -> VehicleSpec:
    unknown = set(merged) - _KEYS
    if unknown:
        raise UsageError(f"{where}: unknown key(s) {sorted(unknown)}; allowed {sorted(_KEYS)}")
    connect = merged.get("connect")
    if not isinstance(connect, str) or not connect:
        raise UsageError(f"{where}: 'connect' (a connection string) is required")
    limits = {k: _positive(where, k, merged[k]) for k in _LIMIT_KEYS if k in merged}
    profile = str(merged.get("profile", "px4"))
    prof = load_profile(profile)  # fail on a bad profile before anything flies
    actuation = merged.get("actuation")
    if actuation is not None and actuation not in [a.value for a in Actuation]:
        raise UsageError(f"{where}: 'actuation' must be torque or attitude, got {actuation!r}")
    act = Actuation(actuation) if actuation is not None else prof.actuation
    loops = _loops(where, merged["loops"], act) if "loops" in merged else None
    baud = merged.get("baud")
    if baud is not None and (isinstance(baud, bool) or not isinstance(baud, int) or baud <= 0):
        raise UsageError(f"{where}: 'baud' must be a positive integer, got {baud!r}")
    try:  # a typo in one vehicle's connection must not wait until the others fly
        parse_connection_string(connect, baud)
    except LinkError as err:
        raise UsageError(f"{where}: 'connect': {err}") from None
    key = merged.get("signing_key")
    if key is not None and not isinstance(key, str):
        raise UsageError(f"{where}: 'signing_key' must be a path to the key file")
    dry = merged.get("dry_link", False)
    if not isinstance(dry, bool):
        raise UsageError(f"{where}: 'dry_link' must be true or false")
    return VehicleSpec(
        str(merged.get("name", default_name)), connect, profile, actuation,
        _positive(where, "altitude_m", merged.get("altitude_m", 1.0)),
        str(merged.get("backup_dir", ".")), dry, limits, loops, baud, key,
        _positive(where, "heartbeat_timeout_s", merged.get("heartbeat_timeout_s", 5.0)))


def parse_fleet(data: Mapping[str, Any], source: str = "<fleet>") -> FleetSpec:
    """Validate a parsed fleet table (UsageError naming the vehicle and the field)."""
    defaults = data.get("defaults", {})
    vehicles = data.get("vehicle")
    if not isinstance(defaults, dict) or not isinstance(vehicles, list) or not vehicles:
        raise UsageError(f"{source}: needs at least one [[vehicle]] table (name, connect)")
    out: list[VehicleSpec] = []
    for i, v in enumerate(vehicles):
        if not isinstance(v, dict):
            raise UsageError(f"{source}: vehicle {i + 1} is not a table")
        merged = {**defaults, **v}
        out.append(_vehicle(merged, f"{source}: vehicle {merged.get('name', i + 1)}",
                            f"vehicle{i + 1}"))
    names = [v.name for v in out]
    if len(set(names)) != len(names):
        raise UsageError(f"{source}: vehicle names must be unique, got {names}")
    return FleetSpec(tuple(out), source)


def load_fleet(path: str | os.PathLike[str]) -> FleetSpec:
    """Read and validate a fleet TOML file."""
    try:
        data = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError) as err:
        raise UsageError(f"cannot read fleet file {path}: {err}") from None
    return parse_fleet(data, str(path))


@dataclass(frozen=True)
class VehicleOutcome:
    """What happened to one vehicle. ``result`` is its TuneResult (partial on failure)."""

    name: str
    connect: str
    status: str  # "ok", "dry-link", or "error:<code>:<Class>"
    error: str | None
    exit_code: int
    duration_s: float
    result: Any = None

    @property
    def ok(self) -> bool:
        return self.exit_code == 0


@dataclass(frozen=True)
class FleetResult:
    vehicles: tuple[VehicleOutcome, ...]
    duration_s: float
    serial: bool

    @property
    def failed(self) -> tuple[VehicleOutcome, ...]:
        return tuple(v for v in self.vehicles if not v.ok)

    def as_dict(self) -> dict[str, Any]:
        """One JSON for the fleet: a summary per vehicle and each vehicle's tune report.

        ``report`` is the vehicle's tune report (README's schema; partial if it failed) or
        null where nothing was flown (no heartbeat, a bad argument).
        """
        return {
            "schema": "mrft-gcs/fleet-1", "serial": self.serial, "duration_s": self.duration_s,
            "ok": not self.failed,
            "vehicles": [{"name": v.name, "connect": v.connect, "status": v.status,
                          "error": v.error, "exit_code": v.exit_code,
                          "duration_s": v.duration_s,
                          "report": report_dict(v.result) if v.result is not None else None}
                         for v in self.vehicles],
        }


#: ``f(vehicle_name, event)``: event is "started", then tune progress snapshots (dicts, see
#: :meth:`mrft_gcs.flight.sequence.TuningSequence.snapshot`), then the vehicle's
#: :class:`VehicleOutcome`.
StatusFn = Callable[[str, Any], None]


def _tune_kwargs(spec: VehicleSpec) -> dict[str, Any]:
    """Keyword arguments of :func:`mrft_gcs.flight.api.tune` set by the fleet file."""
    prof = load_profile(spec.profile)
    kw: dict[str, Any] = dict(
        actuation=spec.actuation, limits=prof.safety.with_overrides(**spec.limits),
        z_ref_m=spec.altitude_m, dry_link=spec.dry_link,
        heartbeat_timeout_s=spec.heartbeat_timeout_s)
    if spec.loops is not None:
        kw["loops"] = spec.loops
    if spec.baud is not None:
        kw["baud"] = spec.baud
    if spec.signing_key is not None:
        kw["signing_key"] = spec.signing_key
    return kw


def _tune_one(spec: VehicleSpec, tuner: Callable[..., Any],
              on_status: StatusFn | None) -> VehicleOutcome:
    t0 = time.monotonic()
    if on_status is not None:
        on_status(spec.name, "started")
    backup = Path(spec.backup_dir) / spec.name
    try:
        backup.mkdir(parents=True, exist_ok=True)
        res = tuner(spec.connect, load_profile(spec.profile), backup_dir=backup,
                    on_progress=(lambda snap: on_status(spec.name, snap)) if on_status else None,
                    **_tune_kwargs(spec))
        status = getattr(res, "status", "ok")
        code = 0 if status in ("ok", "dry-link") else 1
        out = VehicleOutcome(spec.name, spec.connect, status, getattr(res, "error", None), code,
                             time.monotonic() - t0, res)
    except MrftError as err:
        out = VehicleOutcome(spec.name, spec.connect, f"error:{err.exit_code}:"
                             f"{type(err).__name__}", str(err), err.exit_code,
                             time.monotonic() - t0, err.partial_result)
    except Exception as err:  # a bug in one vehicle's run must not stop the others
        out = VehicleOutcome(spec.name, spec.connect, "error:1:internal",
                             f"{type(err).__name__}: {err}", 1, time.monotonic() - t0)
    if on_status is not None:
        on_status(spec.name, out)
    return out


def tune_fleet(fleet: FleetSpec | Mapping[str, Any] | str | os.PathLike[str], *,
               serial: bool = False, tuner: Callable[..., Any] | None = None,
               on_status: StatusFn | None = None) -> FleetResult:
    """Tune every vehicle of ``fleet``.

    Parameters
    ----------
    fleet : FleetSpec, mapping or path
        A :class:`FleetSpec`, a table shaped like the fleet file (``{"defaults": {...},
        "vehicle": [{...}, ...]}``), or a path to a fleet TOML.
    serial : bool
        One after the other instead of concurrently (one thread and one link per vehicle).
        A live tune is a real-time job (a 250 Hz setpoint stream, relay cycles of 0.2 s):
        concurrent tunes need about half a CPU core each, plus a SITL's (README "Fleet").
    tuner : callable, optional
        Replaces :func:`mrft_gcs.flight.api.tune` (same signature): for tests.
    on_status : callable, optional
        ``f(name, event)`` (see :data:`StatusFn`), from the vehicles' threads, one call at
        a time: keep it short (it runs in the tune's thread).

    Returns
    -------
    FleetResult
        In the file's order. Failed vehicles are in :attr:`FleetResult.failed`.

    Raises
    ------
    UsageError
        A bad fleet file, before anything connects. A vehicle's own failure never raises.

    Examples
    --------
    >>> import tempfile
    >>> from mrft_gcs.fleet import tune_fleet
    >>> def fake(connection, profile, **kw):   # stands in for a live tune
    ...     return type("R", (), {"status": "ok", "error": None, "kw": kw})()
    >>> with tempfile.TemporaryDirectory() as runs:
    ...     r = tune_fleet({"defaults": {"profile": "sitl", "backup_dir": runs},
    ...                     "vehicle": [{"name": "a", "connect": "udp:127.0.0.1:14540",
    ...                                  "loops": ["altitude", "roll"]}]}, tuner=fake)
    >>> [(v.name, v.status) for v in r.vehicles], r.failed
    ([('a', 'ok')], ())
    >>> r.vehicles[0].result.kw["loops"]
    ('roll', 'altitude')
    """
    if isinstance(fleet, FleetSpec):
        spec = fleet
    elif isinstance(fleet, Mapping):
        spec = parse_fleet(fleet)
    else:
        spec = load_fleet(fleet)
    run: Callable[..., Any] = tune if tuner is None else tuner
    t0 = time.monotonic()
    if serial:
        outcomes = [_tune_one(v, run, on_status) for v in spec.vehicles]
    else:
        lock = threading.Lock()

        def safe(name: str, event: Any) -> None:
            if on_status is not None:
                with lock:
                    on_status(name, event)

        with ThreadPoolExecutor(max_workers=len(spec.vehicles),
                                thread_name_prefix="fleet") as pool:
            futures = [pool.submit(_tune_one, v, run, safe if on_status else None)
                       for v in spec.vehicles]
            outcomes = [f.result() for f in futures]
    return FleetResult(tuple(outcomes), time.monotonic() - t0, serial)
