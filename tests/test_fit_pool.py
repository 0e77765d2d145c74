"""The fit workers (service.pipeline.fitting.FitPool): windows handed over and fitted in other processes, one
in flight and one waiting per worker, and a worker that dies."""

from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np
import pytest

from service.analysis.results import FitSettings, WindowResult
from service.analysis.segment import Window
from service.errors import MeniscopeError
from service.pipeline.fitting import FitPool
from service.pipeline.windows import WindowJob, fit_job

FPS = 19000.0


def damped(n: int = 190) -> np.ndarray:
    """A clean damped oscillation (mm) as a window's steady D(0, t)."""
    t = np.arange(n) / FPS
    return 0.01 * np.exp(-400 * t) * np.cos(2 * np.pi * 1500 * t)


class Results:
    """Collects what the pool hands back, and says when ``expected`` results have come."""

    def __init__(self, expected: int) -> None:
        self.got: list[tuple[WindowJob, WindowResult, float, float, float]] = []
        self.expected, self.done = expected, threading.Event()

    def __call__(self, closed: WindowJob, result: WindowResult, started: float, finished: float) -> None:
        self.got.append((closed, result, started, finished, time.monotonic()))
        if len(self.got) >= self.expected:
            self.done.set()


@pytest.fixture()
def pool() -> FitPool:
    pool = FitPool(1, FitSettings(), nice=0)
    yield pool
    pool.close()


def test_a_window_is_fitted_in_its_worker_as_in_process_and_its_times_follow_each_other(pool: FitPool) -> None:
    closed = WindowJob(Window(3, 100, 290, True, True), damped())
    results = Results(1)
    submitted = time.monotonic()
    assert pool.submit(closed, FPS, results)
    assert results.done.wait(60)
    ((back, result, started, finished, delivered),) = results.got
    assert back is closed
    assert result == fit_job(closed, FPS, FitSettings())
    assert submitted <= started <= finished <= delivered  # one monotonic clock across the processes


def test_a_window_finding_every_worker_busy_waits_once_and_one_more_is_refused(pool: FitPool) -> None:
    first, second, third = (WindowJob(Window(k, 0, 190, True, True), damped()) for k in (0, 1, 2))
    results = Results(2)
    assert pool.submit(first, FPS, results)
    assert pool.submit(second, FPS, results)  # one worker busy: the window waits behind its fit
    assert not pool.submit(third, FPS, results)  # one waiting per worker: refused, nothing queued
    assert results.done.wait(60)
    assert [closed.window.index for closed, *_ in results.got] == [0, 1]
    (_, _, _, first_done, _), (_, _, second_started, _, _) = results.got
    assert first_done <= second_started  # the waiting window went to the worker once it was free
    results.expected, results.done = 3, threading.Event()
    assert pool.submit(third, FPS, results)
    assert results.done.wait(60)
    assert [closed.window.index for closed, *_ in results.got] == [0, 1, 2]


def kill_worker(pool: FitPool) -> None:
    """Kill the pool's one worker process, as the OOM killer would, and wait until it is gone."""
    process = pool._all[0].process
    os.kill(process.pid, signal.SIGKILL)
    process.join(10)


def test_a_worker_that_dies_while_fitting_fails_its_window_and_the_one_waiting_and_the_pool_reports_itself_broken(
    pool: FitPool,
) -> None:
    results = Results(2)
    n = 200_000  # a fit of seconds: still running when the worker is killed just after the hand-over
    long_window = WindowJob(Window(0, 0, n, True, True), damped(n))
    waiting = WindowJob(Window(1, n, n + 190, True, True), damped())
    assert pool.submit(long_window, FPS, results)
    assert pool.submit(waiting, FPS, results)
    kill_worker(pool)
    assert results.done.wait(30)
    assert [closed for closed, *_ in results.got] == [long_window, waiting]
    for _, result, started, finished, _ in results.got:
        assert (result.status, result.reason) == ("failed", "the fit worker process died")
        assert np.isnan(started) and np.isnan(finished)
    assert pool.broken  # the supervisor starts new workers


def test_a_window_handed_to_a_worker_that_died_idle_is_refused_with_an_error_naming_the_workers(pool: FitPool) -> None:
    kill_worker(pool)
    with pytest.raises(MeniscopeError, match="fit worker process died"):
        pool.submit(WindowJob(Window(0, 0, 190, True, True), damped()), FPS, Results(1))
    assert pool.broken
