"""The real PX4 firmware's own SITL build (``px4_sitl_default``) with its built-in SIH physics.

No external simulator: PX4's Simulation-In-Hardware module (``simulator_sih``) flies a quad-x
inside the px4 process, paced to wall-clock time (it falls behind real time on a loaded host,
never runs ahead). The build is looked up in ``$PX4_SITL_DIR`` (default ``~/px4-sitl``): either
a PX4-Autopilot tree itself or a folder holding one as ``PX4-Autopilot/``; the binary is
``build/px4_sitl_default/bin/px4`` in it (docs/px4-sitl.md).

Each instance ``I`` is started as ``px4 -d -i I -w RUN_DIR build/px4_sitl_default/etc`` (no
shell, parameters kept in ``RUN_DIR``, wiped by :meth:`Px4Sitl.start`) and, per PX4's own
``px4-rc.mavlink``, serves MAVLink on UDP: the GCS link listens on ``18570 + I`` (answers the
address that writes to it first: connect with ``udpout:``), the offboard/API link listens on
``14580 + I`` and sends to ``14540 + I``. Its MAVLink system id is ``I + 1``.

Example
-------
>>> from mrft_gcs.sitl.px4sitl import Px4Sitl, free_instance, why_not
>>> if why_not() is None:                                     # doctest: +SKIP
...     with Px4Sitl.start(free_instance(), "/tmp/px4") as sitl:
...         link = VehicleLink.connect(sitl.gcs)
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType

from pymavlink import mavutil

from mrft_gcs.errors import LinkError

__all__ = ["SITL_DIR", "BUILD_DIR", "BINARY", "AIRFRAME", "Px4Sitl", "why_not", "free_instance",
           "wait_ready", "Readiness"]

SITL_DIR = Path(os.environ.get("PX4_SITL_DIR", Path.home() / "px4-sitl"))


def _build_dir(root: Path) -> Path:
    """The ``px4_sitl_default`` build folder under ``root`` (a PX4 tree or its parent)."""
    for tree in (root, root / "PX4-Autopilot"):
        if (tree / "build" / "px4_sitl_default").is_dir():
            return tree / "build" / "px4_sitl_default"
    return root / "PX4-Autopilot" / "build" / "px4_sitl_default"


BUILD_DIR = _build_dir(SITL_DIR)
BINARY = BUILD_DIR / "bin" / "px4"
#: PX4's SIH quadrotor-x airframe for SITL (ROMFS init.d-posix/airframes/10040_sihsim_quadx)
AIRFRAME = "sihsim_quadx"
#: MAV_SYS_STATUS_PREARM_CHECK: PX4 sets it healthy when its arming checks pass
_PREARM_BIT = 0x10000000
#: UDP ports of instance 0: those PX4's px4-rc.mavlink binds (GCS, offboard, payload, gimbal,
#: SIH view) and the one its offboard link sends to (the readiness wait listens there)
_LOCAL_PORTS = (18570, 14580, 14280, 13030, 19450, 14540)


def why_not() -> str | None:
    """One line saying why the PX4 SITL cannot run here, or ``None`` when it can."""
    if not BINARY.is_file():
        return (f"no PX4 SITL build at {BINARY}: build PX4 v1.14-v1.16 px4_sitl_default "
                f"(docs/px4-sitl.md) or set PX4_SITL_DIR")
    if not (BUILD_DIR / "etc" / "init.d-posix" / "rcS").is_file():
        return f"the PX4 build at {BUILD_DIR} has no etc/init.d-posix/rcS: rebuild it"
    if not any((BUILD_DIR / "etc" / "init.d-posix" / "airframes").glob(f"*_{AIRFRAME}")):
        return f"the PX4 build at {BUILD_DIR} has no {AIRFRAME} airframe (PX4 v1.14 or later)"
    return None


def _udp_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind(("0.0.0.0", port))
        except OSError:
            return False
    return True


def free_instance(first: int = 1, last: int = 10) -> int:
    """The first instance in ``[first, last)`` none of whose UDP ports is bound (instances
    above 9 share PX4's offboard port 14549, so the range stops there; 0 is the one people
    start by hand)."""
    for instance in range(first, last):
        if all(_udp_free(p + instance) for p in _LOCAL_PORTS):
            return instance
    raise LinkError(f"no free PX4 SITL instance in {first}-{last - 1}: stop one")


@dataclass(frozen=True)
class Readiness:
    """What :func:`wait_ready` saw.

    Attributes
    ----------
    heartbeat_s : float
        Wall time from the call to the first heartbeat (s); ``nan`` if none came.
    ready_s : float
        Wall time to arming checks passed and a global position (s); ``nan`` if not reached.
    autopilot : int
        ``MAV_AUTOPILOT`` of the heartbeat (12 = PX4), -1 if none.
    """

    heartbeat_s: float
    ready_s: float
    autopilot: int

    @property
    def ready(self) -> bool:
        return self.ready_s == self.ready_s


def wait_ready(connection: str, timeout_s: float) -> Readiness:
    """Wait until the PX4 at ``connection`` sends heartbeats, reports its arming checks passed
    (SYS_STATUS pre-arm bit) and a global position (GLOBAL_POSITION_INT: EKF2 has GPS).

    Sends GCS heartbeats at 1 Hz on a ``udpout:`` link (PX4 answers only once written to);
    on ``udp:`` (listening) it only listens. PX4 latches each UDP link to the first address
    that writes to it, so :meth:`Px4Sitl.start` waits on the offboard link and leaves the GCS
    link to the ground station.
    """
    t0 = time.monotonic()
    conn = mavutil.mavlink_connection(connection, source_system=254, source_component=190)
    hb_s = ready_s = float("nan")
    autopilot, prearm, position = -1, False, False
    last_beat = 0.0 if connection.startswith("udpout:") else float("inf")
    try:
        while time.monotonic() - t0 < timeout_s:
            now = time.monotonic()
            if now - last_beat >= 1.0:  # never true when listening (last_beat = inf)
                conn.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GCS,
                                        mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
                last_beat = now
            msg = conn.recv_match(type=["HEARTBEAT", "SYS_STATUS", "GLOBAL_POSITION_INT"],
                                  blocking=True, timeout=0.2)
            if msg is None:
                continue
            kind = msg.get_type()
            if kind == "HEARTBEAT" and msg.get_srcComponent() == 1:
                if hb_s != hb_s:
                    hb_s, autopilot = time.monotonic() - t0, msg.autopilot
            elif kind == "SYS_STATUS":
                prearm = bool(msg.onboard_control_sensors_health & _PREARM_BIT)
            elif kind == "GLOBAL_POSITION_INT":
                position = True
            if hb_s == hb_s and prearm and position:
                ready_s = time.monotonic() - t0
                break
    finally:
        conn.close()
    return Readiness(hb_s, ready_s, autopilot)


@dataclass(frozen=True)
class Px4Sitl:
    """A running PX4 SITL (SIH quad-x) started by :meth:`start`; :meth:`stop` ends it.

    Attributes
    ----------
    instance : int
        PX4 instance number (``-i``): ports ``18570 + instance`` ..., system id ``instance + 1``.
    run_dir : Path
        Its working folder (``parameters.bson``, ``log/``, ``px4.log`` = its console output).
    pid : int
        The px4 process id.
    readiness : Readiness
        Heartbeat and ready times.
    """

    instance: int
    run_dir: Path
    pid: int
    readiness: Readiness

    @classmethod
    def start(cls, instance: int, run_dir: str | Path, *, ready_timeout_s: float = 90.0,
              require_ready: bool = True) -> Px4Sitl:
        """Boot a PX4 SITL with factory parameters (``run_dir`` is emptied first) and return
        once it is ready to arm or ``ready_timeout_s`` passed.

        Parameters
        ----------
        instance : int
            PX4 instance number (see :func:`free_instance`).
        run_dir : str or Path
            Scratch folder for it.
        ready_timeout_s : float
            Longest wait for arming checks passed and a global position (s).
        require_ready : bool
            Stop it and raise :class:`LinkError` when it did not get ready; otherwise go on
            and say so in :attr:`readiness`.
        """
        reason = why_not()
        if reason is not None:
            raise LinkError(reason)
        run_dir = Path(run_dir)
        if run_dir.exists():
            shutil.rmtree(run_dir)
        run_dir.mkdir(parents=True)
        env = dict(os.environ, PX4_SIM_MODEL=AIRFRAME, PX4_SIMULATOR="sihsim")
        # PX4_SIM_SPEED_FACTOR would scale its failsafe timeouts: real time only here
        env.pop("PX4_SIM_SPEED_FACTOR", None)
        env.pop("PX4_SYS_AUTOSTART", None)
        with open(run_dir / "px4.log", "wb") as log:
            proc = subprocess.Popen(
                [str(BINARY), "-d", "-i", str(instance), "-w", str(run_dir),
                 str(BUILD_DIR / "etc")],
                cwd=run_dir, env=env, stdin=subprocess.DEVNULL, stdout=log,
                stderr=subprocess.STDOUT, start_new_session=True)
        ready = wait_ready(f"udpin:127.0.0.1:{14540 + instance}", ready_timeout_s)
        sitl = cls(instance, run_dir, proc.pid, ready)
        if proc.poll() is not None or (require_ready and not ready.ready):
            sitl.stop()
            tail = (run_dir / "px4.log").read_text(errors="replace").strip()[-400:]
            raise LinkError(f"the PX4 SITL did not get ready in {ready_timeout_s:g} s (exit "
                            f"{proc.poll()}, heartbeat after {ready.heartbeat_s:.1f} s; a host "
                            f"too loaded?): {tail}")
        return sitl

    def running(self) -> bool:
        """Whether the px4 process is still alive."""
        try:
            os.kill(self.pid, 0)
        except ProcessLookupError:
            return False
        return not _is_zombie(self.pid)

    def stop(self, timeout_s: float = 10.0) -> None:
        """SIGTERM this px4 process (by its id only), SIGKILL it if it outlives ``timeout_s``."""
        for sig in (signal.SIGTERM, signal.SIGKILL):
            try:
                os.kill(self.pid, sig)
            except ProcessLookupError:
                return
            end = time.monotonic() + timeout_s
            while time.monotonic() < end:
                if _reap(self.pid):
                    return
                time.sleep(0.1)

    @property
    def gcs(self) -> str:
        """Connection string of PX4's GCS link (it answers whoever writes to it first)."""
        return f"udpout:127.0.0.1:{18570 + self.instance}"

    @property
    def offboard(self) -> str:
        """Connection string of PX4's offboard/API link (PX4 sends to ``14540 + I``)."""
        return f"udp:127.0.0.1:{14540 + self.instance}"

    @property
    def system_id(self) -> int:
        return self.instance + 1

    def __enter__(self) -> Px4Sitl:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()


def _reap(pid: int) -> bool:
    """Whether ``pid`` is gone (collects it when it is our child)."""
    try:
        done, _ = os.waitpid(pid, os.WNOHANG)
    except ChildProcessError:  # not our child: alive while signal 0 reaches it
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        return _is_zombie(pid)
    return done == pid


def _is_zombie(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] == "Z"
    except OSError:
        return False
