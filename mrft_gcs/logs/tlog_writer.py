"""Write a .tlog as MAVLink traffic passes (docs/logs-and-dry-run.md).

Each record is the time the frame passed (microseconds since the Unix epoch,
8-byte big-endian unsigned) followed by the raw frame bytes, the format
QGroundControl and MAVProxy write and :mod:`mrft_gcs.logs.tlog` reads. Every
record (or batch, see ``flush``) is flushed to the operating system as it is
written, so a session that crashes leaves a log that is readable up to its last
frame.

Examples
--------
>>> import tempfile, pathlib
>>> path = pathlib.Path(tempfile.mkdtemp()) / "session.tlog"
>>> with TlogWriter(path) as w:
...     w.write(bytes.fromhex("fe09000101000000000002030451040300"), 1700000000.0)
>>> path.stat().st_size
25
"""

from __future__ import annotations

import math
import struct
from pathlib import Path
from types import TracebackType

from mrft_gcs.errors import UsageError

__all__ = ["TlogWriter"]

_STAMP = struct.Struct(">Q")


class TlogWriter:
    """Append MAVLink frames with their time stamps to a new .tlog file.

    Parameters
    ----------
    path : str or Path
        File to create. Its folder must exist.
    overwrite : bool
        Replace an existing file; by default an existing file is an error, so a
        session never destroys the log of another.

    Raises
    ------
    UsageError
        If the file exists (and ``overwrite`` is false) or cannot be created.
    """

    def __init__(self, path: str | Path, *, overwrite: bool = False) -> None:
        self.path = Path(path)
        try:
            self._file = open(self.path, "wb" if overwrite else "xb")  # noqa: SIM115
        except FileExistsError:
            raise UsageError(f"{self.path}: a log already exists there; "
                             "choose another path or remove it") from None
        except OSError as exc:
            raise UsageError(f"{self.path}: cannot create the telemetry log "
                             f"({exc.strerror or exc}); check the folder exists and is writable"
                             ) from None
        self.frames = 0

    @property
    def closed(self) -> bool:
        """True once :meth:`close` has run."""
        return self._file.closed

    def write(self, msg_bytes: bytes, t_unix_s: float, *, flush: bool = True) -> None:
        """Log one MAVLink frame.

        Parameters
        ----------
        msg_bytes : bytes
            One whole MAVLink v1 or v2 frame, from its STX (``0xFE``/``0xFD``)
            through its checksum (and signature, if signed).
        t_unix_s : float
            When the frame was sent or received, seconds since the Unix epoch.
        flush : bool
            Hand the record to the operating system now (default); a caller writing a
            batch passes False and calls :meth:`flush` after the last.

        Raises
        ------
        ValueError
            If the writer is closed, ``msg_bytes`` is not a MAVLink frame, or the
            time is not a finite non-negative number.
        """
        if self._file.closed:
            raise ValueError(f"{self.path}: write to a closed TlogWriter")
        if len(msg_bytes) < 8 or msg_bytes[0] not in (0xFD, 0xFE):
            raise ValueError("msg_bytes must be one MAVLink frame starting with 0xFD or 0xFE")
        if not (math.isfinite(t_unix_s) and t_unix_s >= 0.0):
            raise ValueError(f"t_unix_s must be finite and >= 0, got {t_unix_s!r}")
        self._file.write(_STAMP.pack(round(t_unix_s * 1e6)) + bytes(msg_bytes))
        if flush:
            self._file.flush()
        self.frames += 1

    def flush(self) -> None:
        """Hand what was written to the operating system."""
        if not self._file.closed:
            self._file.flush()

    def close(self) -> None:
        """Flush and close the file (idempotent)."""
        if not self._file.closed:
            self._file.close()

    def __enter__(self) -> TlogWriter:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()
