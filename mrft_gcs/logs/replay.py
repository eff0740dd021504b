"""What every log reader produces, and the replay that turns it into a stream.

Each reader decodes its wire records into a :class:`DecodedLog` once: float
tables with the column layout of :class:`~mrft_gcs.telemetry.TelemetryLog`
(time in column 0, SI units, NED) plus discrete samples (status texts,
heartbeats, parameters) as typed values. From there :func:`to_telemetry_log`
builds the arrays ``dry-run`` works on, and :class:`LogReplay` yields the same
content as typed samples through the :class:`~mrft_gcs.telemetry.TelemetrySource`
protocol, in time order. ``collect_log(LogReplay(d))`` equals
``to_telemetry_log(d)``: both drop non-finite rows and sort stably by time.

Tables are decoded with numpy rather than one Python object per record, which
is what keeps a 10-minute 250 Hz log well under a second or two.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from mrft_gcs.telemetry import (
    ActuatorTarget,
    Attitude,
    AttitudeTarget,
    EndOfStream,
    Heartbeat,
    LocalPosition,
    ParamValue,
    Sample,
    StatusText,
    TelemetryLog,
    TelemetrySource,
    collect,
    is_finite_sample,
)

if TYPE_CHECKING:
    from mrft_gcs.link.clock import ClockFit

__all__ = [
    "LoopSample",
    "DecodedLog",
    "LogReplay",
    "to_telemetry_log",
    "collect_log",
    "TABLE_COLUMNS",
]

#: Column count of each float table (time first), as in :class:`TelemetryLog`.
TABLE_COLUMNS: dict[str, int] = {"attitude": 7, "position": 7, "actuator": 5, "attitude_target": 6}


@dataclass(frozen=True, slots=True)
class LoopSample:
    """One row of an explicit per-loop table (the documented CSV format).

    ``loop`` is a :class:`~mrft_gcs.loops.Loop` value (``"roll"`` ...), ``u`` the
    loop input (relay output) in the loop's units, ``y`` the measured variable.
    """

    t_s: float
    loop: str
    u: float
    y: float


def _empty(n: int) -> np.ndarray:
    return np.empty((0, n))


@dataclass(frozen=True)
class DecodedLog:
    """A log decoded at the reader's boundary, before cleaning and sorting.

    Tables are float64 arrays of shape ``(N, k)`` with the columns of
    :class:`~mrft_gcs.telemetry.TelemetryLog`; ``events`` holds the discrete
    samples (:class:`StatusText`, :class:`Heartbeat`, :class:`ParamValue`) in
    file order; ``loops`` maps a loop name to a ``(N, 3)`` table t, u, y.

    ``file_order`` maps a table name to the position in the file where each of its
    rows was logged (int64, one per row), for formats that log the traffic of both
    directions in the order the ground station saw it (.tlog): it tells which
    telemetry sample a ground-station command answered, which the clock cannot
    (commands carry no vehicle time). Tables without it are absent.

    ``clock``: for formats that stamp what the ground station received (.tlog), the fit
    of its receive clock against the vehicle's (:mod:`mrft_gcs.link.clock`) that placed
    the commands on the vehicle clock; None otherwise.
    """

    attitude: np.ndarray = field(default_factory=lambda: _empty(7))
    position: np.ndarray = field(default_factory=lambda: _empty(7))
    actuator: np.ndarray = field(default_factory=lambda: _empty(5))
    attitude_target: np.ndarray = field(default_factory=lambda: _empty(6))
    events: tuple[Sample, ...] = ()
    loops: dict[str, np.ndarray] = field(default_factory=dict)
    source: str = ""
    file_order: dict[str, np.ndarray] = field(default_factory=dict)
    clock: ClockFit | None = None

    def cleaned(self) -> DecodedLog:
        """Drop rows and events with non-finite values; sort each by time (stable).

        ``file_order`` follows its table's rows.
        """

        def keep(a: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
            a = np.asarray(a, dtype=float).reshape(-1, n)
            idx = np.flatnonzero(np.isfinite(a).all(axis=1))
            return a, idx[np.argsort(a[idx, 0], kind="stable")]

        events = [e for e in self.events if is_finite_sample(e)]
        events.sort(key=lambda e: e.t_s)
        changes: dict[str, Any] = {}
        order: dict[str, np.ndarray] = {}
        for name, n in TABLE_COLUMNS.items():
            a, idx = keep(getattr(self, name), n)
            changes[name] = a[idx]
            pos = self.file_order.get(name)
            if pos is not None and len(pos) == len(a):
                order[name] = np.asarray(pos, dtype=np.int64)[idx]
        changes["events"] = tuple(events)
        loops = {}
        for k, v in self.loops.items():
            a, idx = keep(v, 3)
            loops[k] = a[idx]
        changes["loops"] = loops
        changes["file_order"] = order
        return replace(self, **changes)


def to_telemetry_log(decoded: DecodedLog) -> TelemetryLog:
    """Build the :class:`TelemetryLog` of a decoded log (non-finite rows dropped)."""
    d = decoded.cleaned()
    params: dict[str, float] = {}
    for e in d.events:
        if isinstance(e, ParamValue):
            params[e.name] = e.value
    return TelemetryLog(
        attitude=d.attitude,
        position=d.position,
        actuator=d.actuator,
        attitude_target=d.attitude_target,
        status=tuple(e for e in d.events if isinstance(e, StatusText)),
        params=params,
        heartbeats=tuple(e for e in d.events if isinstance(e, Heartbeat)),
        loops={k: v for k, v in d.loops.items() if len(v)},
        source=d.source,
    )


def _row_sample(kind: str, row: list[float]) -> Sample | LoopSample:
    if kind == "attitude":
        return Attitude(*row)
    if kind == "position":
        return LocalPosition(*row)
    if kind == "actuator":
        return ActuatorTarget(*row)
    if kind == "attitude_target":
        return AttitudeTarget(row[0], (row[1], row[2], row[3], row[4]), row[5])
    return LoopSample(row[0], kind, row[1], row[2])


class LogReplay:
    """A :class:`~mrft_gcs.telemetry.TelemetrySource` over a decoded log.

    Yields every finite row and event as a typed sample in time order (ties keep
    the order tables, loops, events). Rows of explicit loop tables come out as
    :class:`LoopSample`. Raises :class:`~mrft_gcs.telemetry.EndOfStream` at the end.

    Parameters
    ----------
    decoded : DecodedLog
        What a reader produced.
    """

    def __init__(self, decoded: DecodedLog) -> None:
        d = decoded.cleaned()
        self.source = d.source
        self._tables: list[tuple[str, np.ndarray]] = [
            *((name, getattr(d, name)) for name in TABLE_COLUMNS),
            *d.loops.items(),
        ]
        self._events = d.events
        times = [t[:, 0] for _, t in self._tables]
        times.append(np.array([e.t_s for e in self._events], dtype=float))
        which = [np.full(len(t), i, dtype=np.int32) for i, t in enumerate(times)]
        rows = [np.arange(len(t), dtype=np.int64) for t in times]
        all_t = np.concatenate(times) if times else np.empty(0)
        order = np.argsort(all_t, kind="stable")
        self._which = np.concatenate(which)[order]
        self._rows = np.concatenate(rows)[order]
        self._next = 0
        self._closed = False

    def __len__(self) -> int:
        return len(self._which)

    def next_sample(self, timeout_s: float = 1.0) -> Sample | LoopSample:
        """Return the next sample; raise :class:`EndOfStream` after the last one.

        ``timeout_s`` is accepted for the protocol and ignored: a log never waits.
        """
        if self._closed or self._next >= len(self._which):
            raise EndOfStream(self.source)
        i = self._next
        self._next += 1
        w = int(self._which[i])
        r = int(self._rows[i])
        if w == len(self._tables):
            return self._events[r]
        kind, table = self._tables[w]
        return _row_sample(kind, table[r].tolist())

    def reset(self) -> None:
        """Rewind to the first sample."""
        self._next = 0
        self._closed = False

    def close(self) -> None:
        """Release the replay (further calls raise :class:`EndOfStream`)."""
        self._closed = True

    def __iter__(self):
        while True:
            try:
                yield self.next_sample()
            except EndOfStream:
                return

    def __enter__(self) -> LogReplay:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def collect_log(source: TelemetrySource | Iterable[Sample | LoopSample],
                name: str = "") -> TelemetryLog:
    """Drain a source (or iterable) into a :class:`TelemetryLog`, loop rows included.

    Like :func:`mrft_gcs.telemetry.collect`, which ignores :class:`LoopSample`;
    this also gathers loop rows into ``TelemetryLog.loops``.
    """
    if isinstance(source, TelemetrySource) and not isinstance(source, Iterable):
        items: Iterable[Sample | LoopSample] = _drain(source)
    else:
        items = source  # type: ignore[assignment]
    loops: dict[str, list[tuple[float, float, float]]] = {}
    rest: list[Sample] = []
    for s in items:
        if isinstance(s, LoopSample):
            if all(math.isfinite(v) for v in (s.t_s, s.u, s.y)):
                loops.setdefault(s.loop, []).append((s.t_s, s.u, s.y))
        else:
            rest.append(s)
    log = collect(rest, source=name or getattr(source, "source", ""))
    tables = {}
    for k, rows in loops.items():
        a = np.asarray(rows, dtype=float)
        tables[k] = a[np.argsort(a[:, 0], kind="stable")]
    return replace(log, loops=tables)


def _drain(source: TelemetrySource) -> Iterable[Sample | LoopSample]:
    while True:
        try:
            s = source.next_sample(0.0)
        except EndOfStream:
            return
        if s is not None:
            yield s
