"""The fit workers (service.pipeline.fitting.FitPool): windows handed over and fitted in other processes, one
in flight per worker and up to BACKLOG waiting, and a worker that dies."""

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
from service.pipeline.fitting import BACKLOG, FitPool
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


def test_windows_finding_every_worker_busy_wait_in_order_up_to_the_backlog_and_one_more_is_refused(
    pool: FitPool,
) -> None:
    n = 10_000  # the first window a fit of tenths of a second: still in flight while the others are submitted
    first = WindowJob(Window(0, 0, n, True, True), damped(n))
    jobs = [first] + [WindowJob(Window(k, 0, 190, True, True), damped()) for k in range(1, BACKLOG + 2)]
    *accepted, refused = jobs
    results = Results(len(accepted))
    assert all(pool.submit(job, FPS, results) for job in accepted)  # one in flight, BACKLOG waiting
    assert not pool.submit(refused, FPS, results)  # the backlog is full: refused, nothing queued
    assert results.done.wait(60)
    assert [closed.window.index for closed, *_ in results.got] == list(range(len(accepted)))
    finished = [got[3] for got in results.got]
    started = [got[2] for got in results.got]
    assert all(done <= next_start for done, next_start in zip(finished, started[1:]))  # one after another
    results.expected, results.done = len(jobs), threading.Event()
    assert pool.submit(refused, FPS, results)
    assert results.done.wait(60)
    assert results.got[-1][0] is refused


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
