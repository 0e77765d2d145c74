"""Where chunks of offline work run: in this process, in local worker processes, or on a Dask cluster.

One :class:`concurrent.futures.Executor` stands for all three, so the code that farms chunks out
(``training.dataset``) is the same whatever runs them; it only needs the chunk function to be pure and
importable on the workers (``meniscope`` installed there, the same version).

Dask distributed, not Ray: dask and distributed are pure-Python wheels (2.5 MB together for 2026.8.0,
against Ray's platform-specific binary wheel), nothing runs but ``dask scheduler`` and ``dask worker`` on each host, and
its client already offers the standard Executor interface (``Client.get_executor``) that a local
``ProcessPoolExecutor`` has.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from concurrent.futures import Executor, Future, ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

from service.errors import MeniscopeError

#: How long a client waits for the scheduler before giving up, s.
CONNECT_TIMEOUT_S = 10.0


class InlineExecutor(Executor):
    """Runs each submitted call at once in this process (one worker, no pickling)."""

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future:
        future: Future = Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except BaseException as exc:
            future.set_exception(exc)
        return future


@dataclass(frozen=True)
class Engine:
    """An open executor and how many calls it runs at once (its slots)."""

    executor: Executor
    slots: int


@contextmanager
def open_engine(workers: int = 1, scheduler: str | None = None) -> Iterator[Engine]:
    """An :class:`Engine` for ``workers`` local processes, or for the Dask scheduler at ``scheduler``
    (``tcp://host:8786``; then ``workers`` is ignored and the cluster's threads count as slots)."""
    if scheduler:
        with _dask_engine(scheduler) as engine:
            yield engine
        return
    if workers < 1:
        raise MeniscopeError("--workers", f"must be at least 1, got {workers}")
    if workers == 1:
        yield Engine(InlineExecutor(), 1)
        return
    with ProcessPoolExecutor(max_workers=workers) as pool:
        yield Engine(pool, workers)


@contextmanager
def _dask_engine(scheduler: str) -> Iterator[Engine]:
    try:
        from distributed import Client
    except ImportError:
        raise MeniscopeError("--scheduler", "needs Dask distributed: pip install 'meniscope[scale]'") from None
    try:
        client = Client(scheduler, timeout=CONNECT_TIMEOUT_S, set_as_default=False)
    except (OSError, TimeoutError, ValueError) as exc:
        raise MeniscopeError(scheduler, f"cannot reach the Dask scheduler: {exc}") from None
    with client:
        threads = sum(client.nthreads().values())
        if threads == 0:
            raise MeniscopeError(scheduler, "the Dask scheduler has no workers: start some with `dask worker`")
        # pure=False: every submission runs, even one equal to an earlier (a retry after a failure)
        yield Engine(client.get_executor(pure=False), threads)
