"""Log readers behind one interface: .tlog, PX4 .ulg, ArduPilot .bin and CSV.

:func:`open_log` returns a :class:`~mrft_gcs.telemetry.TelemetrySource` that
replays a log as typed samples (the interface the live link and the SITL
answer), :func:`read_log` the whole log as a
:class:`~mrft_gcs.telemetry.TelemetryLog`; both decode the file once, at the
reader's boundary, into SI units and NED. The format is detected from the
file's first bytes, then from its extension. Every problem with the file ends in
:class:`~mrft_gcs.errors.InputFileError` with a one-line message naming the file.

Examples
--------
>>> from mrft_gcs.logs import read_log, describe_log      # doctest: +SKIP
>>> log = read_log("session.tlog")                        # doctest: +SKIP
>>> print(describe_log(log))                              # doctest: +SKIP
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from pathlib import Path

from mrft_gcs.logs._common import input_error, read_bytes, read_head
from mrft_gcs.logs.csv import decode_csv, read_csv_metadata, sniff_csv
from mrft_gcs.logs.dataflash import decode_dataflash, sniff_dataflash
from mrft_gcs.logs.describe import LogSummary, SignalSummary, describe_log, summarize_log
from mrft_gcs.logs.integrity import csv_tail, dataflash_tail, tlog_tail, ulog_tail
from mrft_gcs.logs.replay import DecodedLog, LogReplay, LoopSample, collect_log, to_telemetry_log
from mrft_gcs.logs.tlog import decode_tlog, sniff_tlog
from mrft_gcs.logs.tlog_writer import TlogWriter
from mrft_gcs.logs.ulog import decode_ulog, sniff_ulog
from mrft_gcs.telemetry import TelemetryLog

__all__ = [
    "LogFormat",
    "detect_format",
    "decode_log",
    "log_truncation",
    "open_log",
    "read_log",
    "describe_log",
    "summarize_log",
    "LogSummary",
    "SignalSummary",
    "LogReplay",
    "LoopSample",
    "DecodedLog",
    "collect_log",
    "read_csv_metadata",
    "TlogWriter",
]


class LogFormat(enum.Enum):
    """A log format the readers understand; the value is its usual extension."""

    TLOG = ".tlog"
    ULOG = ".ulg"
    DATAFLASH = ".bin"
    CSV = ".csv"


_EXTENSIONS = {".tlog": LogFormat.TLOG, ".ulg": LogFormat.ULOG, ".ulog": LogFormat.ULOG,
               ".bin": LogFormat.DATAFLASH, ".csv": LogFormat.CSV}
_DECODERS: dict[LogFormat, Callable[[str | Path], DecodedLog]] = {
    LogFormat.TLOG: decode_tlog,
    LogFormat.ULOG: decode_ulog,
    LogFormat.DATAFLASH: decode_dataflash,
    LogFormat.CSV: decode_csv,
}


def detect_format(path: str | Path) -> LogFormat:
    """Which reader fits ``path``: by its first bytes, else by its extension.

    Raises
    ------
    InputFileError
        Missing, unreadable or empty file, or neither content nor extension known.
    """
    head = read_head(path, 512)
    if sniff_ulog(head):
        return LogFormat.ULOG
    if sniff_dataflash(head):
        return LogFormat.DATAFLASH
    if sniff_tlog(head):
        return LogFormat.TLOG
    if sniff_csv(head):
        return LogFormat.CSV
    fmt = _EXTENSIONS.get(Path(path).suffix.lower())
    if fmt is None:
        raise input_error(path, "unknown log format (neither its first bytes nor its "
                                "extension say .tlog, .ulg, .bin or .csv)")
    return fmt


def decode_log(path: str | Path) -> DecodedLog:
    """Decode any supported log (see :func:`detect_format`) at its reader's boundary."""
    return _DECODERS[detect_format(path)](path)


def log_truncation(path: str | Path) -> str | None:
    """One line saying the log ends inside a record (cut short), or None if it ends whole.

    The readers use every whole record and drop a cut last one; this says that it happened
    (the rest of the log is still usable). Reads the file again, framing only.

    Raises
    ------
    InputFileError
        As :func:`detect_format`.
    """
    fmt = detect_format(path)
    data = read_bytes(path)
    if fmt is LogFormat.CSV:
        cut = csv_tail(data.decode("utf-8", "replace"))
    else:
        cut = {LogFormat.TLOG: tlog_tail, LogFormat.ULOG: ulog_tail,
               LogFormat.DATAFLASH: dataflash_tail}[fmt](data)
    if not cut:
        return None
    return (f"{path} is truncated: it ends inside a record ({cut} of {len(data)} bytes at the "
            "end are not a whole record; was it copied while still being written?); the "
            "whole records before were read")


def open_log(path: str | Path) -> LogReplay:
    """Open a log as a :class:`~mrft_gcs.telemetry.TelemetrySource`.

    The file is decoded at once (errors surface here, not mid-stream); samples
    then come out in time order, ending with :class:`~mrft_gcs.telemetry.EndOfStream`.

    Parameters
    ----------
    path : str or Path
        A .tlog, .ulg, .bin or CSV log.

    Raises
    ------
    InputFileError
        If the file is missing, empty, of an unknown format, malformed or truncated
        beyond use.
    """
    return LogReplay(decode_log(path))


def read_log(path: str | Path) -> TelemetryLog:
    """Read a whole log as arrays (same content as ``collect_log(open_log(path))``).

    Raises
    ------
    InputFileError
        As :func:`open_log`.
    """
    return to_telemetry_log(decode_log(path))
