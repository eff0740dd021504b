"""Ask the OS to wake a thread on time: for the 250 Hz setpoint stream and its telemetry.

A relay test closes its loop through the ground station, so every wake-up latency (the
SITL's send, the GCS reader's receive, the stream's tick) adds delay to the loop. On a
busy machine a waking thread waits for a CPU; :func:`latency_hints` asks, unprivileged,
for less of that wait. It changes neither the thread's priority nor its share of CPU.
"""

from __future__ import annotations

import ctypes
import os
import platform
import sys

__all__ = ["latency_hints"]

_SLICE_NS = 100_000  # EEVDF custom slice (the kernel's minimum, 0.1 ms)
_PR_SET_TIMERSLACK = 29


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
