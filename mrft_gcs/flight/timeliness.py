"""Whether the ground station keeps its loop on time: telemetry gaps and late set points.

A relay test closes its loop through the ground station. Where telemetry stops coming (the
link drops out; the vehicle's process, or this computer's link reader, is starved of CPU) or
set points stop going out (this computer's stream is starved), the vehicle flies on its last
set point: a relay's torque held for a relay half-cycle or more tilts a small vehicle tens of
degrees within a tenth of a second, and the samples that show it arrive only after the fact
(docs/link-and-stream.md, "A busy host"). No limit on the samples can catch that in time; what
can be seen in time is that the loop has started to stall.

:class:`TimelinessMonitor` is fed the receive time of every telemetry sample
(:meth:`~TimelinessMonitor.sample`) and the send time of every set point
(:meth:`~TimelinessMonitor.tick`), both on the ground station's monotonic clock. Each gap of
``minor_s`` or more between consecutive samples, or between consecutive set points, is a
*stall*; :meth:`~TimelinessMonitor.trouble` gives a one-line reason once a stall reached
``major_s`` (also one still going on) or ``minor_count`` stalls fell within ``window_s``.
:class:`~mrft_gcs.flight.driver.SequenceDriver` then stops the tests with
:class:`HostTooSlow` (the vehicle lands), and the live tune checks the same before arming.

Examples
--------
>>> m = TimelinessMonitor()
>>> for k in range(100):
...     m.sample(0.004 * k)
>>> m.trouble(0.4) is None
True
>>> m.sample(0.52)  # a 124 ms gap in telemetry
>>> m.trouble(0.52)
'telemetry stopped for 124 ms (the rule: none of 100 ms or more)'
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass

from mrft_gcs.errors import LinkError

__all__ = ["HostTooSlow", "Stall", "TimelinessMonitor", "TimelinessRules", "host_advice",
           "SETTLE_S"]

#: how long after a telemetry gap the samples that follow are read (s) to tell a vehicle that
#: flew on through the gap from one whose clock stood still
SETTLE_S = 0.02


class HostTooSlow(LinkError):
    """The ground station could not keep its loop on time (telemetry or set points stalled)."""


@dataclass(frozen=True)
class TimelinessRules:
    """When stalls stop a relay test (seconds on the ground station's clock).

    On a quiet two-core machine, live tunes against the bundled SITL see telemetry gaps of
    20-57 ms at most (one over 50 ms a tune at most) and set-point gaps under 10 ms; a vehicle
    starved beside busy processes showed gaps of 50-460 ms, and a relay ran away in the
    third of three stalls (65, 79, 214 ms) within 0.3 s.
    """

    #: a gap this long (s) is a stall
    minor_s: float = 0.05
    #: one stall this long (s) stops the tests at once
    major_s: float = 0.10
    #: this many stalls within ``window_s`` stop the relay tests
    minor_count: int = 2
    window_s: float = 3.0
    #: and this many the hover on the ground station's PDs (which keep their phase margin
    #: through a short stall, where a relay's held torque does not)
    hover_minor_count: int = 3


@dataclass(frozen=True)
class Stall:
    """A gap in telemetry or in set points: when it ended (s) and how long it was (s)."""

    t_s: float
    length_s: float
    kind: str  # "telemetry" or "set points"


def host_advice() -> str:
    """What to do about a stalled loop (the end of :class:`HostTooSlow`'s message)."""
    return ("close other busy programs (or run them with nice), check the link, and fly "
            "again")


class TimelinessMonitor:
    """Stalls of the ground station's loop (module docstring). Thread-safe: samples come
    from the link's reader thread, set points and the checks from the stream's."""

    def __init__(self, rules: TimelinessRules | None = None) -> None:
        self.rules = rules or TimelinessRules()
        self._lock = threading.Lock()
        self.reset()

    def reset(self) -> None:
        """Forget everything (a new session)."""
        with self._lock:
            self._last: dict[str, float] = {}
            self._vt: float | None = None  # the newest sample's vehicle time
            #: a telemetry gap being read: [rx at its end, its length, vehicle time before
            #: it, newest vehicle time since]
            self._pending: list[float] | None = None
            self._recent: deque[Stall] = deque()
            self.stalls: list[Stall] = []  # every stall since the last forget()

    def forget(self) -> None:
        """Forget the stalls so far, keep the last times (the stalls counted start now)."""
        with self._lock:
            self._recent.clear()
            self.stalls = []

    def sample(self, rx_s: float, vt_s: float | None = None) -> None:
        """A telemetry sample was received at ``rx_s``; ``vt_s``: its vehicle time.

        With vehicle times a gap counts for as long as the vehicle flew through it: the
        vehicle time the samples of the next :data:`SETTLE_S` reach past the last one before
        the gap (a vehicle flying on a held set point comes back with that much flight at
        once; one whose clock stood still, a simulator stopped whole, with none).
        """
        with self._lock:
            self._settle(rx_s)
            last = self._last.get("telemetry")
            self._last["telemetry"] = rx_s if last is None else max(last, rx_s)
            prev_vt = self._vt
            if vt_s is not None:
                self._vt = vt_s if prev_vt is None else max(prev_vt, vt_s)
                if self._pending is not None:
                    self._pending[3] = max(self._pending[3], vt_s)
            if last is None or rx_s - last < self.rules.minor_s:
                return
            if vt_s is None or prev_vt is None:
                self._add(Stall(rx_s, rx_s - last, "telemetry"), last)
            else:
                self._pending = [rx_s, rx_s - last, prev_vt, vt_s]

    def _settle(self, now_s: float) -> None:
        """Count the gap being read once :data:`SETTLE_S` passed after it (lock held)."""
        p = self._pending
        if p is None or now_s <= p[0] + SETTLE_S:
            return
        self._pending = None
        flown = min(p[1], p[3] - p[2])
        if flown >= self.rules.minor_s:
            self._add(Stall(p[0], flown, "telemetry"), p[0] - p[1])

    def tick(self, now_s: float) -> None:
        """A set point was sent (or is about to be) at ``now_s``."""
        with self._lock:
            last = self._last.get("set points")
            self._last["set points"] = now_s if last is None else max(last, now_s)
            if last is not None and now_s - last >= self.rules.minor_s:
                self._add(Stall(now_s, now_s - last, "set points"), last)

    def _add(self, st: Stall, start_s: float) -> None:
        """Count ``st``, which began at ``start_s`` (lock held)."""
        prev = self.stalls[-1] if self.stalls else None
        if prev is not None and prev.t_s > start_s:
            # the same stall seen on the other side too (a starved process holds both its
            # reader and its stream): one stall, as long as the longer of the two
            if st.length_s <= prev.length_s:
                return
            self.stalls.pop()
            if self._recent and self._recent[-1] is prev:
                self._recent.pop()
        self._recent.append(st)
        self.stalls.append(st)

    def longest_s(self) -> float:
        """The longest stall since the last :meth:`forget` (s; 0 with none)."""
        with self._lock:
            return max((st.length_s for st in self.stalls), default=0.0)

    def trouble(self, now_s: float | None = None, relays: bool = True) -> str | None:
        """A one-line reason where the loop stalled by the rules, else None.

        ``now_s``: the current time, to see a telemetry gap still going on (None: only the
        stalls that ended). ``relays``: relay tests run (else the hover's count applies).
        """
        r = self.rules
        count = r.minor_count if relays else r.hover_minor_count
        with self._lock:
            if now_s is not None:
                self._settle(now_s)
            last_rx = self._last.get("telemetry")
            if now_s is not None and last_rx is not None and now_s - last_rx >= r.major_s:
                return (f"telemetry stopped {1e3 * (now_s - last_rx):.0f} ms ago (the rule: "
                        f"no gap of {1e3 * r.major_s:.0f} ms or more)")
            recent = self._recent
            end = max([st.t_s for st in recent] + ([now_s] if now_s is not None else []),
                      default=0.0)
            while recent and recent[0].t_s < end - r.window_s:
                recent.popleft()
            for st in recent:
                if st.length_s >= r.major_s:
                    return (f"{st.kind} stopped for {1e3 * st.length_s:.0f} ms (the rule: none "
                            f"of {1e3 * r.major_s:.0f} ms or more)")
            if len(recent) >= count:
                each = ", ".join(f"{st.kind} {1e3 * st.length_s:.0f} ms" for st in recent)
                return (f"{len(recent)} stalls of {1e3 * r.minor_s:.0f} ms or more within "
                        f"{r.window_s:g} s ({each})")
        return None

    def summary(self) -> str | None:
        """One line on the stalls since the last :meth:`forget` (None: there were none)."""
        with self._lock:
            if not self.stalls:
                return None
            n = len(self.stalls)
            longest = max(self.stalls, key=lambda st: st.length_s)
        return (f"ground-station loop: {n} stall{'s' if n > 1 else ''} of "
                f"{1e3 * self.rules.minor_s:.0f} ms or more in flight (longest: "
                f"{longest.kind}, {1e3 * longest.length_s:.0f} ms)")
