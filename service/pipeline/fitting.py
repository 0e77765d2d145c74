"""Window fits in worker processes: the caller hands a closed window over and never waits for it.

Processes rather than threads because the fit's Python around its compiled kernels (a few dozen calls
per window) holds the interpreter lock, which inference, acquisition and the web server need; the workers run at a lower
priority (``nice``, 10 by default) so that on a busy machine frames keep flowing and windows wait (``meniscope bench
serve`` found no latency to gain at nice 0: the fit's p99 no lower, the frames' higher). One window per
worker is in flight and up to ``BACKLOG`` more wait (a batch of 512 frames at 19,000 frames/s closes up to
three windows at once, and a spell the machine was busy closes more: a backlog of one per worker left 1-4 %
of the windows unfitted on a quiet machine); a window that finds that backlog full is refused (the caller
counts it), so a fit slower than the ejection rate for longer than the backlog lasts costs windows, never
memory or frames.

Each worker has a pipe of its own: the caller writes the window straight into it and a thread per worker,
asleep in the pipe's read until the result comes, hands the result on. (A ``ProcessPoolExecutor`` passes
each window through two threads of its own on the way in and one on the way out, each waiting for the
interpreter lock: milliseconds per window on a busy machine.)
"""

from __future__ import annotations

import math
import multiprocessing
import os
import threading
import time
from collections import deque
from collections.abc import Callable
from multiprocessing.connection import Connection

import numpy as np

from service.analysis.results import FitSettings, WindowResult
from service.analysis.segment import Window
from service.errors import MeniscopeError
from service.pipeline.windows import WindowJob, fit_job, unfitted_result

#: What the pool calls with each finished fit: the job, its result (a failed one if the fit raised), and when
#: (monotonic s: one clock for every process on the machine) its worker started and finished it (NaN if it raised).
OnFitted = Callable[[WindowJob, WindowResult, float, float], None]

#: Windows that may wait for a worker: 160 ms of windows at 100 ejections/s, a few kB each.
BACKLOG = 16


def _serve(conn: Connection, settings: FitSettings, nice: int) -> None:
    """A worker process: fit each (job, fps) the pipe brings until None, answering each with (result, started,
    finished) (monotonic s) or, if the fit raised, the error as text."""
    from service import blas

    os.nice(nice)
    blas.hold_one_thread()
    try:
        _fit_until_told(conn, settings)
    except (EOFError, OSError):  # the service went away (killed, or stopped without waiting): nothing to answer
        return


def _fit_until_told(conn: Connection, settings: FitSettings) -> None:
    """The loop of :func:`_serve`, until None comes or the pipe breaks."""
    while (sent := conn.recv()) is not None:
        started = time.monotonic()
        job, fps = sent
        try:
            answer: tuple[WindowResult, float, float] | str = (fit_job(job, fps, settings), started, time.monotonic())
        except Exception as exc:
            answer = f"{type(exc).__name__}: {exc}"
        conn.send(answer)


#: A window handed to the pool: its job, its frame rate and where its result goes.
Job = tuple[WindowJob, float, OnFitted]


class _Worker:
    """One worker process, the caller's end of its pipe and the window it is fitting (None when idle)."""

    def __init__(self, settings: FitSettings, nice: int) -> None:
        # spawn, not fork: forking a process whose other threads hold locks can deadlock the child
        context = multiprocessing.get_context("spawn")
        self.conn, child = context.Pipe()
        self.process = context.Process(target=_serve, args=(child, settings, nice), name="meniscope-fit", daemon=True)
        self.process.start()
        child.close()
        self.job: Job | None = None


class FitPool:
    """``workers`` processes at ``nice`` fitting windows with ``settings``; each result goes to the callback
    given with it."""

    def __init__(self, workers: int, settings: FitSettings, nice: int = 10) -> None:
        self.workers, self.settings, self.nice = workers, settings, nice
        self.broken = False
        self._closing = False
        self._lock = threading.Lock()  # guards which workers are idle and the windows waiting
        self._idle: list[_Worker] = []
        self._waiting: deque[Job] = deque()
        self._all = [_Worker(settings, nice) for _ in range(workers)]
        warm = np.sin(
            np.arange(64) / 3.0
        )  # start the workers, import and load the compiled fit now, not at the first window
        for worker in self._all:
            worker.conn.send((WindowJob(Window(0, 0, 64, False, False), warm, warm), 1.0))
        for worker in self._all:
            worker.conn.recv()
            threading.Thread(target=self._receive, args=(worker,), name="meniscope-fit-results", daemon=True).start()
            self._idle.append(worker)

    @property
    def pids(self) -> list[int]:
        """The worker processes' ids."""
        return [worker.process.pid for worker in self._all]

    def submit(self, closed: WindowJob, fps: float, on_fitted: OnFitted) -> bool:
        """Start fitting ``closed`` (sampled at ``fps``), or queue it behind the fits in flight; False (and
        nothing done) when every worker is busy and ``BACKLOG`` windows already wait."""
        if self.broken:
            raise MeniscopeError("fit workers", "a fit worker process died; starting new ones")
        job = (closed, fps, on_fitted)
        with self._lock:
            if not self._idle:
                if len(self._waiting) >= BACKLOG:
                    return False
                self._waiting.append(job)
                return True
            worker = self._idle.pop()
        self._start(worker, job)
        return True

    def _start(self, worker: _Worker, job: Job) -> None:
        """Hand ``job`` to ``worker``; a worker found dead breaks the pool."""
        worker.job = job
        closed, fps, _ = job
        try:
            worker.conn.send((closed, fps))
        except OSError:  # the worker died since its last fit
            worker.job, self.broken = None, True
            raise MeniscopeError("fit workers", "a fit worker process died; starting new ones") from None

    def _receive(self, worker: _Worker) -> None:
        """The worker's results, each to its callback, then the next waiting window to the worker, until its pipe
        closes (a worker that died: the pool is broken, its window and those waiting reported failed)."""
        while True:
            try:
                answer = worker.conn.recv()
            except (EOFError, OSError):
                worker.conn.close()
                if not self._closing:
                    self.broken = True
                    with self._lock:
                        lost = ([worker.job] if worker.job is not None else []) + list(self._waiting)
                        self._waiting.clear()
                    for closed, _, on_fitted in lost:
                        on_fitted(closed, unfitted_result(closed, "the fit worker process died"), math.nan, math.nan)
                return
            assert worker.job is not None
            (closed, _, on_fitted), worker.job = worker.job, None
            with self._lock:
                following = self._waiting.popleft() if self._waiting and not self._closing else None
                if following is None:
                    self._idle.append(worker)
            if following is not None:
                try:
                    self._start(worker, following)
                except MeniscopeError:
                    closed_next, _, on_next = following
                    on_next(
                        closed_next, unfitted_result(closed_next, "the fit worker process died"), math.nan, math.nan
                    )
            if isinstance(answer, str):
                on_fitted(closed, unfitted_result(closed, f"the fit raised {answer}"), math.nan, math.nan)
            else:
                on_fitted(closed, *answer)

    def join(self, timeout: float) -> None:
        """Wait up to ``timeout`` s in all for the workers to exit after :meth:`close` (their last results
        delivered while this process still listens; one that does not exit is terminated, and waited for, so that
        no worker outlives the pool: a later reaping counted its CPU to whatever ran then)."""
        deadline = time.monotonic() + timeout
        for worker in self._all:
            worker.process.join(max(0.0, deadline - time.monotonic()))
            if worker.process.is_alive():
                worker.process.terminate()
                worker.process.join(5.0)  # reaped here, not during whatever this process runs next

    def close(self) -> None:
        """Stop the workers: each finishes the fit it is on (its result still delivered) and exits; windows still
        waiting are not fitted."""
        self._closing = True
        for worker in self._all:
            try:
                worker.conn.send(None)
            except OSError:  # already gone
                pass
