"""One interface for the design steps' independent work: local processes or a Dask cluster.

Tasks must be picklable top-level functions of one argument and must carry
their own seed, so results do not depend on where or in what order they ran:
a local run and a Dask run of the same step give identical output.

Examples
--------
>>> with make_executor(workers=1) as ex:
...     ex.map(abs, [-1, 2, -3])
[1, 2, 3]
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor
from typing import Any, Protocol

from mrft_gcs.errors import MissingDependency, UsageError

__all__ = ["Executor", "LocalExecutor", "DaskExecutor", "make_executor"]


class Executor(Protocol):
    """Maps a function over items, returning results in item order."""

    def map(self, fn: Callable[[Any], Any], items: Iterable[Any]) -> list[Any]: ...

    def close(self) -> None: ...


class LocalExecutor:
    """``workers`` local processes (``1``: in this process, no pool)."""

    def __init__(self, workers: int = 1) -> None:
        if workers < 1:
            raise UsageError("--workers must be at least 1")
        self.workers = workers
        self._pool = ProcessPoolExecutor(workers) if workers > 1 else None

    def map(self, fn, items):
        items = list(items)
        if self._pool is None:
            return [fn(x) for x in items]
        return list(self._pool.map(fn, items))

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class DaskExecutor:
    """Tasks on an existing Dask cluster (``dask[distributed]``), by scheduler address."""

    def __init__(self, address: str) -> None:
        try:
            from distributed import Client
        except ImportError as exc:
            raise MissingDependency("--dask needs dask: pip install -e '.[design]'") from exc
        try:
            self.client = Client(address, timeout="10s")
        except OSError as exc:
            raise UsageError(f"no Dask scheduler answers at {address}: is the cluster up?") from exc

    def map(self, fn, items):
        futures = self.client.map(fn, list(items), pure=False)
        return self.client.gather(futures)

    def close(self) -> None:
        self.client.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def make_executor(workers: int = 1, dask: str | None = None) -> LocalExecutor | DaskExecutor:
    """A Dask executor when a scheduler address is given, else local processes."""
    return DaskExecutor(dask) if dask else LocalExecutor(workers)
