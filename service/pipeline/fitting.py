"""Window fits in worker processes: the caller hands a closed window over and never waits for it.

Processes rather than threads because the fit's Python around its compiled kernels (a few dozen calls
per window) holds the interpreter lock, which inference, acquisition and the web server need; the workers run at a lower
priority (``nice``, 10 by default) so that on a busy machine frames keep flowing and windows wait. One window per
worker is in flight and none waits behind it: a window that finds every worker busy is refused (the
caller counts it), so a fit slower than the ejection rate costs windows, never memory or frames, and
what is published is as fresh as the fit allows.
"""
from __future__ import annotations

import multiprocessing
import os
import threading
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Callable

import numpy as np

from service.analysis.fit import fit_window
from service.analysis.results import FitSettings, WindowResult
from service.analysis.segment import Window
from service.errors import MeniscopeError
from service.pipeline.segmenter import ClosedWindow

#: What the pool calls with each finished fit: the window and its result (a failed one if the fit raised).
OnFitted = Callable[[ClosedWindow, WindowResult], None]

def _lower_priority(nice: int) -> None:
    os.nice(nice)


def fit_one(window: Window, values: np.ndarray, fps: float, settings: FitSettings,
            brightness: np.ndarray | None = None) -> WindowResult:
    """:func:`fit_window` on one closed window (runs in a worker process)."""
    return fit_window(values, fps, settings, index=window.index, start_frame=window.start,
                      starts_at_ejection=window.starts_at_ejection, ends_at_ejection=window.ends_at_ejection,
                      brightness=brightness)


def _failed(closed: ClosedWindow, exc: BaseException) -> WindowResult:
    w = closed.window
    return WindowResult(index=w.index, start_frame=w.start, end_frame=w.end, status="failed",
                        reason=f"the fit raised {type(exc).__name__}: {exc}", samples=int(np.isfinite(closed.values).sum()),
                        missing=int((~np.isfinite(closed.values)).sum()), starts_at_ejection=w.starts_at_ejection,
                        ends_at_ejection=w.ends_at_ejection)


class FitPool:
    """``workers`` processes at ``nice`` fitting windows with ``settings``; each result goes to the callback
    given with it."""

    def __init__(self, workers: int, settings: FitSettings, nice: int = 10) -> None:
        self.workers, self.settings, self.nice = workers, settings, nice
        # spawn, not fork: forking a process whose other threads hold locks can deadlock the child
        self._pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                                         initializer=_lower_priority, initargs=(nice,))
        self._slots = threading.BoundedSemaphore(workers)
        self.broken = False
        warm = np.sin(np.arange(64) / 3.0)  # start the workers and import scipy now, not at the first window
        self._pool.submit(fit_one, Window(0, 0, 64, False, False), warm, 1.0, settings).result()

    def submit(self, closed: ClosedWindow, fps: float, on_fitted: OnFitted) -> bool:
        """Start fitting ``closed`` (sampled at ``fps``); False (and nothing done) when every slot is busy."""
        if not self._slots.acquire(blocking=False):
            return False
        try:
            future = self._pool.submit(fit_one, closed.window, closed.values, fps, self.settings, closed.brightness)
        except BrokenProcessPool:
            self._slots.release()
            self.broken = True
            raise MeniscopeError("fit workers", "a fit worker process died; starting new ones") from None
        future.add_done_callback(lambda f: self._done(closed, f, on_fitted))
        return True

    def _done(self, closed: ClosedWindow, future: Future, on_fitted: OnFitted) -> None:
        self._slots.release()
        if future.cancelled():
            return
        exc = future.exception()
        on_fitted(closed, _failed(closed, exc) if exc is not None else future.result())

    def close(self) -> None:
        """Stop the workers; fits not yet started are dropped."""
        self._pool.shutdown(wait=False, cancel_futures=True)
