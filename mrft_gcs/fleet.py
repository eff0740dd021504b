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
    max_tilt_deg = 30.0             # optional safety overrides (SafetyLimits fields)
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

from mrft_gcs.errors import MrftError, UsageError
from mrft_gcs.profiles import SafetyLimits, load_profile

__all__ = ["VehicleSpec", "FleetSpec", "VehicleOutcome", "FleetResult", "load_fleet",
           "parse_fleet", "tune_fleet"]

_LIMIT_KEYS = tuple(vars(SafetyLimits()))
_KEYS = {"name", "connect", "profile", "actuation", "altitude_m", "backup_dir", "dry_link",
         *_LIMIT_KEYS}


@dataclass(frozen=True)
class VehicleSpec:
    """One vehicle of a fleet file."""

    name: str
    connect: str
    profile: str = "px4"
    actuation: str | None = None
    altitude_m: float = 1.0
    backup_dir: str = "."
    dry_link: bool = False
    limits: Mapping[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class FleetSpec:
    vehicles: tuple[VehicleSpec, ...]
    source: str = "<fleet>"


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
        where = f"{source}: vehicle {merged.get('name', i + 1)}"
        unknown = set(merged) - _KEYS
        if unknown:
            raise UsageError(f"{where}: unknown key(s) {sorted(unknown)}; allowed {sorted(_KEYS)}")
        name, connect = merged.get("name", f"vehicle{i + 1}"), merged.get("connect")
        if not isinstance(connect, str) or not connect:
            raise UsageError(f"{where}: 'connect' (a connection string) is required")
        limits = {}
        for k in _LIMIT_KEYS:
            if k in merged:
                val = merged[k]
                if isinstance(val, bool) or not isinstance(val, int | float) or not (
                        math.isfinite(val) and val > 0):
                    raise UsageError(f"{where}: '{k}' must be a positive number")
                limits[k] = float(val)
        profile = str(merged.get("profile", "px4"))
        load_profile(profile)  # fail on a bad profile before anything flies
        out.append(VehicleSpec(str(name), connect, profile, merged.get("actuation"),
                               float(merged.get("altitude_m", 1.0)),
                               str(merged.get("backup_dir", ".")),
                               bool(merged.get("dry_link", False)), limits))
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
        """One JSON for the fleet: a summary per vehicle and each vehicle's tune report."""
        from mrft_gcs.flight.report import report_dict

        return {
            "schema": "mrft-gcs/fleet-1", "serial": self.serial, "duration_s": self.duration_s,
            "ok": not self.failed,
            "vehicles": [{"name": v.name, "connect": v.connect, "status": v.status,
                          "error": v.error, "exit_code": v.exit_code,
                          "duration_s": v.duration_s,
                          "report": report_dict(v.result) if v.result is not None else None}
                         for v in self.vehicles],
        }


#: ``f(vehicle_name, event)``: event is "started", "done" or a tune progress snapshot (dict)
StatusFn = Callable[[str, Any], None]


def _tune_one(spec: VehicleSpec, tuner: Callable[..., Any],
              on_status: StatusFn | None) -> VehicleOutcome:
    t0 = time.monotonic()
    if on_status is not None:
        on_status(spec.name, "started")
    prof = load_profile(spec.profile)
    limits = prof.safety.with_overrides(**spec.limits)
    backup = Path(spec.backup_dir) / spec.name
    try:
        backup.mkdir(parents=True, exist_ok=True)
        res = tuner(spec.connect, prof, actuation=spec.actuation, limits=limits,
                    z_ref_m=spec.altitude_m, dry_link=spec.dry_link, backup_dir=backup,
                    on_progress=(lambda snap: on_status(spec.name, snap)) if on_status else None)
        status = getattr(res, "status", "ok")
        code = 0 if status in ("ok", "dry-link") else 1
        out = VehicleOutcome(spec.name, spec.connect, status, getattr(res, "error", None), code,
                             time.monotonic() - t0, res)
    except MrftError as err:
        out = VehicleOutcome(spec.name, spec.connect, f"error:{err.exit_code}:"
                             f"{type(err).__name__}", str(err), err.exit_code,
                             time.monotonic() - t0, getattr(err, "partial_result", None))
    except Exception as err:  # a bug in one vehicle's run must not stop the others
        out = VehicleOutcome(spec.name, spec.connect, "error:1:internal",
                             f"{type(err).__name__}: {err}", 1, time.monotonic() - t0)
    if on_status is not None:
        on_status(spec.name, "done")
    return out


def tune_fleet(fleet: FleetSpec | str | os.PathLike[str], *, serial: bool = False,
               tuner: Callable[..., Any] | None = None,
               on_status: StatusFn | None = None) -> FleetResult:
    """Tune every vehicle of ``fleet`` (a FleetSpec or a path to a fleet TOML).

    Parameters
    ----------
    serial : bool
        One after the other instead of concurrently (one thread per vehicle).
    tuner : callable, optional
        Replaces :func:`mrft_gcs.flight.api.tune` (same signature): for tests.
    on_status : callable, optional
        ``f(name, event)`` from the vehicles' threads: keep it short and thread-safe.

    Returns
    -------
    FleetResult
        In the file's order. Failed vehicles are in :attr:`FleetResult.failed`.
    """
    spec = fleet if isinstance(fleet, FleetSpec) else load_fleet(fleet)
    if tuner is None:
        from mrft_gcs.flight.api import tune as tuner
    assert tuner is not None
    run: Callable[..., Any] = tuner
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
