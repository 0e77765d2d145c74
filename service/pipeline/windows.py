"""Window-level work: what a closed window becomes before its fit, and the fit itself, for every front door.

A :class:`WindowJob` is self-contained (picklable, no handle on the stream), so it runs wherever there is
room: the live service's fit workers (:class:`service.pipeline.fitting.FitPool`), a local process pool or a
Dask cluster for an offline analysis (:func:`run_jobs`).
"""

from __future__ import annotations

import gc
import math
import threading
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from service import blas
from service.analysis.results import FitSettings, Status, WindowResult
from service.analysis.segment import Window
from service.analysis.steady import window_steady_centre
from service.inverse.window_model import Intervals, WindowModel
from service.medians import median
from service.pipeline.records import NO_HIGHLIGHT, coefficients_of


@dataclass(frozen=True)
class WindowJob:
    """One window's fit to be done: the series it takes (the steady D(0, t), mm per frame, NaN where frames are
    missing), its frames' mean brightness (where the fit takes its poles from the frames), their median highlight
    (:data:`~service.pipeline.records.FRAME`'s, fraction of full scale; NaN where unknown) and when (monotonic s)
    the frame that closed it was read (NaN offline); the window model's calibration of its intervals, if any, and
    the steady D(0, t) it corrected (``series`` being the correction's)."""

    window: Window
    series: np.ndarray
    brightness: np.ndarray | None = None
    highlight: float = math.nan
    closed_at: float = math.nan
    intervals: Intervals | None = None
    steady: np.ndarray | None = None


def job_for(
    window: Window,
    records: np.ndarray,
    radius_mm: float,
    transient: int,
    closed_at: float = math.nan,
    model: WindowModel | None = None,
) -> WindowJob:
    """The job of ``window`` from its frames' records: its steady D(0, t) (:mod:`service.analysis.steady`), with
    ``model``'s correction and its intervals' calibration where there is one (:func:`window_model_for`), and
    brightness."""
    coefficients = coefficients_of(records)
    steady = window_steady_centre(coefficients, radius_mm, transient, window.starts_at_ejection)
    series = steady
    if model is not None:
        skip = transient if window.starts_at_ejection else 0
        series = model.correct(coefficients, records["brightness"], steady, skip, records["latent"])
    highlight = records["highlight"][np.isfinite(records["highlight"])]
    return WindowJob(
        window,
        series,
        np.ascontiguousarray(records["brightness"]),
        median(highlight),
        closed_at,
        None if model is None else model.intervals,
        None if model is None else steady,
    )


def window_model_for(settings: FitSettings, models: Path, method: str) -> WindowModel | None:
    """The window model of the model folder ``models`` when ``settings`` ask for it (``series_model``) and the
    per-frame ``method`` is the network whose outputs it reads (the other methods' windows keep their steady
    series)."""
    return WindowModel.of_folder(models) if settings.series_model == "window" and method == "network" else None


def fit_job(job: WindowJob, fps: float, settings: FitSettings) -> WindowResult:
    """The window fit (:func:`service.analysis.fit.fit_window`) of one job, its intervals calibrated where the job
    carries a calibration; ``unresolved`` without a fit where its frames show no highlight (a dark or unlit camera
    would otherwise pass for a settled meniscus). The window model de-shrinks oscillations; it does not make a
    settled meniscus move: where its series leaves the window unresolved (a slow swing or trend: its correction
    wandering, on a Blender recording's settled window) and the steady series it corrected is settled, the window is
    settled, as that series' fit reports it, its intervals calibrated as any other's (the calibration was made on
    every window the path reports, such ones among them)."""
    from service.analysis.fit import fit_window

    w = job.window
    if job.highlight < NO_HIGHLIGHT:
        return unfitted_result(
            job,
            f"no highlight in its frames (the brightest pixel {100 * job.highlight:.1f} % of "
            "full scale above the mean, median): a dark, capped or unlit camera shows nothing of "
            "the meniscus",
            "unresolved",
        )
    where = dict(
        index=w.index,
        start_frame=w.start,
        starts_at_ejection=w.starts_at_ejection,
        ends_at_ejection=w.ends_at_ejection,
        brightness=job.brightness,
    )
    result = fit_window(job.series, fps, settings, **where)
    if result.status == "unresolved" and job.steady is not None:
        steady = fit_window(job.steady, fps, settings, **where)
        if steady.status == "settled":
            note = f"in the steady series (the window model's was unresolved: {result.reason})"
            result = steady.model_copy(update={"reason": f"{steady.reason}, {note}"})
    return result if job.intervals is None else job.intervals.apply(result)


def unfitted_result(job: WindowJob, reason: str, status: Status = "failed") -> WindowResult:
    """The result of a job that was not fitted, saying why: its fit failed, or (``unresolved``) had nothing to fit."""
    w, finite = job.window, np.isfinite(job.series)
    return WindowResult(
        index=w.index,
        start_frame=w.start,
        end_frame=w.end,
        status=status,
        reason=reason,
        samples=int(finite.sum()),
        missing=int((~finite).sum()),
        starts_at_ejection=w.starts_at_ejection,
        ends_at_ejection=w.ends_at_ejection,
    )


#: Seconds to wait for a Dask scheduler to answer.
CONNECT_TIMEOUT_S = 10.0
#: Window jobs per task: sent one a task, each window's hand-off (pickling, the pipe both ways, a future) cost the
#: parent and the worker a good part of its fit (docs/benchmarks.md); a few a task keep the workers' last tasks even.
#: The tail (jobs not yet started when :meth:`JobRunner.results` is called) goes one a task, so all workers share it.
CHUNK = 8


class JobRunner:
    """Runs window jobs as independent tasks: in a local process pool of ``workers`` (default: one per core it may
    use, :func:`service.blas.usable_cores`), or on the Dask cluster whose scheduler listens at ``scheduler``
    (``tcp://host:8786``; the ``scale`` extra).

    ``threads``: the threads a task may run (a renderer's), its share of the cores: the pool's processes share the
    machine's; a Dask worker thread is one core (as Dask's nanny gives BLAS and OpenMP one thread), the workers
    being how a cluster grows. More, and the tasks' threads fight for the cores they share.

    A local pool holds its maker's BLAS to one thread for good (:func:`service.blas.hold_one_thread`: its workers
    fork without a BLAS's idle threads to re-create and spin). Started before the frames are read, so that its
    workers load the compiled fit while inference runs; jobs
    :meth:`send` as windows close start :data:`CHUNK` at a time, so that fits run beside the frames' inference."""

    def __init__(self, settings: FitSettings, scheduler: str | None = None, workers: int | None = None) -> None:
        self.settings, self.scheduler = settings, scheduler
        self._client = self._pool = None
        self._closing: threading.Thread | None = None  # the pool's shutdown, once released
        self._waiting: list[WindowJob] = []  # sent, not yet started: fewer than a chunk
        self._started: list[tuple[list[WindowJob], float, Future]] = []  # (jobs, fps, future of results) per task
        self._fps = math.nan  # of the jobs queued
        self._cores, self._workers = 1, 1  # a Dask worker thread is one core
        if scheduler is not None:
            self._client = _dask_client(scheduler)
        else:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            cores = blas.usable_cores()
            count = workers or cores
            self._cores, self._workers = cores, count
            _warm()  # here, once: the forked workers inherit the compiled fit instead of each loading it again
            # fork: a worker starts in milliseconds with everything imported (spawned ones took seconds of the two
            # cores the frames need). Safe here although the caller may run inference threads: a worker only fits
            # (numpy, numba) and never takes a lock those threads hold; the runner is made before the analysis
            # starts threads of its own. The worker freezes what it inherits (gc.freeze) so that its collector never
            # frees the parent's garbage: an onnxruntime session freed so waits on threads the fork did not copy
            # (a test run hung in one).
            self._pool = ProcessPoolExecutor(count, multiprocessing.get_context("fork"), initializer=gc.freeze)
            for _ in range(count):  # the pool starts its processes as work comes: start them all now
                self._pool.submit(int)

    def send(self, jobs: list[WindowJob], fps: float, last: bool = False) -> None:
        """Queue ``jobs``' fits: they start as one task per :data:`CHUNK` jobs queued (see :meth:`results`); with
        ``last`` (no more jobs follow) these and those queued start at once, one a task, so every worker shares them."""
        self._waiting += jobs
        if last:
            self._fps = fps
            self._start_tail()
        while len(self._waiting) >= CHUNK:
            self._start(self._waiting[:CHUNK], fps)
            del self._waiting[:CHUNK]
        self._fps = fps

    def results(self, progress: bool = False) -> list[WindowResult]:
        """Each job's result, in the order sent (a failed one, saying why, where its fit raised), once the jobs still
        queued have started too; with a progress bar over windows. No more jobs come: those not started yet (the
        local pool's tasks still pending, the jobs queued) go one a task, so that every worker has a share of the
        tail rather than one worker a last chunk while the others idle."""
        self._start_tail()
        started, self._started = self._started, []
        return gather([(len(jobs), future) for jobs, _, future in started], progress)

    def _start_tail(self) -> None:
        """Start the jobs queued and those of the local pool's tasks still pending (cancelled: no worker has taken
        them) one a task, in the order sent."""
        tail: list[tuple[WindowJob, float]] = []
        if self._pool is not None:
            while self._started and self._started[-1][2].cancel():
                jobs, fps, _ = self._started.pop()
                tail = [(job, fps) for job in jobs] + tail
        for job, fps in tail + [(job, self._fps) for job in self._waiting]:
            self._start([job], fps)
        self._waiting = []

    def _start(self, jobs: list[WindowJob], fps: float) -> None:
        if self._client is not None:
            future = self._client.submit(_fit_all, jobs, fps, self.settings, pure=False)
        else:
            future = self._pool.submit(_fit_all, jobs, fps, self.settings)
        self._started.append((jobs, fps, future))

    @property
    def threads(self) -> int:
        """The threads a task may run while every worker has one: its share of the cores."""
        return self.threads_for(self._workers)

    def threads_for(self, tasks: int) -> int:
        """The threads each of ``tasks`` tasks started together may run: the cores shared among them, or among the
        local pool's workers where there are more tasks (fewer: a short recording's few windows to refine)."""
        return max(1, self._cores // max(1, min(tasks, self._workers)))

    def call(self, task: Callable[..., Any], *args: Any) -> Future:
        """Start any other window-level ``task(*args)`` (a picklable function of self-contained arguments)."""
        if self._client is not None:
            return self._client.submit(task, *args, pure=False)
        return self._pool.submit(task, *args)

    def release(self) -> None:
        """No more work comes: the local pool's workers start to exit now, beside what the caller does next (its
        report); :meth:`close` waits for them (so that their CPU is counted as the caller's children's)."""
        if self._pool is not None and self._closing is None:
            self._closing = threading.Thread(target=self._pool.shutdown, name="meniscope-pool-close")
            self._closing.start()

    def close(self) -> None:
        if self._client is not None:
            self._client.close()
        if self._pool is not None:
            self.release()
            self._closing.join()

    def __enter__(self) -> JobRunner:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def gather(started: list[tuple[int, Future]], progress: bool = False) -> list[WindowResult]:
    """The results of tasks (their number of jobs, the future of their results) in order, with a progress bar over
    windows."""
    from tqdm import tqdm

    results: list[WindowResult] = []
    with tqdm(total=sum(n for n, _ in started), desc="fit", unit="window", disable=not progress) as bar:
        for n, future in started:
            results += future.result()
            bar.update(n)
    return results


def _fit_all(jobs: list[WindowJob], fps: float, settings: FitSettings) -> list[WindowResult]:
    """Each job's :func:`fit_or_failed`."""
    return [fit_or_failed(job, fps, settings) for job in jobs]


def fit_or_failed(job: WindowJob, fps: float, settings: FitSettings) -> WindowResult:
    """:func:`fit_job`, or the failed result naming what it raised (one window's fit never stops an analysis)."""
    try:
        return fit_job(job, fps, settings)
    except Exception as exc:
        return unfitted_result(job, f"the fit raised {type(exc).__name__}: {exc}")


def _warm() -> None:
    """Load the fit and its compiled kernels (from numba's cache; milliseconds once loaded), and hold this process's
    BLAS to one thread for good (:func:`service.blas.hold_one_thread`), so that the workers it forks have none of a
    BLAS's threads to re-create and spin, nor does it start them again by raising it back."""
    from service.analysis.fit import warm

    warm()
    blas.hold_one_thread()


def _dask_client(scheduler: str):  # type: ignore[no-untyped-def]
    """A client of the Dask scheduler at ``scheduler``; a clear error without the ``scale`` extra or a scheduler."""
    from service.errors import MeniscopeError

    try:
        from distributed import Client
    except ImportError:
        raise MeniscopeError(
            "--scheduler", "needs the Dask distributed package: pip install 'meniscope[scale]'"
        ) from None
    try:
        return Client(scheduler, timeout=CONNECT_TIMEOUT_S, set_as_default=False)
    except (OSError, TimeoutError) as exc:
        raise MeniscopeError(scheduler, f"cannot reach the Dask scheduler: {exc}") from None
