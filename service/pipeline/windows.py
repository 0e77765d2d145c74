"""Window-level work: what a closed window becomes before its fit, and the fit itself, for every front door.

A :class:`WindowJob` is self-contained (picklable, no handle on the stream), so it runs wherever there is
room: the live service's fit workers (:class:`service.pipeline.fitting.FitPool`), a local process pool or a
Dask cluster for an offline analysis (:func:`run_jobs`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from service.analysis.results import FitSettings, WindowResult
from service.analysis.segment import Window
from service.analysis.steady import window_steady_centre
from service.pipeline.records import coefficients_of


@dataclass(frozen=True)
class WindowJob:
    """One window's fit to be done: the series it takes (the steady D(0, t), mm per frame, NaN where frames are
    missing), its frames' mean brightness (where the fit takes its poles from the frames) and when (monotonic s)
    the frame that closed it was read (NaN offline)."""

    window: Window
    series: np.ndarray
    brightness: np.ndarray | None = None
    closed_at: float = math.nan


def job_for(window: Window, records: np.ndarray, radius_mm: float, transient: int,
            closed_at: float = math.nan) -> WindowJob:
    """The job of ``window`` from its frames' records: its steady D(0, t) (:mod:`service.analysis.steady`) and
    brightness."""
    series = window_steady_centre(coefficients_of(records), radius_mm, transient, window.starts_at_ejection)
    return WindowJob(window, series, np.ascontiguousarray(records["brightness"]), closed_at)


def fit_job(job: WindowJob, fps: float, settings: FitSettings) -> WindowResult:
    """The window fit (:func:`service.analysis.fit.fit_window`) of one job."""
    from service.analysis.fit import fit_window

    w = job.window
    return fit_window(job.series, fps, settings, index=w.index, start_frame=w.start,
                      starts_at_ejection=w.starts_at_ejection, ends_at_ejection=w.ends_at_ejection,
                      brightness=job.brightness)


def failed_result(job: WindowJob, reason: str) -> WindowResult:
    """The result of a job whose fit could not be done, saying why."""
    w, finite = job.window, np.isfinite(job.series)
    return WindowResult(index=w.index, start_frame=w.start, end_frame=w.end, status="failed", reason=reason,
                        samples=int(finite.sum()), missing=int((~finite).sum()),
                        starts_at_ejection=w.starts_at_ejection, ends_at_ejection=w.ends_at_ejection)
