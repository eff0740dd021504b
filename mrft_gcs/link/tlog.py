"""A thread-safe sink that appends MAVLink frames to a .tlog as they pass.

The format is QGroundControl's and MAVProxy's: for each frame, 8 bytes of
big-endian microseconds since the Unix epoch, then the raw frame. The writer
itself is :class:`mrft_gcs.logs.tlog_writer.TlogWriter` when that module is
present; a minimal one of the same format is used otherwise.
"""

from __future__ import annotations

import os
import struct
import threading
import time
from pathlib import Path
from typing import Any

__all__ = ["TlogSink"]


class _MinimalTlogWriter:
    def __init__(self, path: str | os.PathLike[str]) -> None:
        self._f = open(path, "wb")  # noqa: SIM115 - closed in close()

    def write(self, msg_bytes: bytes, t_unix_s: float) -> None:
        self._f.write(struct.pack(">Q", int(t_unix_s * 1e6)) + bytes(msg_bytes))

    def close(self) -> None:
        self._f.close()


def _writer(path: Path) -> Any:
    try:
        from mrft_gcs.logs.tlog_writer import TlogWriter
    except ImportError:
        return _MinimalTlogWriter(path)
    return TlogWriter(path)


class TlogSink:
    """Append frames from several threads (the reader and the senders) in arrival order."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._writer = _writer(self.path)
        self._lock = threading.Lock()
        self.frames = 0

    def write(self, frame: bytes) -> None:
        with self._lock:
            if self._writer is None:
                return
            try:
                self._writer.write(bytes(frame), time.time())
            except ValueError:  # not a whole frame (never expected from pymavlink): skip it
                return
            self.frames += 1

    def close(self) -> None:
        with self._lock:
            if self._writer is not None:
                self._writer.close()
                self._writer = None
