"""``meniscope bench pipeline``: the one pipeline's two ways of running, side by side on one recording.

- offline: ``meniscope analyze``'s analysis (:func:`service.analysis.offline.analyse_recording`: the stages on a
  replay at full speed, the windows fitted on the local process pool), the method opened once beforehand;
- live: the live :class:`service.pipeline.runtime.Pipeline` (acquisition and inference threads, the fit workers)
  on the same recording replayed at full speed: its capacity, the frames/s it infers when no camera paces it.

Each ``--repeat`` times, alternating, so that both see the same load; medians and the ratio to the camera's rate,
and the CPU each spent per frame (this process and its fit processes; the fit processes' share beside it), which a
loaded machine changes less than it changes frames/s, and where it went: each thread's CPU per frame (sampled from
``/proc`` while it runs, Linux only). The live fit workers count from after they started: spawning them and importing
the service in each is a second or more of CPU, once per service, no cost per frame.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from service.verbs import add_scene_option


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "pipeline", help="offline analysis and the live pipeline's capacity on one recording", description=__doc__
    )
    p.add_argument("recording", type=Path, help="REC.cine or REC.avi, e.g. from `meniscope simulate --windows 200`")
    add_scene_option(p)
    p.add_argument("--repeat", type=int, default=3, help="runs of each (default 3)")
    p.add_argument("--workers", type=int, help="fit processes (default: one per core)")
    p.add_argument("--models", type=Path, help="model folder (default: the shipped one)")
    p.add_argument("--out", type=Path, required=True, help="PIPELINE.json to write; a Markdown table beside it")
    p.set_defaults(func=run)


def cpu_seconds() -> tuple[float, float]:
    """CPU seconds (user + system) this process and its ended children (the fit processes) have used so far."""
    import resource

    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime, children.ru_utime + children.ru_stime


class ThreadCpu:
    """CPU seconds of this process's threads, by thread name, and of ``processes`` added as they start, sampled every
    ``period`` s while in use (a thread that ends keeps its last sample): where a pipeline's CPU goes. Threads
    Python did not start (onnxruntime's) are counted together; empty where ``/proc`` is missing."""

    NATIVE = "native threads (onnxruntime)"

    def __init__(self, period: float = 0.02) -> None:
        import threading

        self.period = period
        self._names: dict[int, str] = {}
        self._start: dict[int, float] = {}
        self._last: dict[int, float] = {}
        self._processes: dict[int, tuple[float, float]] = {}  # pid -> (at start, last)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample_until_stopped, name="bench-sampler", daemon=True)

    @staticmethod
    def _cpu(stat: str) -> float:
        import os

        fields = stat[stat.rindex(")") + 2 :].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime + stime

    def _threads(self) -> dict[int, float]:
        import os

        seconds = {}
        for tid in os.listdir("/proc/self/task") if os.path.isdir("/proc/self/task") else []:
            try:
                with open(f"/proc/self/task/{tid}/stat") as f:
                    seconds[int(tid)] = self._cpu(f.read())
            except OSError:  # ended meanwhile
                pass
        return seconds

    def add_processes(self, pids: list[int]) -> None:
        """Count ``pids``' CPU from now on."""
        for pid in pids:
            try:
                with open(f"/proc/{pid}/stat") as f:
                    now = self._cpu(f.read())
            except OSError:
                continue
            self._processes[pid] = (now, now)

    def _sample(self) -> None:
        import re
        import threading

        for thread in threading.enumerate():
            if thread.native_id is not None:  # an executor's threads by its prefix ("meniscope-hash", not "..._0")
                self._names.setdefault(thread.native_id, re.sub(r"_\d+$", "", thread.name))
        self._last.update(self._threads())
        for pid, (start, _) in list(self._processes.items()):
            try:
                with open(f"/proc/{pid}/stat") as f:
                    self._processes[pid] = (start, self._cpu(f.read()))
            except OSError:  # ended: its last sample stays
                pass

    def _sample_until_stopped(self) -> None:
        while not self._stop.wait(self.period):
            self._sample()

    def __enter__(self) -> ThreadCpu:
        self._start = self._threads()
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self._sample()

    def per_frame(self, frames: int, processes: str = "processes") -> dict[str, float]:
        """CPU us per frame by thread name (this sampler's own left out), and of the processes under ``processes``."""
        by: dict[str, float] = {}
        for tid, seconds in self._last.items():
            name = self._names.get(tid, self.NATIVE)
            if name != self._thread.name:
                by[name] = by.get(name, 0.0) + seconds - self._start.get(tid, 0.0)
        if self._processes:
            by[processes] = sum(last - start for start, last in self._processes.values())
        return {name: 1e6 * seconds / max(frames, 1) for name, seconds in by.items()}


#: The live fit workers, counted from after their start.
LIVE_FITS = "fit workers (after their start)"


def cpu_per_frame(before: tuple[float, float], frames: int) -> dict:
    """CPU us per frame since ``before`` (:func:`cpu_seconds`): in all, and of it the fit processes'."""
    own, fits = (now - then for now, then in zip(cpu_seconds(), before))
    return {
        "cpu_us_per_frame": 1e6 * (own + fits) / max(frames, 1),
        "fit_cpu_us_per_frame": 1e6 * fits / max(frames, 1),
    }


def measure_offline(recording: Path, scene, opened, workers: int | None, models: Path) -> dict:  # type: ignore[no-untyped-def]
    """One offline analysis: wall seconds, frames/s and CPU us per frame (the method of ``models`` already open)."""
    import time

    from service.analysis.offline import analyse_recording

    t0, cpu0 = time.perf_counter(), cpu_seconds()
    with ThreadCpu() as threads:
        analysis = analyse_recording(
            recording, scene, "network", models, progress=False, opened=opened, workers=workers
        )
    seconds = time.perf_counter() - t0
    frames = analysis.report.source.frames
    cpu = cpu_per_frame(cpu0, frames)  # the fit pool has ended: its CPU is counted
    return {
        "seconds": seconds,
        "frames_per_s": frames / seconds,
        **cpu,
        "windows": len(analysis.report.windows),
        "threads_us_per_frame": {**threads.per_frame(frames), "fit processes": cpu["fit_cpu_us_per_frame"]},
    }


def measure_live(recording: Path, scene, method, workers: int | None, models: Path) -> dict:  # type: ignore[no-untyped-def]
    """One run of the live pipeline over the recording at full speed with its fit workers: frames/s inferred and
    windows fitted by the time the last fit came back."""
    import os
    import threading
    import time

    from service.pipeline.fitting import FitPool
    from service.pipeline.runtime import Pipeline, PipelineStats
    from service.server.settings import ServiceSettings
    from service.sources import open_source
    from service.sources.replay import replay_uri

    settings = ServiceSettings(
        source=replay_uri(recording, speed="max"),
        recordings_dir=recording.parent,
        models=models,
        fit_workers=workers or os.cpu_count() or 1,
        queue_batches=1024,
    )
    fitted: list = []
    done = threading.Event()

    class Count:
        def on_window(self, window) -> None:  # type: ignore[no-untyped-def]
            fitted.append(window)
            if len(fitted) >= stats.windows_closed - stats.windows_skipped and ended:
                done.set()

        def on_trace(self, trace) -> None:  # type: ignore[no-untyped-def]
            pass

        def on_inference(self, seconds: float, frames: int) -> None:
            pass

    stats, ended = PipelineStats(), False
    own0, _ = cpu_seconds()
    pool = FitPool(settings.fit_workers, settings.fit, settings.fit_nice)
    try:
        with open_source(settings.source) as source, ThreadCpu() as threads:
            threads.add_processes(pool.pids)
            t0 = time.perf_counter()
            Pipeline(settings, scene, source, method, pool, Count(), stats).run(threading.Event())
            inferred = time.perf_counter() - t0
            ended = True
            if len(fitted) < stats.windows_closed - stats.windows_skipped:
                done.wait(120)
            seconds = time.perf_counter() - t0
    finally:
        pool.close()
    pool.join(10.0)
    frames = stats.frames_inferred
    by_thread = threads.per_frame(frames, LIVE_FITS)
    fits = by_thread.get(LIVE_FITS, 0.0)  # from after their start: spawning them and importing the service is no
    own = 1e6 * (cpu_seconds()[0] - own0) / max(frames, 1)  # cost per frame (a second or more of CPU each)
    return {
        "seconds": seconds,
        "frames_per_s": frames / seconds,
        "cpu_us_per_frame": own + fits,
        "fit_cpu_us_per_frame": fits,
        "inferred_frames_per_s": frames / inferred,
        "frames_dropped": stats.frames_dropped,
        "windows": len(fitted),
        "windows_skipped": stats.windows_skipped,
        "threads_us_per_frame": by_thread,
    }


def markdown(results: dict) -> str:
    """The side-by-side table, and each thread's CPU per frame."""
    import statistics

    fps = results["camera_fps"]
    lines = [
        "| pipeline | frames/s (median) | x camera | CPU us/frame (median) | of it fit processes | windows "
        "| runs (frames/s) |",
        "|---|---:|---:|---:|---:|---:|---|",
    ]
    for name in ("offline", "live"):
        runs = results[name]
        median = results[f"{name}_median_frames_per_s"]
        each = ", ".join(f"{r['frames_per_s']:.0f}" for r in runs)
        lines.append(
            f"| {name} | {median:.0f} | {median / fps:.2f} | {results[f'{name}_median_cpu_us_per_frame']:.0f} "
            f"| {results[f'{name}_median_fit_cpu_us_per_frame']:.0f} | {runs[-1]['windows']} | {each} |"
        )
    lines.append(
        f"\noffline / live: {results['offline_over_live']:.2f} (medians of {len(results['offline'])} "
        f"alternating runs on {results['recording']}, models {results['models']})\n"
    )
    lines += ["| thread | pipeline | CPU us/frame (median) | runs |", "|---|---|---:|---|"]
    for name in ("offline", "live"):
        threads: dict[str, list[float]] = {}
        for run in results[name]:
            for thread, us in run.get("threads_us_per_frame", {}).items():
                threads.setdefault(thread, []).append(us)
        for thread, runs in sorted(threads.items(), key=lambda item: -statistics.median(item[1])):
            each = ", ".join(f"{us:.1f}" for us in runs)
            lines.append(f"| {thread} | {name} | {statistics.median(runs):.1f} | {each} |")
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from service import DEFAULT_MODELS
    from service.bench.results import write_results
    from service.errors import MeniscopeError
    from service.inverse.methods import open_method
    from service.recordings import open_recording
    from service.scene import Scene

    if args.repeat < 1:
        raise MeniscopeError("--repeat", f"must be at least 1, got {args.repeat}")
    scene = Scene.load(args.scene)
    with open_recording(args.recording) as rec:
        camera_fps = rec.fps
    models = args.models or DEFAULT_MODELS
    opened = open_method("network", scene, models)
    offline, live = [], []
    for k in range(args.repeat):
        print(f"bench pipeline: run {k + 1} of {args.repeat} ...", flush=True)
        offline.append(measure_offline(args.recording, scene, opened, args.workers, models))
        live.append(measure_live(args.recording, scene, opened[0], args.workers, models))
    results = {
        "recording": str(args.recording),
        "models": str(models),
        "camera_fps": camera_fps,
        "offline": offline,
        "live": live,
    }
    for name, runs in (("offline", offline), ("live", live)):
        results[f"{name}_median_frames_per_s"] = float(np.median([r["frames_per_s"] for r in runs]))
        for key in ("cpu_us_per_frame", "fit_cpu_us_per_frame"):
            results[f"{name}_median_{key}"] = float(np.median([r[key] for r in runs]))
    results["offline_over_live"] = results["offline_median_frames_per_s"] / results["live_median_frames_per_s"]
    write_results(args.out, results, markdown(results))
    return 0
