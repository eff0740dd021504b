"""The MAVLink parameter protocol, with a backup before every write (README, safety).

:class:`ParamClient` reads one parameter (PARAM_REQUEST_READ), all of them
(PARAM_REQUEST_LIST, re-requesting indices that went missing), and writes a set
of values safely:

1. every name is read first: a name the vehicle lacks fails before anything is written;
2. the current values go to a timestamped backup file in QGroundControl's
   ``.params`` format (QGC and MAVProxy load it too) before the first write;
3. each PARAM_SET is read back (PARAM_VALUE) and retried;
4. if a value does not stick, what was already written is rolled back and
   :class:`~mrft_gcs.errors.ParameterError` names the parameter.

:meth:`ParamClient.restore` puts a backup file back the same way (backing up the
values it replaces, so a restore can itself be undone).
"""

from __future__ import annotations

import datetime as _dt
import math
import os
import struct
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from functools import partial
from pathlib import Path

from mrft_gcs.errors import InputFileError, LinkError, ParameterError
from mrft_gcs.link.vehicle import ParamReport, VehicleLink
from mrft_gcs.telemetry import AutopilotFamily

__all__ = [
    "Param",
    "ParamChange",
    "WriteResult",
    "ParamClient",
    "BackupEntry",
    "write_params_file",
    "read_params_file",
    "MAV_PARAM_TYPE_REAL32",
]

MAV_PARAM_TYPE_REAL32 = 9
_INT_TYPES = {1: "<B", 2: "<b", 3: "<H", 4: "<h", 5: "<I", 6: "<i"}  # MAV_PARAM_TYPE -> struct
_MAX_NAME = 16


@dataclass(frozen=True)
class Param:
    """A parameter value as the vehicle holds it (ints decoded to their integer value)."""

    name: str
    value: float
    param_type: int = MAV_PARAM_TYPE_REAL32


@dataclass(frozen=True)
class ParamChange:
    """One write: the value before and the value read back after."""

    name: str
    old: float
    new: float


@dataclass(frozen=True)
class WriteResult:
    """What :meth:`ParamClient.write` did: the backup made first, then the changes."""

    backup_path: Path
    changes: tuple[ParamChange, ...]


@dataclass(frozen=True)
class BackupEntry:
    """One line of a ``.params`` file."""

    vehicle_id: int
    component_id: int
    param: Param


def _as_float32(x: float) -> float:
    return struct.unpack("<f", struct.pack("<f", x))[0]


def _has_index(index: int, report: ParamReport) -> bool:
    return report.index == index


def _same(a: float, b: float, param_type: int) -> bool:
    if param_type in _INT_TYPES:
        return round(a) == round(b)
    fa, fb = _as_float32(a), _as_float32(b)
    return fa == fb or math.isclose(fa, fb, rel_tol=1e-6, abs_tol=1e-9)


class ParamClient:
    """Parameter reads and safe writes over a :class:`~mrft_gcs.link.VehicleLink`.

    Parameters
    ----------
    link : VehicleLink
    timeout_s : float
        Wait for each PARAM_VALUE answer.
    retries : int
        Extra attempts per read or write.
    """

    def __init__(self, link: VehicleLink, timeout_s: float = 0.5, retries: int = 3) -> None:
        self.link = link
        self.timeout_s = timeout_s
        self.retries = retries
        # PX4 sends integer parameters bytewise in the float field; ArduPilot casts them.
        self._bytewise = link.family is not AutopilotFamily.ARDUPILOT

    # ------------------------------------------------------------------ encoding
    def _decode(self, r: ParamReport) -> Param:
        value = r.value
        if r.param_type in _INT_TYPES and self._bytewise:
            value = float(struct.unpack("<i", struct.pack("<f", r.value))[0])
        return Param(r.name, value, r.param_type)

    def _encode(self, value: float, param_type: int) -> float:
        if param_type in _INT_TYPES and self._bytewise:
            return struct.unpack("<f", struct.pack("<i", int(round(value))))[0]
        return float(value)

    # ------------------------------------------------------------------ reading
    def read(self, name: str) -> Param:
        """Read one parameter by name.

        Raises
        ------
        ParameterError
            If the vehicle does not answer for ``name`` (it has no such parameter).
        """
        _check_name(name)
        with self.link.subscribe(ParamReport) as sub:
            for _ in range(self.retries + 1):
                self.link.send_param_request_read(name)
                r = sub.wait_for(lambda e: e.name == name, self.timeout_s)
                if r is not None:
                    return self._decode(r)
        raise ParameterError(f"vehicle has no parameter {name} (no answer to "
                             f"{self.retries + 1} reads): check the profile matches this autopilot")

    def read_many(self, names: Iterable[str]) -> dict[str, Param]:
        """Read several parameters (each by name); ParameterError names the first missing one."""
        return {n: self.read(n) for n in names}

    def read_all(self, idle_s: float = 0.5, timeout_s: float = 60.0) -> dict[str, Param]:
        """Fetch every parameter with PARAM_REQUEST_LIST; missing indices are re-requested.

        Raises
        ------
        ParameterError
            If some indices never arrive after the re-requests.
        """
        got: dict[int, Param] = {}
        extra: dict[str, Param] = {}
        count = -1
        deadline = time.monotonic() + timeout_s
        with self.link.subscribe(ParamReport) as sub:
            self.link.send_param_request_list()
            while time.monotonic() < deadline:
                r = sub.get(idle_s)
                if r is None:
                    break
                assert isinstance(r, ParamReport)
                count = max(count, r.count)
                if 0 <= r.index < 0xFFFF:
                    got[r.index] = self._decode(r)
                else:
                    extra[r.name] = self._decode(r)
                if count > 0 and len(got) >= count:
                    break
            if count < 0:
                raise ParameterError("vehicle sent no parameters in answer to PARAM_REQUEST_LIST: "
                                     "check the link and that the vehicle has booted")
            for _ in range(self.retries + 1):
                missing = [i for i in range(count) if i not in got]
                if not missing:
                    break
                for i in missing:
                    self.link.send_param_request_read(index=i)
                    r = sub.wait_for(partial(_has_index, i), self.timeout_s)
                    if r is not None:
                        got[i] = self._decode(r)
        missing = [i for i in range(count) if i not in got]
        if missing:
            raise ParameterError(f"vehicle did not send parameters at indices {missing[:10]} of "
                                 f"{count} after re-requests: retry on a better link")
        params = {p.name: p for p in got.values()}
        params.update(extra)
        return dict(sorted(params.items()))

    # ------------------------------------------------------------------ writing
    def _set(self, name: str, value: float, param_type: int) -> Param | None:
        """PARAM_SET with read-back and retries; the last value read back, None if no answer."""
        last: Param | None = None
        with self.link.subscribe(ParamReport) as sub:
            for _ in range(self.retries + 1):
                self.link.send_param_set(name, self._encode(value, param_type), param_type)
                r = sub.wait_for(lambda e: e.name == name, self.timeout_s)
                if r is None:
                    # Some autopilots answer a PARAM_SET only when the value changes: read it.
                    self.link.send_param_request_read(name)
                    r = sub.wait_for(lambda e: e.name == name, self.timeout_s)
                if r is not None:
                    last = self._decode(r)
                    if _same(last.value, value, param_type):
                        return last
        return last

    def write_known(self, values: Mapping[str, float], known: Mapping[str, Param]
                    ) -> tuple[ParamChange, ...]:
        """Write ``values`` with read-back, for parameters already backed up: ``known``
        holds each one's type (e.g. from the write that backed them up), so nothing is read
        first (ArduPilot answers a read only from its 10 Hz parameter stream). A value that
        does not stick raises ParameterError naming it; nothing is rolled back."""
        out = []
        for name, value in values.items():
            if name not in known:
                raise ParameterError(f"{name} was not backed up before this write")
            new = self._set(name, float(value), known[name].param_type)
            if new is None or not _same(new.value, float(value), known[name].param_type):
                seen = "no answer" if new is None else f"vehicle reports {new.value:g}"
                raise ParameterError(f"parameter {name} did not stick: wrote {value:g}, {seen}")
            out.append(ParamChange(name, known[name].value, new.value))
        return tuple(out)

    def write(self, values: Mapping[str, float], backup_dir: str | os.PathLike[str] = ".",
              *, label: str = "backup") -> WriteResult:
        """Back up, then write ``values`` with read-back; all or nothing.

        Parameters
        ----------
        values : mapping of name -> value
            Written in this order.
        backup_dir : path
            Folder for the backup file ``params-<label>-<YYYYmmdd-HHMMSS>.params``.

        Raises
        ------
        ParameterError
            A name the vehicle lacks or a non-finite value (nothing written); a value that
            does not stick (what was written is rolled back; the message names it).
        """
        for name, v in values.items():
            _check_name(name)
            if not math.isfinite(float(v)):
                raise ParameterError(f"refusing to write non-finite value {v} to {name}")
        current = self.read_many(values)
        backup = self._backup(current.values(), Path(backup_dir), label)
        done: list[tuple[Param, Param]] = []  # (old, new read back)
        for name, value in values.items():
            old = current[name]
            new = self._set(name, float(value), old.param_type)
            if new is None or not _same(new.value, float(value), old.param_type):
                seen = "no answer" if new is None else f"vehicle reports {new.value:g}"
                failed = self._rollback([*(o for o, _ in done), old])
                tail = ("; rolled back the parameters written before it"
                        if not failed else
                        f"; rollback of {', '.join(failed)} failed too: run 'mrft-tune params "
                        f"restore {backup}'")
                raise ParameterError(f"parameter {name} did not stick: wrote {value:g}, {seen}"
                                     f"{tail} (backup {backup})")
            done.append((old, new))
        return WriteResult(backup, tuple(ParamChange(o.name, o.value, n.value) for o, n in done))

    def _rollback(self, olds: list[Param]) -> list[str]:
        failed = []
        for p in reversed(olds):
            try:
                back = self._set(p.name, p.value, p.param_type)
            except LinkError:
                back = None
            if back is None or not _same(back.value, p.value, p.param_type):
                failed.append(p.name)
        return failed

    def _backup(self, params: Iterable[Param], folder: Path, label: str) -> Path:
        stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / f"params-{label}-{stamp}.params"
        n = 1
        while path.exists():
            n += 1
            path = folder / f"params-{label}-{stamp}-{n}.params"
        write_params_file(path, params, self.link.target_system, self.link.target_component,
                          stack=self.link.family.value)
        return path

    def restore(self, backup_path: str | os.PathLike[str],
                backup_dir: str | os.PathLike[str] | None = None) -> WriteResult:
        """Write back every value of a ``.params`` file (read back, rolled back on failure).

        The values replaced are backed up first (next to the file unless ``backup_dir``).
        Entries of other vehicle ids are skipped when the file has some for this vehicle.
        """
        entries = read_params_file(backup_path)
        mine = [e for e in entries if e.vehicle_id == self.link.target_system] or entries
        values = {e.param.name: e.param.value for e in mine}
        folder = Path(backup_dir) if backup_dir is not None else Path(backup_path).parent
        return self.write(values, folder, label="before-restore")


def _check_name(name: str) -> None:
    if not name or len(name) > _MAX_NAME or not name.isascii():
        raise ParameterError(f"'{name}' is not a MAVLink parameter name (1-16 ASCII characters)")


# ---------------------------------------------------------------------- .params files
_HEADER_COLUMNS = "# Vehicle-Id Component-Id Name Value Type"


def write_params_file(path: str | os.PathLike[str], params: Iterable[Param], vehicle_id: int = 1,
                      component_id: int = 1, stack: str = "") -> Path:
    """Write QGroundControl's ``.params`` format (tab-separated, ``#`` header lines).

    Floats are written with 18 decimals as QGC does; integer types as integers. The
    file is flushed to disk before returning (a backup must survive a crash).
    """
    path = Path(path)
    now = _dt.datetime.now().isoformat(timespec="seconds")
    lines = [f"# Onboard parameters for Vehicle {vehicle_id}", "#",
             f"# Stack: {stack or 'unknown'}", f"# Written by mrft-tune at {now}", "#",
             _HEADER_COLUMNS]
    for p in params:
        value = f"{int(round(p.value))}" if p.param_type in _INT_TYPES else f"{p.value:.18f}"
        lines.append(f"{vehicle_id}\t{component_id}\t{p.name}\t{value}\t{p.param_type}")
    with open(path, "w", encoding="ascii", newline="\n") as f:
        f.write("\n".join(lines) + "\n")
        f.flush()
        os.fsync(f.fileno())
    return path


def read_params_file(path: str | os.PathLike[str]) -> list[BackupEntry]:
    """Read a QGroundControl ``.params`` file.

    Raises
    ------
    InputFileError
        Missing file, a malformed line (the message gives its number) or no parameters.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as err:
        raise InputFileError(f"cannot read parameter file {path}: {err.strerror or err}") from err
    out = []
    for no, line in enumerate(text.splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        fields = line.split("\t") if "\t" in line else line.split()
        try:
            if len(fields) != 5:
                raise ValueError
            vid, cid, name, value, ptype = fields
            param = Param(name.strip(), float(value), int(ptype))
            _check_name(param.name)
            if not math.isfinite(param.value):
                raise ValueError
            out.append(BackupEntry(int(vid), int(cid), param))
        except (ValueError, ParameterError):
            raise InputFileError(f"{path}:{no}: not a .params line (expected tab-separated "
                                 f"vehicle-id, component-id, name, value, type)") from None
    if not out:
        raise InputFileError(f"{path} holds no parameters")
    return out
