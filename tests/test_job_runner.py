"""The offline runner of window fits: jobs sent as windows close, several a task, come back in the order sent, each
as the window fit alone makes it, and a fit that raises fails its own window only; the tail (the last jobs, and
those whose task no worker has taken yet) goes one a task; released, the workers exit while results stay."""

from __future__ import annotations

import gc
import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from service.analysis.results import FitSettings
from service.analysis.segment import Window
from service.physics import damped_mode
from service.pipeline.windows import CHUNK, JobRunner, WindowJob, fit_job

FPS = 19000.0


def job(index: int, frames: int = 190, brightness: int | None = None) -> WindowJob:
    """A window of one damped mode (its frequency set by ``index``) with the frames' brightness oscillating with it;
    ``brightness``: that many brightness values instead (a length the fit refuses)."""
    t = np.arange(frames) / FPS
    series = damped_mode(t, 0.01, 300.0, 1200.0 + 10.0 * index, 0.3)
    light = 1000.0 + 2e4 * damped_mode(np.arange(brightness or frames) / FPS, 0.01, 300.0, 1200.0 + 10.0 * index, 0.3)
    start = 200 * index
    return WindowJob(Window(index, start, start + frames, True, True), series, light, highlight=0.5)


@pytest.fixture(scope="module")
def runner() -> JobRunner:
    with JobRunner(FitSettings(), workers=2) as r:
        yield r


@settings(max_examples=8, deadline=None)
@given(sends=st.lists(st.integers(0, 2 * CHUNK + 1), min_size=1, max_size=4), last=st.booleans())
def test_results_come_back_in_the_order_sent_whatever_the_chunks(
    runner: JobRunner, sends: list[int], last: bool
) -> None:
    jobs = [job(i) for i in range(sum(sends))]
    sent = 0
    for k, count in enumerate(sends):  # windows closing a few at a time, as a pass over the frames sends them
        runner.send(jobs[sent : sent + count], FPS, last=last and k == len(sends) - 1)
        sent += count
    results = runner.results()
    assert [r.index for r in results] == [j.window.index for j in jobs]
    assert runner.results() == []  # each result is handed back once


def test_a_window_fitted_by_the_runner_is_the_window_fitted_alone(runner: JobRunner) -> None:
    jobs = [job(i) for i in range(CHUNK + 3)]
    runner.send(jobs, FPS)
    assert runner.results() == [fit_job(j, FPS, FitSettings()) for j in jobs]


def test_a_fit_that_raises_fails_its_own_window_and_no_other(runner: JobRunner) -> None:
    jobs = [job(0), job(1, brightness=50), job(2)]
    runner.send(jobs, FPS)
    first, broken, last = runner.results()
    assert broken.status == "failed" and "the fit raised ValueError" in (broken.reason or "")
    assert first.status == "ok" and last.status == "ok"


def test_the_last_jobs_and_the_tasks_no_worker_took_go_one_a_task(runner: JobRunner) -> None:
    jobs = [job(i) for i in range(6 * CHUNK)]
    runner.send(jobs[: 5 * CHUNK], FPS)  # more tasks than the workers take at once: some still pending
    runner.send(jobs[5 * CHUNK :], FPS, last=True)
    sizes = [len(task) for task, _, _ in runner._started]
    assert sum(sizes) == len(jobs) and sizes[-CHUNK:] == [1] * CHUNK  # the tail sent one a task
    assert sizes[: sizes.index(1)] == [CHUNK] * sizes.index(1)  # the tasks taken kept their chunk
    assert runner.results() == [fit_job(j, FPS, FitSettings()) for j in jobs]


def test_a_released_runner_hands_back_its_results_and_closes() -> None:
    with JobRunner(FitSettings(), workers=2) as r:
        jobs = [job(i) for i in range(CHUNK + 1)]
        r.send(jobs, FPS, last=True)
        results = r.results()
        r.release()  # the workers exit while the caller goes on
        r.release()  # twice does nothing
    assert results == [fit_job(j, FPS, FitSettings()) for j in jobs]


class _Freed:
    """Cyclic garbage that notes, when finalised, the process that freed it."""

    def __init__(self, log: Path) -> None:
        self.log, self.cycle = log, self

    def __del__(self) -> None:
        with self.log.open("a") as out:
            out.write(f"{os.getpid()}\n")


def test_a_forked_worker_never_frees_what_it_inherited(tmp_path):
    """Garbage the parent holds when the pool forks is freed by the parent alone, never by a worker's collector: an
    onnxruntime session freed in a worker waits on threads the fork did not copy (a test run hung so)."""
    log = tmp_path / "freed"
    gc.disable()  # the garbage must still be there when the workers fork
    try:
        _Freed(log)
        with JobRunner(FitSettings(), workers=1) as r:
            r.call(gc.collect).result()
    finally:
        gc.enable()
    gc.collect()
    assert log.read_text().split() == [str(os.getpid())]


def test_fewer_tasks_than_workers_share_the_cores_among_them(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """A task's threads (a renderer's) are its share of the cores: one each where the pool's workers are all busy,
    all of them for a window refined alone (a short recording's)."""
    from service import blas

    monkeypatch.setattr(blas, "usable_cores", lambda: 4)
    with JobRunner(FitSettings(), workers=4) as four, JobRunner(FitSettings(), workers=2) as two:
        assert [four.threads_for(n) for n in (0, 1, 2, 3, 4, 9)] == [4, 4, 2, 1, 1, 1]
        assert [two.threads_for(n) for n in (1, 2, 5)] == [4, 2, 2]
