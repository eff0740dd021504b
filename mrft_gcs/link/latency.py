"""Ask the OS to wake a thread on time: for the 250 Hz setpoint stream and its telemetry.

A relay test closes its loop through the ground station, so every wake-up latency (the
SITL's send, the GCS reader's receive, the stream's tick) adds delay to the loop. On a
busy machine a waking thread waits for a CPU; :func:`latency_hints` asks, unprivileged,
for less of that wait. It changes neither the thread's priority nor its share of CPU.

An idle CPU waits in a sleep state, and leaving it takes time: on a virtual machine the
host must schedule the halted virtual CPU again, which took up to 8-19 ms on the
development box. :class:`CpuWakeLatency` holds Linux's PM QoS request
(``/dev/cpu_dma_latency``, the mechanism real-time tools such as ``cyclictest`` use) so
that CPUs only use idle states they leave within the bound (0 us: poll, never halt) while
the setpoint stream runs. Writing it needs root or write access granted to the device (a
udev rule); without it the stream runs as before and says so.
"""

from __future__ import annotations

import ctypes
import os
import platform
import struct
import sys

from mrft_gcs.errors import UsageError

__all__ = ["latency_hints", "CpuWakeLatency", "CPU_LATENCY_ENV"]

_SLICE_NS = 100_000  # EEVDF custom slice (the kernel's minimum, 0.1 ms)
_PR_SET_TIMERSLACK = 29
_PM_QOS_DEVICE = "/dev/cpu_dma_latency"
#: environment variable: the CPU wake-up bound the stream asks for, in microseconds
#: (default 0), or ``off`` to ask for none
CPU_LATENCY_ENV = "MRFT_CPU_LATENCY_US"


class _SchedAttr(ctypes.Structure):
    _fields_ = [("size", ctypes.c_uint32), ("sched_policy", ctypes.c_uint32),
                ("sched_flags", ctypes.c_uint64), ("sched_nice", ctypes.c_int32),
                ("sched_priority", ctypes.c_uint32), ("sched_runtime", ctypes.c_uint64),
                ("sched_deadline", ctypes.c_uint64), ("sched_period", ctypes.c_uint64)]


#: (sched_setattr, sched_getattr) system call numbers
_SCHED_ATTR_CALLS = {"x86_64": (314, 315), "aarch64": (274, 275)}


def latency_hints() -> list[str]:
    """Ask for timely wake-ups of the *calling thread* (Linux); returns what took.

    1 us timer slack instead of 50 us (``PR_SET_TIMERSLACK``), and a 0.1 ms scheduler
    slice for a normal (SCHED_OTHER) thread (``sched_setattr``): on Linux >= 6.12
    (EEVDF) a waking task with a shorter slice gets an earlier virtual deadline and
    preempts a busy CPU sooner; older kernels accept and ignore it. Neither needs a
    privilege; both are skipped silently where unsupported (other systems, other
    architectures, a thread already on a real-time policy).
    """
    if not sys.platform.startswith("linux"):
        return []
    done: list[str] = []
    try:
        libc = ctypes.CDLL(None, use_errno=True)
    except OSError:
        return done
    if libc.prctl(_PR_SET_TIMERSLACK, ctypes.c_ulong(1), ctypes.c_ulong(0), ctypes.c_ulong(0),
                  ctypes.c_ulong(0)) == 0:
        done.append("timer slack 1 us")
    calls = _SCHED_ATTR_CALLS.get(platform.machine())
    if calls is not None:
        attr = _SchedAttr()
        size = ctypes.sizeof(attr)
        if (libc.syscall(calls[1], 0, ctypes.byref(attr), size, 0) == 0
                and attr.sched_policy == os.SCHED_OTHER):
            attr.size, attr.sched_flags, attr.sched_runtime = size, 0, _SLICE_NS
            if libc.syscall(calls[0], 0, ctypes.byref(attr), 0) == 0:
                done.append(f"scheduler slice {_SLICE_NS / 1e6:g} ms")
    return done


class CpuWakeLatency:
    """A PM QoS request on CPU wake-up latency, held from :meth:`acquire` to :meth:`release`.

    The kernel honours the smallest bound any open request asks for and drops a request
    when its file is closed, including when the process dies: nothing outlives the stream.

    Parameters
    ----------
    us : int, optional
        Largest acceptable wake-up latency in microseconds; default from the environment
        variable ``MRFT_CPU_LATENCY_US`` (``off``: no request), else 0.
    path : str
        The PM QoS device (tests point it elsewhere).

    Examples
    --------
    >>> q = CpuWakeLatency(path="/nonexistent")
    >>> q.acquire().startswith("CPU wake-up latency not bounded")
    True
    >>> q.held
    False
    """

    def __init__(self, us: int | None = None, path: str = _PM_QOS_DEVICE) -> None:
        if us is None:
            raw = os.environ.get(CPU_LATENCY_ENV, "0").strip().lower()
            try:
                us = None if raw in ("off", "none", "") else int(raw)
            except ValueError:
                raise UsageError(f"{CPU_LATENCY_ENV}={raw!r}: give whole microseconds "
                                 f"(e.g. 0 or 10) or 'off'") from None
        if us is not None and us < 0:
            raise UsageError(f"CPU wake-up latency must be >= 0 us, not {us} "
                             f"({CPU_LATENCY_ENV})")
        self.us = us
        self.path = path
        #: True when the request was refused for want of permission (worth telling the user)
        self.denied = False
        #: what the last :meth:`acquire` did, in words ("" before)
        self.outcome = ""
        self._fd: int | None = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def acquire(self) -> str:
        """Open the request; returns what happened, in words (also kept in :attr:`outcome`)."""
        self.outcome = self._acquire()
        return self.outcome

    def _acquire(self) -> str:
        if self.us is None:
            return f"CPU wake-up latency not bounded ({CPU_LATENCY_ENV}=off)"
        if self._fd is not None:
            return f"CPU wake-up latency <= {self.us} us"
        try:
            fd = os.open(self.path, os.O_WRONLY)
        except PermissionError:
            self.denied = True
            return (f"CPU wake-up latency not bounded (no write access to {self.path}: run as "
                    f"root or grant it, e.g. by a udev rule, for steadier stream timing)")
        except OSError as err:
            return f"CPU wake-up latency not bounded ({self.path}: {err.strerror or err})"
        try:
            os.write(fd, struct.pack("i", self.us))
        except OSError as err:
            os.close(fd)
            return f"CPU wake-up latency not bounded ({self.path}: {err.strerror or err})"
        self._fd = fd
        return f"CPU wake-up latency <= {self.us} us"

    def release(self) -> None:
        if self._fd is not None:
            fd, self._fd = self._fd, None
            os.close(fd)
