"""A setpoint stream at a steady rate, with the telemetry watchdog (README, safety).

:class:`SetpointStreamer` asks a callback for the next setpoint every ``1/rate_hz``
seconds, on absolute deadlines of the monotonic clock, and sends it. Deadlines do not
drift with late ticks: a late tick is followed by an early one; a tick more than one
period late is skipped and counted rather than sent in a burst. Each achieved period is
recorded for the jitter figures.

Every tick also checks the link's telemetry age: past ``watchdog_s`` (0.5 s by
README, safety) the stream stops, a landing is commanded and :attr:`abort_reason` says
why; :meth:`raise_if_aborted` turns it into :class:`~mrft_gcs.errors.SafetyAbort`.

Timing: where the process may use two CPUs (Linux), two worker threads, each pinned to
a CPU of its own (:func:`stream_cpus`), race for every tick: each sleeps right to the
deadline (``clock_nanosleep`` on the monotonic clock), the first awake takes the tick
under a lock and sends it, the other finds it taken. On a virtual machine a late wake-up
is mostly the hypervisor holding one virtual CPU, and the two are held at different
moments (README, "Link": p99 lateness 2.2 ms on either CPU, 0.37 ms for the earlier of
the two). One worker (``workers=1``, or one CPU) is unpinned; it sleeps to a margin before
each deadline and spins the rest, yielding the CPU and the GIL on each turn
(``os.sched_yield``), the margin following how late this machine's sleeps wake
(:func:`spin_margin_s`: the 99th percentile of the last second's overshoots plus 0.2 ms,
between 0.4 ms and 90 % of a period). While any stream runs, the interpreter's GIL switch
interval is 0.5 ms instead of 5 ms (restored when the last stream stops). The workers ask
the OS to wake them on time (:func:`~mrft_gcs.link.latency.latency_hints`: unprivileged,
no priority change). While the stream runs it holds a PM QoS request that keeps the CPUs
out of slow idle states (:class:`~mrft_gcs.link.latency.CpuWakeLatency`, where the
process may write ``/dev/cpu_dma_latency``): on the development VM a halted virtual CPU
was woken up to 8-19 ms late; with the request most live tunes sent every tick.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from mrft_gcs.errors import SafetyAbort
from mrft_gcs.link.latency import CpuWakeLatency, latency_hints
from mrft_gcs.telemetry import ActuatorTarget, AttitudeTarget, RateTarget

__all__ = ["SetpointStreamer", "StreamStats", "SetpointSink", "Setpoint", "period_stats",
           "latency_hints", "spin_margin_s", "stream_cpus"]

Setpoint = ActuatorTarget | AttitudeTarget | RateTarget
#: The callback: monotonic seconds since the stream started -> setpoint, or None to skip a tick.
SetpointFn = Callable[[float], Setpoint | None]

#: two workers sleep right to the deadline: the other covers a late wake-up, and spinning
#: holds the GIL and costs a third to half a core (docs/link-and-stream.md)
_TWIN_MARGIN_S = 0.0
_SPIN_MIN_S = 0.0004  # never sleep closer to a deadline than this (sleep() overshoots ~0.1 ms)
_SPIN_PAD_S = 0.0002  # added to the measured overshoot percentile
_SPIN_MAX_FRACTION = 0.9  # of a period: always sleep a little, so the stream never takes a core
_OVERSHOOT_WINDOW = 250  # sleeps remembered for the margin (one second at 250 Hz)
_MARGIN_EVERY = 25  # ticks between margin updates
_yield_cpu = getattr(os, "sched_yield", lambda: time.sleep(0))  # not every system has it
_SWITCH_INTERVAL_S = 0.0005
_switch_lock = threading.Lock()
_switch_users = 0
_switch_saved = 0.0


def _shorten_switch_interval() -> None:
    """A thread waiting for the GIL waits up to the switch interval (5 ms by default)
    while another thread runs Python code: far too long for a 4 ms period."""
    global _switch_users, _switch_saved
    with _switch_lock:
        if _switch_users == 0:
            _switch_saved = sys.getswitchinterval()
            if _switch_saved > _SWITCH_INTERVAL_S:
                sys.setswitchinterval(_SWITCH_INTERVAL_S)
        _switch_users += 1


def _restore_switch_interval() -> None:
    global _switch_users
    with _switch_lock:
        _switch_users = max(0, _switch_users - 1)
        if _switch_users == 0 and _switch_saved > 0:
            sys.setswitchinterval(_switch_saved)


class SetpointSink(Protocol):
    """What the streamer needs from a link (:class:`~mrft_gcs.link.VehicleLink` is one)."""

    def send_setpoint(self, target: Setpoint) -> None: ...

    def telemetry_age_s(self) -> float: ...

    def land(self, *, wait_ack: bool = True, timeout_s: float = 1.0) -> None: ...


@dataclass(frozen=True)
class StreamStats:
    """Achieved stream figures. Periods in milliseconds; jitter is |period - nominal|."""

    rate_hz_target: float
    rate_hz_achieved: float
    sent: int
    skipped: int
    period_p50_ms: float
    period_p99_ms: float
    period_max_ms: float
    jitter_p50_ms: float
    jitter_p99_ms: float

    def line(self) -> str:
        return (f"{self.rate_hz_achieved:.1f} Hz achieved of {self.rate_hz_target:g} Hz; period "
                f"p50 {self.period_p50_ms:.3f} ms, p99 {self.period_p99_ms:.3f} ms, max "
                f"{self.period_max_ms:.3f} ms; jitter p50 {self.jitter_p50_ms:.3f} ms, p99 "
                f"{self.jitter_p99_ms:.3f} ms; {self.skipped} ticks skipped")


def spin_margin_s(overshoots_s: np.ndarray, period_s: float) -> float:
    """How long before a deadline to stop sleeping, from recent sleep overshoots (s).

    The 99th percentile of ``overshoots_s`` (how late past their request the last
    sleeps woke) plus 0.2 ms, clipped to [0.4 ms, 0.9 period]. Empty: 0.4 ms.
    """
    o = np.asarray(overshoots_s, dtype=float)
    o = o[np.isfinite(o)]
    if not len(o):
        return _SPIN_MIN_S
    m = float(np.percentile(o, 99)) + _SPIN_PAD_S
    return min(max(m, _SPIN_MIN_S), _SPIN_MAX_FRACTION * period_s)


def period_stats(send_times_s: np.ndarray, rate_hz: float, skipped: int = 0) -> StreamStats:
    """Figures from the monotonic send times (s, shape (N,))."""
    t = np.asarray(send_times_s, dtype=float)
    if len(t) < 2:
        nan = float("nan")
        return StreamStats(rate_hz, 0.0, len(t), skipped, nan, nan, nan, nan, nan)
    periods = np.diff(t) * 1e3
    jitter = np.abs(periods - 1e3 / rate_hz)
    return StreamStats(
        rate_hz_target=rate_hz,
        rate_hz_achieved=float((len(t) - 1) / (t[-1] - t[0])),
        sent=len(t),
        skipped=skipped,
        period_p50_ms=float(np.percentile(periods, 50)),
        period_p99_ms=float(np.percentile(periods, 99)),
        period_max_ms=float(periods.max()),
        jitter_p50_ms=float(np.percentile(jitter, 50)),
        jitter_p99_ms=float(np.percentile(jitter, 99)),
    )


def stream_cpus(workers: int | None = None) -> list[int | None]:
    """The CPU each stream worker is pinned to (``None``: not pinned).

    Two workers on two different CPUs where this process may run on two or more and the
    OS pins threads (Linux): the last two it may use (the first CPUs of a machine tend to
    take more of its interrupts), else one unpinned. ``workers`` (or the environment
    variable ``MRFT_STREAM_WORKERS``) forces 1 or 2.
    """
    if workers is None:
        workers = int(os.environ.get("MRFT_STREAM_WORKERS", "2"))
    if workers not in (1, 2):
        raise ValueError(f"stream workers must be 1 or 2, not {workers}")
    try:
        allowed = sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        allowed = []
    if workers == 1 or len(allowed) < 2 or not hasattr(os, "sched_setaffinity"):
        return [None]
    return list[int | None](allowed[-2:])


class SetpointStreamer:
    """Stream setpoints from ``make_setpoint`` to ``link`` at ``rate_hz`` from worker threads.

    Parameters
    ----------
    link : SetpointSink
        Usually a :class:`~mrft_gcs.link.VehicleLink`.
    make_setpoint : callable
        ``f(t_s) -> ActuatorTarget | AttitudeTarget | None``; ``t_s`` is seconds since
        :meth:`start`. Runs on a stream worker, one tick at a time (never two at once, but
        not always on the same thread): keep it short (well under a period).
    rate_hz : float
        Default 250 Hz.
    watchdog_s : float or None
        Stop and land when no telemetry arrived for this long (0.5 s, README, safety). None
        disables the watchdog (bench tests without a vehicle only).
    land_on_abort : bool
        Command a landing when the watchdog fires or the callback raises.
    workers : int, optional
        1 or 2 worker threads (default :func:`stream_cpus`: 2 where there are two CPUs).

    Examples
    --------
    >>> stream = SetpointStreamer(link, lambda t: ActuatorTarget(t, 0, 0, 0, 0.5))  # doctest: +SKIP
    >>> with stream as s:  # doctest: +SKIP
    ...     time.sleep(2.0)
    ...     s.raise_if_aborted()
    """

    def __init__(self, link: SetpointSink, make_setpoint: SetpointFn, rate_hz: float = 250.0,
                 watchdog_s: float | None = 0.5, land_on_abort: bool = True,
                 max_records: int = 1_000_000, workers: int | None = None) -> None:
        if rate_hz <= 0:
            raise ValueError("rate_hz must be positive")
        self.link = link
        self.make_setpoint = make_setpoint
        self.rate_hz = float(rate_hz)
        self.watchdog_s = watchdog_s
        self.land_on_abort = land_on_abort
        self._times = np.empty(max_records)
        self._n = 0
        self._skipped = 0
        self._stop = threading.Event()
        self._cpus = stream_cpus(workers)
        self._threads: list[threading.Thread] = []
        self._tick_lock = threading.Lock()
        self._claimed = -1  # the last tick sent or skipped
        self._t0 = 0.0
        self._cpu = [0.0] * len(self._cpus)
        #: the PM QoS request held while the stream runs (:class:`CpuWakeLatency`)
        self.cpu_latency = CpuWakeLatency() if sys.platform.startswith("linux") else None
        self.abort_reason: str | None = None
        self.landing_commanded = False
        #: the OS latency hints the stream threads got (:func:`latency_hints`, and the CPU
        #: each worker is pinned to)
        self.hints: list[str] = []
        #: the current spin margin (s, :func:`spin_margin_s`; one worker only) and the stream
        #: threads' CPU seconds so far (what the precise pacing costs)
        self.spin_margin_s = _SPIN_MIN_S
        self.cpu_s = 0.0
        self.wall_s = 0.0

    def reset(self) -> None:
        """Forget recorded periods (the stream must be stopped)."""
        if self.running:
            raise RuntimeError("stop the stream before reset()")
        self._n = 0
        self._skipped = 0
        self.abort_reason = None
        self.landing_commanded = False
        self._stop.clear()

    @property
    def running(self) -> bool:
        return any(t.is_alive() for t in self._threads)

    @property
    def workers(self) -> int:
        """Threads that race for each tick (1, or 2 pinned to different CPUs)."""
        return len(self._cpus)

    def start(self) -> SetpointStreamer:
        if self.running:
            return self
        self._stop.clear()
        self.hints = [self.cpu_latency.acquire()] if self.cpu_latency is not None else []
        self._claimed, self._t0 = -1, time.monotonic()
        self._threads = [threading.Thread(target=self._run, args=(i, cpu), daemon=True,
                                          name=f"setpoint-streamer-{i}")
                         for i, cpu in enumerate(self._cpus)]
        for t in self._threads:
            t.start()
        return self

    def stop(self) -> None:
        """Stop streaming (no landing: the caller decides what comes next)."""
        self._stop.set()
        for t in self._threads:
            if t is not threading.current_thread():
                t.join(timeout=2.0)
        if self.cpu_latency is not None:
            self.cpu_latency.release()

    def __enter__(self) -> SetpointStreamer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def wait(self, timeout_s: float) -> bool:
        """Block until the stream stops (True) or ``timeout_s`` passes (False)."""
        return self._stop.wait(timeout_s)

    def raise_if_aborted(self) -> None:
        """Raise :class:`SafetyAbort` if the watchdog or the callback stopped the stream."""
        if self.abort_reason is not None:
            raise SafetyAbort(self.abort_reason)

    def stats(self) -> StreamStats:
        return period_stats(self._times[: self._n], self.rate_hz, self._skipped)

    def _abort(self, reason: str) -> None:
        if self.land_on_abort:
            try:
                self.link.land(wait_ack=False)
                self.landing_commanded = True
                reason = f"{reason}; landing commanded"
            except Exception as err:  # the link may be gone: say so, do not mask the reason
                reason = f"{reason}; landing command could not be sent ({err})"
        self.abort_reason = reason
        self._stop.set()

    def _run(self, worker: int = 0, cpu: int | None = None) -> None:
        _shorten_switch_interval()
        try:
            hints = latency_hints()
            if cpu is not None:
                try:
                    os.sched_setaffinity(0, {cpu})  # this thread only (Linux)
                    hints.append(f"CPU {cpu}")
                except OSError:
                    pass
            with self._tick_lock:
                self.hints.extend(hints)
            self._loop(worker)
        finally:
            _restore_switch_interval()

    def _loop(self, worker: int) -> None:
        period = 1.0 / self.rate_hz
        t0 = self._t0
        cpu0 = time.thread_time()
        overshoots = np.full(_OVERSHOOT_WINDOW, np.nan)
        n_sleeps = 0
        k = 0
        twin = len(self._threads) > 1
        margin = _TWIN_MARGIN_S if twin else _SPIN_MIN_S
        while not self._stop.is_set():
            if k % _MARGIN_EVERY == 0:
                if not twin:  # one thread covers late wake-ups by spinning longer
                    margin = self.spin_margin_s = spin_margin_s(overshoots, period)
                self._cpu[worker] = time.thread_time() - cpu0
                self.cpu_s, self.wall_s = sum(self._cpu), time.monotonic() - t0
            k = max(k, self._claimed + 1)
            deadline = t0 + k * period
            now = time.monotonic()
            left = deadline - now
            if left > margin:
                asked = left - margin
                time.sleep(asked)
                if not twin:  # what the single worker's margin follows
                    overshoots[n_sleeps % _OVERSHOOT_WINDOW] = time.monotonic() - now - asked
                    n_sleeps += 1
            while time.monotonic() < deadline:
                _yield_cpu()  # releases the GIL and the CPU to whoever else is ready
            with self._tick_lock:
                if self._claimed >= k or self._stop.is_set():
                    continue  # the other worker sent this tick
                now = time.monotonic()
                if now - deadline > period:  # more than a whole period late: skip, no burst
                    missed = int((now - deadline) / period)
                    self._skipped += missed
                    self._claimed = k + missed - 1
                    continue
                self._claimed = k
                if not self._tick(now):
                    return

    def _tick(self, now: float) -> bool:
        """Send one setpoint (the tick lock held); False when the stream must stop."""
        if self.watchdog_s is not None and self.link.telemetry_age_s() > self.watchdog_s:
            self._abort(f"no telemetry for {self.link.telemetry_age_s():.2f} s "
                        f"(limit {self.watchdog_s:g} s): setpoint stream stopped")
            return False
        try:
            target = self.make_setpoint(now - self._t0)
            if target is not None:
                self.link.send_setpoint(target)
        except Exception as err:
            self._abort(f"setpoint stream failed: {err}")
            return False
        if self._n < len(self._times):
            self._times[self._n] = now
            self._n += 1
        return True
