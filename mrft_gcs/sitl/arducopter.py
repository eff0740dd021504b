"""The real ArduCopter firmware's own SITL build as a process, for tests and benchmarks.

Wraps the recipe of ``../shared/external/ardupilot-sitl`` (``start.sh`` / ``stop.sh``): the
build in ``$ARDUPILOT_SITL_DIR`` (default ``~/ardupilot-sitl``), the scripts in
``$ARDUPILOT_SITL_RECIPE`` (default ``shared/external/ardupilot-sitl`` next to the checkout).
Each instance ``I`` serves MAVLink on TCP ``5760 + 10 I`` (SERIAL0), ``+2`` (SERIAL1), ``+3``
(SERIAL2) and reads simulated RC on UDP ``5501 + 10 I``.

Example
-------
>>> from mrft_gcs.sitl.arducopter import ArduCopterSitl, free_instance, why_not
>>> if why_not() is None:                                     # doctest: +SKIP
...     with ArduCopterSitl.start(free_instance(), "/tmp/ac", {"SCR_ENABLE": 1}) as sitl:
...         link = VehicleLink.connect(sitl.serial0)
"""

from __future__ import annotations

import os
import socket
import subprocess
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType

from mrft_gcs.errors import LinkError
from mrft_gcs.link import VehicleLink
from mrft_gcs.telemetry import AttitudeTarget, LocalPosition

__all__ = ["RECIPE", "SITL_DIR", "BINARY", "ArduCopterSitl", "why_not", "listening",
           "free_instance", "fly_level"]

RECIPE = Path(os.environ.get("ARDUPILOT_SITL_RECIPE", Path(__file__).resolve().parents[3]
                             / "shared" / "external" / "ardupilot-sitl"))
SITL_DIR = Path(os.environ.get("ARDUPILOT_SITL_DIR", Path.home() / "ardupilot-sitl"))
BINARY = SITL_DIR / "ardupilot" / "build" / "sitl" / "bin" / "arducopter"
#: what start.sh prints (stderr) once the vehicle has a position and the RC is at neutral
READY_LINE = "RC at neutral sticks"


def why_not() -> str | None:
    """One line saying why the ArduCopter SITL cannot run here, or ``None`` when it can."""
    if not BINARY.is_file():
        return (f"no ArduCopter SITL build at {BINARY}: build it with {RECIPE / 'build.sh'} or "
                f"set ARDUPILOT_SITL_DIR")
    if not (RECIPE / "start.sh").is_file():
        return f"no start.sh in {RECIPE}: set ARDUPILOT_SITL_RECIPE"
    return None


def listening(port: int) -> bool:
    """Whether a TCP server listens on loopback ``port``."""
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


def free_instance(first: int = 31, last: int = 90) -> int:
    """The first instance in ``[first, last)`` none of whose MAVLink ports is taken (the
    default range stays clear of the instances people start by hand, 0-9)."""
    for instance in range(first, last):
        if not any(listening(5760 + 10 * instance + k) for k in (0, 2, 3)):
            return instance
    raise LinkError(f"no free ArduCopter SITL instance in {first}-{last - 1}: stop one "
                    f"(stop.sh PID) or pick one with --instance")


@dataclass(frozen=True)
class ArduCopterSitl:
    """A running ArduCopter SITL started by :meth:`start`; :meth:`stop` ends it.

    Attributes
    ----------
    instance : int
        SITL instance number (ports ``5760 + 10 instance`` ...).
    run_dir : Path
        Its folder (``eeprom.bin``, ``logs/``, ``arducopter.log``).
    pid : str
        The arducopter process id, as start.sh printed it.
    ready : bool
        Whether start.sh saw a position fix and put the RC at neutral sticks.
    boot_log : str
        start.sh's progress output (stderr).
    """

    instance: int
    run_dir: Path
    pid: str
    ready: bool
    boot_log: str

    @classmethod
    def start(cls, instance: int, run_dir: str | Path,
              defaults: Mapping[str, float] | None = None, *, ready_timeout_s: float = 120.0,
              require_ready: bool = False) -> ArduCopterSitl:
        """Boot a wiped SITL (parameters back to the recipe's defaults files) that does not
        wait for a ground station, and return once it is ready or ``ready_timeout_s`` passed.

        Parameters
        ----------
        instance : int
            SITL instance number.
        run_dir : str or Path
            Scratch folder for it; ``defaults`` go into ``run_dir/extra.parm``.
        defaults : mapping of str to float, optional
            Parameters loaded after the recipe's defaults (e.g. ``{"SCR_ENABLE": 1}``: they
            take effect at boot, which scripting needs).
        ready_timeout_s : float
            Longest wait for a position fix (s).
        require_ready : bool
            Stop it and raise :class:`LinkError` when it did not get ready (a host too
            loaded); otherwise go on and say so in :attr:`ready`.
        """
        reason = why_not()
        if reason is not None:
            raise LinkError(reason)
        run_dir = Path(run_dir)
        run_dir.mkdir(parents=True, exist_ok=True)
        env = dict(os.environ, ARDUPILOT_SITL_DIR=str(SITL_DIR), INSTANCE=str(instance),
                   NOWAIT="1", WIPE="1", RUN_DIR=str(run_dir),
                   READY_TIMEOUT=f"{ready_timeout_s:g}")
        if defaults:
            extra = run_dir / "extra.parm"
            extra.write_text("".join(f"{n} {v:g}\n" for n, v in defaults.items()))
            env["EXTRA_DEFAULTS"] = str(extra)
        else:
            env.pop("EXTRA_DEFAULTS", None)
        out = subprocess.run([str(RECIPE / "start.sh")], env=env, capture_output=True,
                             text=True, timeout=ready_timeout_s + 60)
        if out.returncode != 0:
            raise LinkError(f"ArduCopter SITL start.sh failed: {out.stderr.strip()[-500:]}")
        sitl = cls(instance, run_dir, out.stdout.strip().splitlines()[-1],
                   READY_LINE in out.stderr, out.stderr)
        if require_ready and not sitl.ready:
            sitl.stop()
            raise LinkError(f"the ArduCopter SITL did not get ready (a host too loaded?): "
                            f"{out.stderr.strip()[-300:]}")
        return sitl

    def stop(self) -> None:
        """Stop the process (stop.sh acts on this PID only, and only if it is arducopter)."""
        subprocess.run([str(RECIPE / "stop.sh"), self.pid], capture_output=True, timeout=30)

    @property
    def base_port(self) -> int:
        return 5760 + 10 * self.instance

    @property
    def serial0(self) -> str:
        """Connection string of SERIAL0 (the ground station's)."""
        return f"tcp:127.0.0.1:{self.base_port}"

    @property
    def serial1(self) -> str:
        return f"tcp:127.0.0.1:{self.base_port + 2}"

    @property
    def serial2(self) -> str:
        return f"tcp:127.0.0.1:{self.base_port + 3}"

    @property
    def rc_port(self) -> int:
        """UDP port of the simulated RC receiver (8 channels of ``<H`` microseconds)."""
        return 5501 + 10 * self.instance

    def __enter__(self) -> ArduCopterSitl:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()


def fly_level(link: VehicleLink, seconds: float, alt_m: float = 2.0,
              until_m: float | None = None) -> float:
    """Fly level in GUIDED_NOGPS: SET_ATTITUDE_TARGET at 50 Hz, thrust from a PD on altitude
    (``GUID_OPTIONS`` 8: raw thrust), for ``seconds`` or until above ``until_m`` (m).

    Returns the last altitude (m). Wall-clock time: on a loaded host the SITL runs slower
    than real time."""
    z = vz = 0.0
    end = time.monotonic() + seconds
    while time.monotonic() < end and (until_m is None or -z < until_m):
        while (s := link.next_sample(0.0)) is not None:
            if isinstance(s, LocalPosition):
                z, vz = s.z_m, s.vz_m_s
        thrust = min(0.75, max(0.2, 0.4 + 0.15 * (alt_m + z) + 0.15 * vz))
        link.send_attitude_target(AttitudeTarget(0.0, (1.0, 0.0, 0.0, 0.0), thrust))
        time.sleep(0.02)
    return -z
