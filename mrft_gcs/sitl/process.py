"""Start and stop the SITL: configuration, a server builder, and a subprocess wrapper.

:class:`SitlProcess` runs ``python -m mrft_gcs.sitl ...`` as a real subprocess (what tests and
the demo use); :func:`make_server` builds the same server in-process (what ``mrft-tune sitl``
runs in the foreground).

Example
-------
>>> from mrft_gcs.sitl import SitlProcess
>>> with SitlProcess(vehicle="qdrone", port=14550) as sitl:   # doctest: +SKIP
...     link = mavutil.mavlink_connection(sitl.connection_string)
"""

from __future__ import annotations

import dataclasses
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType

from mrft_gcs.errors import LinkError, UsageError
from mrft_gcs.sitl.airframe import Airframe, load_airframe
from mrft_gcs.sitl.population import random_airframe

__all__ = [
    "DEFAULT_PORT",
    "SitlConfig",
    "SitlProcess",
    "make_server",
    "parse_effects",
    "read_signing_key",
    "free_udp_port",
    "vehicle_airframe",
    "build_vehicle",
]

DEFAULT_PORT = 14540
READY_PREFIX = "SITL ready:"


def free_udp_port(host: str = "127.0.0.1") -> int:
    """A UDP port that is free right now (bind port 0 and ask which one the OS gave)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def parse_effects(items: Iterable[str]) -> dict[str, float]:
    """``["sensor_lpf=30", ...]`` -> ``{"sensor_lpf": 30.0}`` (raises :class:`UsageError`)."""
    out: dict[str, float] = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name.strip():
            raise UsageError(f"bad --effect '{item}': write NAME=VALUE, e.g. sensor_lpf=30")
        try:
            out[name.strip()] = float(value)
        except ValueError:
            raise UsageError(f"bad --effect '{item}': '{value}' is not a number") from None
    return out


def read_signing_key(path: str | Path) -> bytes:
    """A MAVLink 2 signing key from a file: 32 raw bytes, or 64 hex digits."""
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise UsageError(f"cannot read signing key file '{path}': {exc.strerror}") from None
    if len(data) == 32:
        return data
    text = data.strip()
    if len(text) == 64:
        try:
            return bytes.fromhex(text.decode("ascii"))
        except (UnicodeDecodeError, ValueError):
            pass
    raise UsageError(f"signing key file '{path}' must hold 32 raw bytes or 64 hex digits")


@dataclass(frozen=True)
class SitlConfig:
    """Everything that defines one SITL run (command line beats profile beats default)."""

    #: bundled profile or TOML path (default ``qdrone``); with ``physics="rotorpy"`` one of
    #: RotorPy's parameter sets (default ``crazyfliebrushless``)
    vehicle: str | None = None
    port: int = DEFAULT_PORT
    speedup: float = 1.0
    effects: Mapping[str, float] = field(default_factory=dict)
    seed: int = 0
    signing_key_file: str | None = None
    wind_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    host: str = "127.0.0.1"
    #: draw the vehicle at random from this seed (:func:`random_airframe`) instead
    random_seed: int | None = None
    #: ``native`` (the project's physics) or ``rotorpy`` (:mod:`mrft_gcs.sitl.rotorpy_physics`)
    physics: str = "native"

    @property
    def connection_string(self) -> str:
        """What the ground station should connect to (pymavlink syntax)."""
        return f"udp:{self.host}:{self.port}"


def _check_physics(physics: str) -> None:
    from mrft_gcs.sitl.rotorpy_physics import PHYSICS_BACKENDS

    if physics not in PHYSICS_BACKENDS:
        raise UsageError(f"physics '{physics}': use one of {', '.join(PHYSICS_BACKENDS)}")


def vehicle_airframe(vehicle: str | None, random_seed: int | None = None,
                     physics: str = "native") -> Airframe:
    """The bundled or TOML vehicle ``vehicle`` (default ``qdrone``), or the random one of
    ``random_seed``; with ``physics="rotorpy"`` the airframe matching that RotorPy vehicle
    (its hover linearisation: the truth to score on)."""
    _check_physics(physics)
    if physics == "rotorpy":
        from mrft_gcs.sitl.rotorpy_physics import rotorpy_airframe

        return rotorpy_airframe(vehicle, random_seed).airframe
    if random_seed is not None:
        return random_airframe(random_seed)
    return load_airframe(vehicle or "qdrone")


def build_vehicle(cfg: SitlConfig):  # -> SimVehicle
    """The in-process vehicle of ``cfg``, on the physics it names; raises :class:`UsageError`."""
    from mrft_gcs.sitl.vehicle import SimVehicle

    _check_physics(cfg.physics)
    if cfg.physics == "rotorpy":
        from mrft_gcs.sitl.rotorpy_physics import rotorpy_airframe, rotorpy_vehicle

        spec = rotorpy_airframe(cfg.vehicle, cfg.random_seed)
        spec = dataclasses.replace(spec, airframe=spec.airframe.with_effects(dict(cfg.effects)))
        return rotorpy_vehicle(spec, seed=cfg.seed, wind_m_s=cfg.wind_m_s)
    airframe = vehicle_airframe(cfg.vehicle, cfg.random_seed).with_effects(dict(cfg.effects))
    return SimVehicle(airframe, seed=cfg.seed, wind_m_s=cfg.wind_m_s)


def make_server(cfg: SitlConfig):  # -> SitlServer (imported lazily: pymavlink is heavy)
    """Build the vehicle and its MAVLink server for ``cfg``; raises :class:`UsageError`."""
    from mrft_gcs.sitl.server import SitlServer

    if not 0 < cfg.port < 65536:
        raise UsageError(f"port {cfg.port} is out of range 1-65535")
    if not cfg.speedup > 0 or cfg.speedup > 100:
        raise UsageError(f"speedup {cfg.speedup} must be in (0, 100]")
    if len(cfg.wind_m_s) != 3:
        raise UsageError("wind needs 3 components (north, east, down) in m/s")
    vehicle = build_vehicle(cfg)
    key = read_signing_key(cfg.signing_key_file) if cfg.signing_key_file else None
    return SitlServer(vehicle, port=cfg.port, host=cfg.host, speedup=cfg.speedup,
                      signing_key=key)


class SitlProcess:
    """The SITL as a subprocess, started on ``__enter__`` and stopped on ``__exit__``.

    The subprocess runs in a session of its own, as a vehicle would on its own computer:
    where the kernel groups processes by session for fair CPU sharing (Linux autogroup),
    it is then not one share with the ground station that tunes it, and a Ctrl-C in the
    terminal reaches only the ground station, which lands the vehicle before stopping
    it. It exits by itself when its parent process goes away.

    Parameters
    ----------
    vehicle : str, optional
        Bundled profile name or path to a TOML profile (default ``qdrone``); with
        ``physics="rotorpy"`` a RotorPy parameter set (default ``crazyfliebrushless``).
    port : int or None
        UDP port the ground station listens on; ``None`` picks a free one.
    speedup : float
        Simulated seconds per wall second (not bit-reproducible; see README).
    effects : mapping
        Unmodelled effects, e.g. ``{"sensor_lpf": 30.0}``.
    seed : int
        Sensor-noise seed.
    signing_key : bytes or None
        32-byte MAVLink 2 signing key; unsigned commands and setpoints are then ignored.
    wind_m_s : (3,) float
        Constant wind, NED.
    startup_timeout_s : float
        How long to wait for the subprocess to report ready.
    random_seed : int or None
        Fly the random vehicle of this seed (:func:`mrft_gcs.sitl.random_airframe`)
        instead of ``vehicle`` (with ``physics="rotorpy"``:
        :func:`mrft_gcs.sitl.rotorpy_physics.rotorpy_airframe` of this seed).
    physics : str
        ``native`` (the project's physics, default) or ``rotorpy`` (RotorPy's, the ``test``
        extra).

    Raises
    ------
    UsageError
        Bad vehicle name, effect or key (checked before the process starts).
    LinkError
        The subprocess did not come up.
    """

    def __init__(self, vehicle: str | None = None, port: int | None = DEFAULT_PORT,
                 speedup: float = 1.0, effects: Mapping[str, float] | None = None,
                 seed: int = 0, signing_key: bytes | None = None,
                 wind_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0),
                 startup_timeout_s: float = 20.0, random_seed: int | None = None,
                 physics: str = "native") -> None:
        # fail early, in this process
        self.airframe = vehicle_airframe(vehicle, random_seed, physics).with_effects(
            dict(effects or {}))
        self.random_seed = random_seed
        self.physics = physics
        if signing_key is not None and len(signing_key) != 32:
            raise UsageError("signing_key must be exactly 32 bytes")
        self.vehicle = vehicle
        self.port = free_udp_port() if port is None else int(port)
        self.speedup = float(speedup)
        self.effects = dict(effects or {})
        self.seed = int(seed)
        self.signing_key = signing_key
        self.wind_m_s = tuple(float(w) for w in wind_m_s)
        self.startup_timeout_s = startup_timeout_s
        self._proc: subprocess.Popen[str] | None = None
        self._tmpdir: tempfile.TemporaryDirectory[str] | None = None
        self._stderr_path: Path | None = None

    @property
    def connection_string(self) -> str:
        """pymavlink connection string for the ground station (``udp:127.0.0.1:PORT``)."""
        return f"udp:127.0.0.1:{self.port}"

    @property
    def mavsdk_address(self) -> str:
        """The same for MAVSDK (``udpin://127.0.0.1:PORT``)."""
        return f"udpin://127.0.0.1:{self.port}"

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    @property
    def pid(self) -> int | None:
        """The vehicle process's id while it runs (tests stall it with SIGSTOP/SIGCONT)."""
        return self._proc.pid if self.running and self._proc is not None else None

    def command(self) -> list[str]:
        """The argument vector of the subprocess."""
        cmd = [sys.executable, "-m", "mrft_gcs.sitl", "--port", str(self.port),
               "--speedup", repr(self.speedup), "--seed", str(self.seed),
               "--wind", ",".join(repr(w) for w in self.wind_m_s), "--exit-with-parent"]
        if self.vehicle is not None:
            cmd += ["--vehicle", str(self.vehicle)]
        if self.physics != "native":
            cmd += ["--physics", self.physics]
        if self.random_seed is not None:
            cmd += ["--random", str(self.random_seed)]
        for name, value in self.effects.items():
            cmd += ["--effect", f"{name}={value!r}"]
        return cmd

    def start(self) -> SitlProcess:
        """Start the subprocess and wait until it serves."""
        if self.running:
            return self
        self._tmpdir = tempfile.TemporaryDirectory(prefix="mrft-sitl-")
        cmd = self.command()
        if self.signing_key is not None:
            key_path = Path(self._tmpdir.name) / "signing.key"
            key_path.write_bytes(self.signing_key)
            key_path.chmod(0o600)
            cmd += ["--signing-key", str(key_path)]
        self._stderr_path = Path(self._tmpdir.name) / "stderr.txt"
        with self._stderr_path.open("w") as err:
            self._proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err, text=True,
                                          env={**os.environ, "PYTHONUNBUFFERED": "1"},
                                          start_new_session=True)
        deadline = time.monotonic() + self.startup_timeout_s
        assert self._proc.stdout is not None
        import selectors

        with selectors.DefaultSelector() as sel:
            sel.register(self._proc.stdout, selectors.EVENT_READ)
            while time.monotonic() < deadline:
                if sel.select(timeout=0.1):
                    line = self._proc.stdout.readline()
                    if line.startswith(READY_PREFIX):
                        return self
                    if not line and self._proc.poll() is not None:
                        break
                elif self._proc.poll() is not None:
                    break
        tail = self._stderr_tail()
        self.stop()
        what = self.vehicle or ("random " + str(self.random_seed) if self.random_seed is not None
                                else "default vehicle")
        raise LinkError(f"the SITL subprocess did not start ({what}, {self.physics} physics): "
                        f"{tail or 'no output'}")

    def _stderr_tail(self) -> str:
        try:
            text = self._stderr_path.read_text() if self._stderr_path else ""
        except OSError:
            return ""
        lines = [ln for ln in text.strip().splitlines() if ln.strip()]
        return lines[-1] if lines else ""

    def stop(self, timeout_s: float = 5.0) -> int | None:
        """SIGTERM, then kill after ``timeout_s``; returns the exit code."""
        proc, self._proc = self._proc, None
        code = None
        if proc is not None:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
                try:
                    proc.wait(timeout_s)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait(timeout_s)
            code = proc.returncode
            if proc.stdout is not None:
                proc.stdout.close()
        if self._tmpdir is not None:
            self._tmpdir.cleanup()
            self._tmpdir = None
        return code

    def __enter__(self) -> SitlProcess:
        return self.start()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()
