"""``meniscope analyze`` and ``meniscope fit`` as functions: a recording or a series in, a Report out.

A recording is streamed in chunks (any length fits in memory): each chunk's ROI feeds the video
activity (ejection detection) and the per-frame inverse method. The window-level ``regularised``
method then replaces each window's per-frame values by the neighbour candidates its damped
sinusoid passes through. With ``refine``, each window's motion is then refined on its frames through the
renderer (:mod:`service.inverse.synthesis`), starting from the window's fit where the network method's window
model made it (else from the per-frame values), and replaces them. Every
window's steady D(0, t) (:mod:`service.analysis.steady`) is fitted on the runner's processes
(:class:`~service.pipeline.windows.JobRunner`); with the per-frame methods alone, as soon as the window closes.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import ExitStack
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TypeVar

import numpy as np
from tqdm import tqdm

from service.analysis.fit import fit_windows
from service.analysis.results import FitSettings, Report, Source, WindowResult
from service.analysis.segment import Window, find_ejections, frame_activity, series_activity, windows_between
from service.analysis.student import t_quantile
from service.csvtable import write_columns
from service.errors import MeniscopeError
from service.inverse import regularised, synthesis
from service.inverse.base import InverseMethod, InverseOutput
from service.inverse.methods import open_method
from service.inverse.nearest import NearestDatabase
from service.inverse.window_model import WindowModel
from service.physics import WindowMotion, centre_displacement
from service.pipeline.ejections import OFFLINE_LOOKAHEAD_S, EjectionDetector
from service.pipeline.records import COEFFICIENTS, FRAME, coefficients_of
from service.pipeline.segmenter import StreamingSegmenter
from service.pipeline.stages import FrameStages
from service.pipeline.windows import JobRunner, WindowJob, fit_or_failed, job_for, window_model_for
from service.recordings import open_recording
from service.recordings.digest import xxh3_file
from service.recordings.roi import roi_frames
from service.render.renderer import Renderer
from service.scene import Scene
from service.sources import FrameBatch
from service.sources.replay import ReplaySource

_T = TypeVar("_T")

#: Neighbours per frame among which the regularised fit chooses (the paper's 10).
CANDIDATES = 10
#: Frames per read of the replay: large enough that per-call overheads vanish, small enough for the cache.
READ_FRAMES = 512


@dataclass(frozen=True)
class Ejections:
    """How the windows are cut: the printer's file, its rate, or (neither) detection from the data."""

    file: Path | None = None
    hz: float | None = None


@dataclass(frozen=True)
class Analysis:
    """A report, the per-frame estimates behind it (``per_frame.coefficients`` (N, 4), ``centre`` (N,) mm) and
    the series its windows were fitted to (``fitted`` (N,) mm, see :mod:`service.analysis.steady`)."""

    report: Report
    per_frame: InverseOutput
    fitted: np.ndarray


def analyse_recording(
    path: Path,
    scene: Scene,
    method: str,
    models: Path,
    database: Path | None = None,
    ejections: Ejections = Ejections(),
    settings: FitSettings = FitSettings(),
    progress: bool = True,
    opened: tuple[InverseMethod, NearestDatabase | None] | None = None,
    refine: bool = False,
    scheduler: str | None = None,
    workers: int | None = None,
) -> Analysis:
    """The pipeline's stages over a recording replayed at full speed, its windows, (``refine``) each window's motion
    refined on its frames, and one fit per window as independent tasks (:class:`JobRunner`: a local process
    pool of ``workers``, or the Dask cluster at ``scheduler``).

    ``opened``: the method and database :func:`open_method` returned, when analysing several
    recordings with one (they are opened here otherwise). With ``refine`` the windows keep their own poles
    (``settings.poles`` becomes "series"): the refined motion is the window's inversion. The network method's
    windows are fitted first with the window model and their series' own poles (:func:`start_settings`) and searched
    from that fit; where a refinement is rejected (:func:`refine_window`) the window is reported as the default
    method fits it.
    """
    fitted_first = refine and method == "network"  # the window model's fit: the refinement's start
    if method != "network":  # the window model reads the network's per-frame values
        settings = settings.model_copy(update={"series_model": "steady"})
    first_settings = default_settings = settings  # the windows' first fit: the report's, or the search's start
    if refine:
        first_settings, settings = start_settings(settings), refined_settings(settings)
    with ExitStack() as stack:
        # the recording opened once (its header and every image's offset read: ~1 us of CPU per frame), on the
        # hash's thread while this one starts the runner's workers, then replayed
        hasher = ThreadPoolExecutor(1, "meniscope-hash")
        opening = hasher.submit(_open_replay, path)
        stack.callback(_close_opened, opening)  # last: after the hash (read from its mapping) and the runner
        stack.enter_context(hasher)
        inverse, db = opened or open_method(method, scene, models, database)
        db = db if method == "regularised" else None
        model = window_model_for(first_settings, models, method)
        runner = stack.enter_context(JobRunner(first_settings, scheduler, workers))
        replay = opening.result()
        # the hash lets go of the interpreter lock: read while it hashes, from the replay's own mapping of the file
        digest = hasher.submit(xxh3_file, path, replay.mapped)
        fps, frames, width, height = replay.fps, replay.frames, replay.width, replay.height
        transient, radius = settings.transient_frames(fps), scene.nozzle.radius_mm
        detecting = ejections.file is None and ejections.hz is None
        # the windows cut as the frames come, at the ejections the live detector finds looking further ahead; with
        # the default method each is fitted as soon as it closes, beside the inference of the frames after it
        segmenter = StreamingSegmenter(
            frames, EjectionDetector(fps, lookahead=int(round(OFFLINE_LOOKAHEAD_S * fps))) if detecting else None
        )
        # the window-level methods need every window's frames first
        streamed = db is None and (not refine or fitted_first)
        # one pass over the frames (each read once: reading was a fifth of the CPU), in three stages on three threads:
        # read and measured, inferred (the graph, no longer on the thread that segments: docs/benchmarks.md), then
        # segmented and the closed windows sent to be fitted on this one
        parts, found, closed, jobs = [], [], [], []
        with tqdm(total=frames, unit="frame", desc=f"{inverse.name} {path.name}", disable=not progress) as bar:
            measured = _ahead(_measured(replay, scene, inverse), "meniscope-read-ahead")
            for batch, part in _ahead(_inferred(measured, db is None), "meniscope-infer"):
                if db is not None:  # the window fit picks every frame's values among these; one search serves
                    index = db.search(batch.pixels, k=CANDIDATES, exact=True).index
                    _set_coefficients(part, db.coeffs[index[:, 0]], db.centre[index[:, 0]])
                    found.append(index)
                parts.append(part)
                if detecting:
                    closed += segmenter.push(
                        batch.indices, part, part["change"], np.zeros(len(part)), novelty=part["novelty"]
                    )
                if streamed:
                    jobs += _send(runner, [(c.window, c.values) for c in closed], radius, transient, model, fps)
                    closed = []
                bar.update(len(batch))
        # every frame is read: the file's mapping is let go on the hash's thread once the hash is done, beside the
        # last windows' fits, rather than unmapped on this thread as it returns (docs/benchmarks.md, branch spd8)
        batch = None
        released = hasher.submit(replay.close)
        records = np.concatenate(parts) if parts else np.empty(0, FRAME)
        n = len(records)
        if n < 2:
            raise MeniscopeError(path, f"{n} frame(s): a window analysis needs at least 2")
        if not detecting:  # the printer's ejections, or its rate's, placed on the whole recording's changes
            cuts, _ = find_ejections(frame_activity(records["change"]), fps, ejections.file, ejections.hz)
            closed += segmenter.push(np.arange(n), records, records["change"], np.zeros(n), cuts)
        closed += segmenter.finish(np.nan)
        if streamed:  # the last windows: every worker shares them
            jobs += _send(runner, [(c.window, c.values) for c in closed], radius, transient, model, fps, last=True)
            windows = [job.window for job in jobs]
        else:
            windows = [c.window for c in closed]
        if detecting:
            cuts = np.array([w.start for w in windows if w.starts_at_ejection], np.int64)
        if db is not None:
            _set_coefficients(records, *_regularise(db, np.concatenate(found), windows, fps, settings, progress))
        refined: dict[int, RefinedWindow] = {}
        if refine:
            fitted, unrefined = {}, {}
            if fitted_first:  # the search's starts, then the same jobs fitted as the default method fits them
                fitted = {r.index: r for r in runner.results(progress)}
                runner.settings = default_settings
                runner.send(jobs, fps, last=True)
                unrefined = {
                    r.index: RefinedWindow.unrefined(job, records[job.window.start : job.window.end], r)
                    for job, r in zip(jobs, runner.results(progress))
                }
            refined = _refine(path, scene, records, windows, fps, settings, runner, progress, fitted, unrefined)
            for w in windows:
                if w.index in refined:
                    records[w.start : w.end] = refined[w.index].records
            records["centre"] = centre_displacement(*coefficients_of(records).T, radius)
            runner.settings, model = settings, None  # the refined motion's own series and poles are fitted now
        if not streamed or refine:  # (with ``refine``, the windows too short for the search: refitted alone)
            rest = [w for w in windows if w.index not in refined]
            jobs = _send(runner, [(w, records[w.start : w.end]) for w in rest], radius, transient, model, fps)
        results = iter(runner.results(progress))
        results = [refined[w.index].result if w.index in refined else next(results) for w in windows]
        runner.release()  # its workers exit while the report is built
        source = Source(path=str(path), frames=n, fps=fps, width=width, height=height, xxh3_128=digest.result())
        released.result()  # a failure to let go of the file is this analysis' error, not lost on the hash's thread
        report = Report(
            source=source, method=method_label(method, refine), ejections=cuts.tolist(), windows=results, fit=settings
        )
        fitted = np.full(n, np.nan)
        for w, series in [(job.window, job.series) for job in jobs] + [(r.window, r.series) for r in refined.values()]:
            fitted[w.start : w.end] = series
        per_frame = InverseOutput(coefficients=coefficients_of(records), centre=records["centre"].copy())
    return Analysis(report, per_frame, fitted)


def fps_of(path: Path) -> float:
    """The recording's frame rate."""
    with open_recording(path) as rec:
        return rec.fps


#: A read of the replay, measured: its frames, their records and the inverse method's input, and the stream's stages.
_Measured = tuple[FrameBatch, np.ndarray, np.ndarray, FrameStages]


def _measured(source: ReplaySource, scene: Scene, inverse: InverseMethod) -> Iterator[_Measured]:
    """The open replay ``source`` read at full speed in reads of :data:`READ_FRAMES`: each read's ROI, its records
    as far as the pixels alone fill them and the inverse method's input (:meth:`FrameStages.measure`), with the
    stages of the stream."""
    stages = FrameStages(scene, source.format, str(source.path), inverse)
    while (batch := source.read(READ_FRAMES)) is not None:
        batch = stages.roi(batch)
        yield batch, *stages.measure(batch), stages


def _inferred(measured: Iterator[_Measured], infer: bool) -> Iterator[tuple[FrameBatch, np.ndarray]]:
    """Each read of ``measured``: its frames and records, with ``infer`` the inverse method's values filled in
    (:meth:`FrameStages.infer`)."""
    for batch, part, inputs, stages in measured:
        yield batch, stages.infer(inputs, part) if infer else part


_END = object()


def _ahead(items: Iterator[_T], name: str, depth: int = 2) -> Iterator[_T]:
    """``items``, each made on a thread of its own (``name``) up to ``depth`` ahead, in order: reading and measuring
    the next frames, inferring these and segmenting those before overlap on two cores (the file reads, numpy, OpenCV,
    numba's passes and onnxruntime let go of the interpreter lock)."""
    with ThreadPoolExecutor(1, name) as thread:  # one thread: ``items`` advanced by it alone
        pending = deque(thread.submit(next, items, _END) for _ in range(depth))
        while (item := pending.popleft().result()) is not _END:
            pending.append(thread.submit(next, items, _END))
            yield item


def _send(
    runner: JobRunner,
    windows: list[tuple[Window, np.ndarray]],
    radius_mm: float,
    transient: int,
    model: WindowModel | None,
    fps: float,
    last: bool = False,
) -> list[WindowJob]:
    """The jobs of ``windows`` (each with its frames' records: :func:`job_for`), sent to ``runner`` to be fitted
    (``last``: no more follow, :meth:`JobRunner.send`)."""
    jobs = [job_for(window, records, radius_mm, transient, model=model) for window, records in windows]
    runner.send(jobs, fps, last)
    return jobs


def _open_replay(path: Path) -> ReplaySource:
    """The recording at ``path`` open for a replay at full speed (its frames views of the file's mapping)."""
    replay = ReplaySource(path, speed=0.0, views=True)
    replay.open()
    return replay


def _close_opened(opening: Future[ReplaySource]) -> None:
    """Close the replay ``opening`` opened, if it did (where it raised, the error was raised where it was awaited)."""
    if opening.exception() is None:
        opening.result().close()


def _set_coefficients(records: np.ndarray, coefficients: np.ndarray, centre: np.ndarray) -> None:
    """Write coefficients (N, 4) and D(0, t) (N,) into ``records`` (N,) in place."""
    for name, column in zip(COEFFICIENTS, np.asarray(coefficients).T):
        records[name] = column
    records["centre"] = centre


def _regularise(
    db: NearestDatabase,
    candidates: np.ndarray,
    windows: list[Window],
    fps: float,
    settings: FitSettings,
    progress: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """Per frame, the candidate the window's regularised fit chose (the nearest in a window's transient)."""
    chosen = candidates[:, 0].copy()
    skip = settings.transient_frames(fps)
    for w in tqdm(windows, desc="regularised fit", unit="window", disable=not progress):
        lo = w.oscillation_start(skip)
        if w.end - lo < 4:  # too short to fit a sinusoid: keep the nearest
            continue
        chosen[lo : w.end] = regularised.chosen_rows(candidates[lo : w.end], db.centre, fps)[0]
    return db.coeffs[chosen], db.centre[chosen]


def start_settings(settings: FitSettings) -> FitSettings:
    """The first fit of a window that ``--refine`` searches from (in ``analyze`` and ``serve``'s lane alike): the
    series ``settings`` name, with its own poles."""
    return settings.model_copy(update={"poles": "series"})


def refined_settings(settings: FitSettings) -> FitSettings:
    """The fit of a refined window: the refined motion's own series and poles (the window model reads per-frame
    values, not refined ones)."""
    return settings.model_copy(update={"poles": "series", "series_model": "steady"})


def method_label(method: str, refine: bool) -> str:
    """The method a report names: the per-frame method, with ``+synthesis`` when its windows were refined."""
    return f"{method}+synthesis" if refine else method


def _refine(
    path: Path,
    scene: Scene,
    records: np.ndarray,
    windows: list[Window],
    fps: float,
    settings: FitSettings,
    runner: JobRunner,
    progress: bool,
    fitted: dict[int, WindowResult],
    unrefined: dict[int, RefinedWindow],
) -> dict[int, RefinedWindow]:
    """Each window long enough for the search refined by :func:`refine_window` (from its result in ``fitted``, by
    index, where it has one, and reporting ``unrefined``'s where the refinement is rejected), by index; each window
    an independent task on ``runner`` (on a share of the cores: all of them for a window alone)."""
    futures = []
    refinable = [w for w in windows if refined_from(w, fps, settings) is not None]
    threads = runner.threads_for(len(refinable))
    with open_recording(path) as rec:
        for w in refinable:
            frames = roi_frames(rec, scene, w.start, w.end - w.start)
            futures.append(
                runner.call(
                    refine_window,
                    scene,
                    w,
                    records[w.start : w.end],
                    frames,
                    fps,
                    settings,
                    fitted.get(w.index),
                    threads,
                    unrefined.get(w.index),
                )
            )
    refined = [f.result() for f in tqdm(futures, desc="refine by synthesis", unit="window", disable=not progress)]
    return {r.window.index: r for r in refined}


@dataclass(frozen=True)
class RefinedWindow:
    """A window refined by synthesis: its records with the refined motion's coefficients and D(0, t) (the
    transient's frames keep their per-frame values), the refined series' fit with the pixel fit's intervals, and
    that series (mm per frame); or, where the refinement was rejected, the window as it was and why (``rejected``)."""

    window: Window
    records: np.ndarray
    result: WindowResult
    series: np.ndarray
    rejected: str | None = None

    @classmethod
    def unrefined(cls, job: WindowJob, records: np.ndarray, result: WindowResult) -> RefinedWindow:
        """The window reported as it was, where its refinement is rejected: its own ``records`` (copied), ``result``
        (a fit of ``job``) and ``job``'s series."""
        return cls(job.window, records.copy(), result, job.series)


def refined_from(window: Window, fps: float, settings: FitSettings) -> int | None:
    """The first frame the search reads of ``window`` (after the ejection's transient), None where too few frames
    remain for it (:data:`synthesis.MIN_FRAMES`)."""
    lo = window.oscillation_start(settings.transient_frames(fps))
    return lo if window.end - lo >= synthesis.MIN_FRAMES else None


#: The reason a window whose refinement left the coefficient ranges gives for its unrefined result.
UNREFINED = "the refinement by synthesis ended outside the coefficient ranges: the unrefined fit is reported"
#: How far (relative) the refined window's mode 1 may lie from the frequency the frames' brightness puts it at
#: before the refinement is taken to have settled on another motion (docs/benchmarks.md, "--refine" tails).
ASTRAY_FREQUENCY = 0.01


def _astray(refined: WindowResult, unrefined: WindowResult) -> str | None:
    """Why a refined window's result is not to be reported (None: it is): its mode 1 off the unrefined window's
    (the default method's: the poles of the frames' brightness, which a refinement that settled on mode 2, or on
    the frames' noise, does not move) by over :data:`ASTRAY_FREQUENCY`."""
    if not refined.modes or not unrefined.modes:
        return None
    ours, theirs = refined.modes[0].frequency_hz, unrefined.modes[0].frequency_hz
    if abs(ours - theirs) <= ASTRAY_FREQUENCY * theirs:
        return None
    return (
        f"the refinement by synthesis ended at {ours:.0f} Hz, {100 * abs(ours / theirs - 1):.1f} % off the "
        f"{theirs:.0f} Hz of the frames' brightness: the unrefined window is reported"
    )


def refine_window(
    scene: Scene,
    window: Window,
    records: np.ndarray,
    frames: np.ndarray,
    fps: float,
    settings: FitSettings,
    first: WindowResult | None = None,
    threads: int = 1,
    unrefined: RefinedWindow | None = None,
) -> RefinedWindow:
    """One window of ``meniscope analyze --refine`` (and of ``meniscope serve --refine``'s lane: the same numbers
    from both): its motion refined on its ROI ``frames`` (as stored, one per record) through the renderer, searched
    from its ``first`` fit where there is one (:func:`synthesis.window_start`), else from its per-frame values
    (``records``, :data:`FRAME`), then the refined D(0, t)'s fit with ``settings`` (the refined motion's own series
    and poles) and the pixel fit's intervals. Where the search ends outside the coefficient ranges
    (:func:`synthesis.within_ranges`: a motion no meniscus makes), or (``unrefined`` given: the window as the default
    method reports it) its mode 1 is off the frames' frequency (:func:`_astray`), nothing refined is reported: the
    window is ``unrefined``'s (else its records with their ``first`` fit, else the fit of its records), with the
    reason. ``window`` must be long enough (:func:`refined_from`)."""
    lo = refined_from(window, fps, settings)
    if lo is None:
        raise MeniscopeError(f"window {window.index}", f"{window.end - window.start} frames: too short to refine")
    k, radius = lo - window.start, scene.nozzle.radius_mm
    coefficients = coefficients_of(records)
    t = (np.arange(lo, window.end) - window.start) / fps
    start = synthesis.start_motion(coefficients[k:], t, fps)
    from_fit = None if first is None else synthesis.window_start(first, coefficients[k:], radius)
    coefficients[k:], motion, covariance, clusters = refine_task(scene, frames[k:], t, start, threads, from_fit)
    if not synthesis.within_ranges(motion, t):
        return _kept(window, records, radius, fps, settings, first, unrefined, UNREFINED)
    refined = records.copy()
    _set_coefficients(refined, coefficients, centre_displacement(*coefficients.T, radius))
    job = job_for(window, refined, radius, settings.transient_frames(fps))
    result = fit_or_failed(job, fps, settings)
    astray = None if unrefined is None else _astray(result, unrefined.result)
    if astray is not None:
        return _kept(window, records, radius, fps, settings, first, unrefined, astray)
    intervals = _with_pixel_intervals(result, motion, covariance, clusters, fps, settings.confidence, radius)
    return RefinedWindow(window, refined, intervals, job.series)


def _kept(
    window: Window,
    records: np.ndarray,
    radius_mm: float,
    fps: float,
    settings: FitSettings,
    first: WindowResult | None,
    unrefined: RefinedWindow | None,
    why: str,
) -> RefinedWindow:
    """A window whose refinement is rejected (``why``): ``unrefined`` where given (the default method's window),
    else its records with their ``first`` fit (else the fit of its records), saying why."""
    if unrefined is None:
        job = job_for(window, records, radius_mm, settings.transient_frames(fps))
        unrefined = RefinedWindow.unrefined(
            job, records, first if first is not None else fit_or_failed(job, fps, settings)
        )
    reason = "; ".join(r for r in (unrefined.result.reason, why) if r)
    return replace(unrefined, result=unrefined.result.model_copy(update={"reason": reason}), rejected=why)


#: One renderer per scene and thread count in each process that refines windows (building one costs more than a
#: window's refinement).
_RENDERERS: dict[tuple[str, int], Renderer] = {}


def refine_task(
    scene: Scene,
    frames: np.ndarray,
    t: np.ndarray,
    start: WindowMotion,
    threads: int = 1,
    fitted: WindowMotion | None = None,
) -> tuple[np.ndarray, WindowMotion, np.ndarray, int]:
    """One window's refinement by synthesis (a task that runs wherever the runner sends it, rendering on ``threads``,
    :meth:`JobRunner.threads_for`; the result does not depend on them): the refined motion's coefficients at times
    ``t`` (m, 4), the motion, and the pixel fit's covariance and clusters (:func:`synthesis.covariance`)."""
    key = scene.model_dump_json(), threads
    renderer = _RENDERERS.get(key) or _RENDERERS.setdefault(
        key, Renderer(scene, sun_samples=synthesis.SUN_SAMPLES, threads=threads)
    )
    refined = synthesis.refine_window(renderer, frames, t, start, fitted)
    return (
        refined.motion.coefficients(t).to_array(),
        refined.motion,
        *synthesis.covariance(renderer, frames, t, refined),
    )


def _with_pixel_intervals(
    result: WindowResult,
    motion: WindowMotion,
    covariance: np.ndarray,
    clusters: int,
    fps: float,
    confidence: float,
    radius_mm: float,
) -> WindowResult:
    """A refined window's result with each mode's frequency, decay and amplitude intervals and the offset's (d + p R)
    from the pixel fit's cluster-robust covariance (:func:`synthesis.covariance`; the mode of the motion nearest in
    frequency; Student's t with ``clusters`` - 1 degrees of freedom), not from the window fit of its noise-free
    D(0, t), whose intervals are round-off."""
    z = t_quantile(max(clusters - 1, 1), confidence)
    names = list(motion.as_dict())  # the covariance's order

    def half(*weights: tuple[str, float]) -> float:
        index, w = [names.index(n) for n, _ in weights], np.array([v for _, v in weights])
        return z * float(np.sqrt(max(w @ covariance[np.ix_(index, index)] @ w, 0.0)))

    fields, modes = result.model_dump(), []
    for mode in fields["modes"]:
        k = int(np.argmin(np.abs(np.array([motion.f1, motion.f2]) - mode["frequency_hz"]))) + 1
        f, g, a = mode["frequency_hz"], mode["decay_rate_per_s"], mode["amplitude_mm"]
        f_half, g_half, a_half = (half((f"{n}{k}", 1.0)) for n in "fgA")
        modes.append(
            {
                **mode,
                "frequency_ci_hz": (max(f - f_half, 0.0), min(f + f_half, fps / 2)),
                "decay_rate_ci_per_s": (max(g - g_half, 0.0), g + g_half),
                "amplitude_ci_mm": (max(a - a_half, 0.0), a + a_half),
            }
        )
    offset, offset_half = fields["offset_mm"], half(("d", 1.0), ("p", radius_mm))
    offset_ci = None if offset is None else (offset - offset_half, offset + offset_half)
    kind = "pixels" if modes or offset_ci else fields["intervals"]
    return WindowResult.model_validate({**fields, "modes": modes, "offset_ci_mm": offset_ci, "intervals": kind})


def analyse_series(
    values: np.ndarray,
    fps: float,
    source: Source,
    ejections: Ejections = Ejections(),
    settings: FitSettings = FitSettings(),
    progress: bool = True,
) -> Report:
    """The window fit alone on a displacement series (mm per frame, NaN missing); one window without ejections."""
    if ejections.file is None and ejections.hz is None:
        cuts = np.empty(0, np.int64)
    else:
        cuts, _ = find_ejections(series_activity(values), fps, ejections.file, ejections.hz)
    settings = settings.model_copy(update={"poles": "series"})  # a series alone: no frames to take poles from
    results = fit_windows(values, fps, windows_between(cuts, len(values)), settings, progress=progress)
    return Report(source=source, method="series", ejections=cuts.tolist(), windows=results, fit=settings)


#: Columns of the per-frame CSV that ``meniscope analyze`` writes beside its report.
PER_FRAME_COLUMNS = ("frame", "t_s", "d_mm", "p", "a_mm", "b_mm", "centre_mm")


def write_per_frame(path: Path, per_frame: InverseOutput, fps: float) -> Path:
    """One row per frame: index, time (s) since frame 0, d, p, a, b and D(0, t) (mm)."""
    n = len(per_frame.centre)
    return write_columns(
        path,
        PER_FRAME_COLUMNS,
        [np.arange(n), np.arange(n) / fps, *per_frame.coefficients.T, per_frame.centre],
        "per-frame table",
    )
