"""A thread-safe sink that appends MAVLink frames to a .tlog as they pass.

The format is QGroundControl's and MAVProxy's: for each frame, 8 bytes of
big-endian microseconds since the Unix epoch, then the raw frame. The writer
itself is :class:`mrft_gcs.logs.tlog_writer.TlogWriter` when that module is
present; a minimal one of the same format is used otherwise.

The frames come from the telemetry reader and from the setpoint stream's ticks,
and a write to a file can block for milliseconds (the file system's journal,
dirty-page throttling): a live tune here had a write take 10 ms, and the stream
tick behind it 12 ms. So :meth:`TlogSink.write` only stamps the frame and queues
it, and a thread of the sink's own writes the queue out every 10 ms, each batch
handed to the operating system at once: a crash loses at most the last 10 ms.
"""

from __future__ import annotations

import os
import struct
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

__all__ = ["TlogSink"]


class _MinimalTlogWriter:
    def __init__(self, path: str | os.PathLike[str]) -> None:
        self._f = open(path, "wb")  # noqa: SIM115 - closed in close()

    def write(self, msg_bytes: bytes, t_unix_s: float, *, flush: bool = True) -> None:
        self._f.write(struct.pack(">Q", int(t_unix_s * 1e6)) + bytes(msg_bytes))
        if flush:
            self._f.flush()

    def flush(self) -> None:
        self._f.flush()

    def close(self) -> None:
        self._f.close()


def _writer(path: Path) -> Any:
    try:
        from mrft_gcs.logs.tlog_writer import TlogWriter
    except ImportError:
        return _MinimalTlogWriter(path)
    return TlogWriter(path)


class TlogSink:
    """Append frames from several threads (the reader and the senders) in arrival order.

    :meth:`write` never touches the file: it stamps the frame with the time it passed and
    queues it. The sink's writer thread drains the queue every ``every_s`` seconds;
    :meth:`close` writes what is left.
    """

    def __init__(self, path: str | os.PathLike[str], every_s: float = 0.01) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._writer = _writer(self.path)
        self._queue: deque[tuple[float, bytes]] = deque()  # append/popleft: thread-safe
        self._lock = threading.Lock()  # the file, between the writer thread and close()
        self._closing = threading.Event()
        self.every_s = every_s
        self.frames = 0  # written to the file so far
        #: why writing the file failed (the disk full, say); the session goes on unlogged
        self.error: str | None = None
        self._thread = threading.Thread(target=self._run, daemon=True, name="tlog-writer")
        self._thread.start()

    def write(self, frame: bytes) -> None:
        """Queue one frame (cheap: safe on the stream's ticks)."""
        if not self._closing.is_set() and self.error is None:
            self._queue.append((time.time(), bytes(frame)))

    def _run(self) -> None:
        while not self._closing.wait(self.every_s):
            self._drain()

    def _drain(self) -> None:
        with self._lock:
            if self._writer is None or not self._queue:
                return
            try:
                while self._queue:
                    t, frame = self._queue.popleft()
                    try:
                        self._writer.write(frame, t, flush=False)
                    except ValueError:  # not a whole frame (never expected from pymavlink)
                        continue
                    self.frames += 1
                self._writer.flush()
            except OSError as err:  # a log must not stop a flight: say so and stop logging
                self.error = f"{err.strerror or err}"
                self._queue.clear()

    def close(self) -> None:
        """Write what is queued and close the file (idempotent)."""
        self._closing.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)
        self._drain()
        with self._lock:
            if self._writer is not None:
                writer, self._writer = self._writer, None
                try:
                    writer.close()
                except OSError as err:  # the last flush
                    self.error = self.error or f"{err.strerror or err}"
