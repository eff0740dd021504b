"""The bundled identification in a process of its own, beside a live tune's setpoint stream.

A live tune streams setpoints at 250 Hz from threads of the ground station's process while
its main thread identifies each loop (classifier, exact gain scaling, the refined fit's
optimisation: 60-120 ms a loop, much of it Python holding the interpreter lock). In the
same process every such call delays stream ticks (the figures: docs/link-and-stream.md).

:class:`IdentificationWorker` starts ``python -m mrft_gcs.identify.worker`` (a plain child
process: nothing of the caller's ``__main__`` is imported again, unlike ``multiprocessing``'s
spawn), warms it up (:func:`mrft_gcs.identify.live.warm_up_identification`'s work) and sends
it one request at a time over its standard input and output as pickles. Each request's
exception is raised again in the caller, so a refused identification reads exactly as an
in-process one. The child runs in a session of its own (a Ctrl-C reaches only the ground
station, which lands first) and exits when its input closes, i.e. when the caller goes.
POSIX only (the reply is waited for with ``select``); elsewhere the caller identifies in
its own process.
"""

from __future__ import annotations

import gc
import os
import pickle
import select
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mrft_gcs.identify.live import (
    bundled_identifier,
    measured_attitude_loop,
    warm_up_identification,
)

__all__ = ["IdentificationWorker", "WorkerError", "AVAILABLE"]

#: whether this platform can run the worker (pipes waited for with ``select``)
AVAILABLE = os.name == "posix"


class WorkerError(RuntimeError):
    """The worker process failed (exited, timed out, or sent something unreadable)."""


class IdentificationWorker:
    """A child process that runs the bundled identification's calls (:meth:`request`).

    Examples
    --------
    >>> w = IdentificationWorker()                                    # doctest: +SKIP
    >>> w.request("warm", att, alt); w.reply(timeout_s=30.0)          # doctest: +SKIP
    >>> ident = w.call("identify", loop, snapshot, inner)             # doctest: +SKIP
    >>> w.close()                                                     # doctest: +SKIP
    """

    def __init__(self) -> None:
        if not AVAILABLE:
            raise WorkerError("the identification worker needs a POSIX system")
        env = dict(os.environ)
        # the same mrft_gcs as this process, whatever the caller did to sys.path
        root = str(Path(__file__).resolve().parents[2])
        env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "mrft_gcs.identify.worker"], stdin=subprocess.PIPE,
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env,
            start_new_session=True)
        self._waiting = False

    @property
    def alive(self) -> bool:
        return self._proc.poll() is None

    def request(self, op: str, *args: Any) -> None:
        """Send one request; :meth:`reply` reads its answer.

        ``"warm"`` (:func:`~mrft_gcs.identify.live.warm_up_identification`), ``"identify"``
        (:func:`~mrft_gcs.identify.live.bundled_identifier`) or ``"attitude_loop"``
        (:func:`~mrft_gcs.identify.live.measured_attitude_loop`, the attitude path).
        """
        if self._waiting:
            raise WorkerError("the worker is still busy with the previous request")
        assert self._proc.stdin is not None
        try:
            pickle.dump((op, args), self._proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
            self._proc.stdin.flush()
        except (OSError, pickle.PicklingError) as err:
            code = self._proc.poll()
            raise WorkerError(f"the identification worker exited (code {code})" if code
                              is not None else f"could not send to the identification "
                              f"worker: {err}") from err
        self._waiting = True

    def reply(self, timeout_s: float) -> Any:
        """The answer to the last request; its exception is raised here."""
        assert self._proc.stdout is not None
        out = self._proc.stdout
        deadline = time.monotonic() + timeout_s
        while True:  # select says when the answer starts to arrive
            left = deadline - time.monotonic()
            if left <= 0:
                raise WorkerError(f"the identification worker did not answer within "
                                  f"{timeout_s:g} s")
            ready, _, _ = select.select([out], [], [], left)
            if ready:
                break
        try:
            status, value = pickle.load(out)
        except (EOFError, OSError, pickle.UnpicklingError) as err:
            code = self._proc.poll()
            raise WorkerError(f"the identification worker exited (code {code})" if code
                              is not None else f"unreadable answer from the identification "
                              f"worker: {err}") from err
        finally:
            self._waiting = False
        if status == "error":
            raise value
        return value

    def call(self, op: str, *args: Any, timeout_s: float = 20.0) -> Any:
        """:meth:`request` and :meth:`reply` in one."""
        self.request(op, *args)
        return self.reply(timeout_s)

    def close(self) -> None:
        """End the worker (closing its input ends it; killed if it does not go in 1 s)."""
        if self._proc.stdin is not None:
            try:
                self._proc.stdin.close()
            except OSError:
                pass
        try:
            self._proc.wait(timeout=1.0)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()
        if self._proc.stdout is not None:
            self._proc.stdout.close()

    def __enter__(self) -> IdentificationWorker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _serve() -> None:
    """The child's loop: one pickled ``(op, args)`` in, one ``(status, value)`` out."""
    ops: dict[str, Callable[..., Any]] = {
        "warm": warm_up_identification, "identify": bundled_identifier,
        "attitude_loop": measured_attitude_loop}
    inp = sys.stdin.buffer
    out = os.fdopen(os.dup(sys.stdout.fileno()), "wb")
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())  # stray prints must not break replies
    while True:
        try:
            op, args = pickle.load(inp)
        except EOFError:
            return  # the ground station closed our input: it is done or gone
        try:
            reply: tuple[str, Any] = ("ok", ops[op](*args))
            if op == "warm":
                gc.freeze()  # what the warm-up loaded stays: no long collections later
        except Exception as err:  # noqa: BLE001 - raised again in the caller
            reply = ("error", err)
        try:
            data = pickle.dumps(reply, protocol=pickle.HIGHEST_PROTOCOL)
        except Exception as err:  # noqa: BLE001 - an unpicklable result or exception
            data = pickle.dumps(("error", WorkerError(f"{type(err).__name__}: {err}")))
        out.write(data)
        out.flush()


if __name__ == "__main__":
    _serve()
