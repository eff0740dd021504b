"""Say plainly what a log holds: which signals, how many samples, at what rate.

``dry-run`` uses this when it finds no relay test, so the user sees at once
whether the log lacks a signal (no setpoints, no position) or just a test.

Examples
--------
>>> import numpy as np
>>> from mrft_gcs.telemetry import TelemetryLog
>>> t = np.arange(0.0, 2.0, 0.004)
>>> log = TelemetryLog(attitude=np.column_stack([t] + [0 * t] * 6), source="a.tlog")
>>> print(describe_log(log))
a.tlog: 2.0 s of telemetry (t 0.000 .. 1.996 s)
  attitude         500 samples  250.0 Hz
  position         none
  actuator         none
  attitude target  none
  status texts     0
  parameters       0
  heartbeats       0
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mrft_gcs.telemetry import TelemetryLog

__all__ = ["SignalSummary", "LogSummary", "summarize_log", "describe_log"]


@dataclass(frozen=True)
class SignalSummary:
    """One table of a log: sample count, time span and typical rate."""

    name: str
    count: int
    t_start_s: float = float("nan")
    t_end_s: float = float("nan")
    rate_hz: float = float("nan")  # 1 / median sample interval; NaN with < 2 samples


@dataclass(frozen=True)
class LogSummary:
    """What a :class:`TelemetryLog` holds."""

    source: str
    signals: tuple[SignalSummary, ...]
    status_texts: int
    parameters: int
    heartbeats: int

    @property
    def duration_s(self) -> float:
        """Span from the first to the last sample of any table, s (0 when empty)."""
        spans = [s for s in self.signals if s.count]
        if not spans:
            return 0.0
        return max(s.t_end_s for s in spans) - min(s.t_start_s for s in spans)

    def found(self) -> tuple[str, ...]:
        """Names of the tables that hold samples."""
        return tuple(s.name for s in self.signals if s.count)

    def __str__(self) -> str:
        spans = [s for s in self.signals if s.count]
        if spans:
            t0 = min(s.t_start_s for s in spans)
            t1 = max(s.t_end_s for s in spans)
            head = f"{self.duration_s:.1f} s of telemetry (t {t0:.3f} .. {t1:.3f} s)"
        else:
            head = "no telemetry samples"
        lines = [f"{self.source or 'log'}: {head}"]
        for s in self.signals:
            if not s.count:
                lines.append(f"  {s.name:<16} none")
            else:
                rate = f"{s.rate_hz:.1f} Hz" if np.isfinite(s.rate_hz) else "single sample"
                lines.append(f"  {s.name:<16} {s.count:>3} samples  {rate}")
        lines += [f"  {'status texts':<16} {self.status_texts}",
                  f"  {'parameters':<16} {self.parameters}",
                  f"  {'heartbeats':<16} {self.heartbeats}"]
        return "\n".join(lines)


def _signal(name: str, table: np.ndarray) -> SignalSummary:
    n = len(table)
    if n == 0:
        return SignalSummary(name, 0)
    t = table[:, 0]
    rate = float("nan")
    if n >= 2:
        dt = float(np.median(np.diff(t)))
        rate = 1.0 / dt if dt > 0 else float("inf")
    return SignalSummary(name, n, float(t[0]), float(t[-1]), rate)


def summarize_log(log: TelemetryLog) -> LogSummary:
    """Count and time each table of ``log``.

    Parameters
    ----------
    log : TelemetryLog

    Returns
    -------
    LogSummary
        Per table (attitude, position, actuator, attitude target, then each explicit
        loop as ``loop <name>``): samples, first and last time, rate in Hz.
    """
    signals = [
        _signal("attitude", log.attitude),
        _signal("position", log.position),
        _signal("actuator", log.actuator),
        _signal("attitude target", log.attitude_target),
        *(_signal(f"loop {k}", v) for k, v in sorted(log.loops.items())),
    ]
    return LogSummary(log.source, tuple(signals), len(log.status), len(log.params),
                      len(log.heartbeats))


def describe_log(log: TelemetryLog) -> str:
    """A few lines saying which signals ``log`` holds (see :func:`summarize_log`)."""
    return str(summarize_log(log))
