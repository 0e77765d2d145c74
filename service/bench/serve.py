"""``meniscope bench serve``: the live pipeline end to end on a replayed recording, as ``meniscope serve`` runs it.

Per configuration (inference batch x onnxruntime threads), replay speed (1: the camera's rate,
19,000 frames/s for the demo), fit model order and variant (any other service settings, e.g.
``--variants "batch_ms=1000,read_frames=128;batch_ms=2"`` to compare an inference batch bounded in frames
with one bounded in time) one run of ``--seconds`` through the real supervisor, pipeline, fit
workers and publishers (SQLite history in a temporary folder, ZeroMQ on a free port, metrics; only
HTTP is left out), counted from when frames come no faster than the camera makes them (the start's catch-up
over, ``settled_s`` after the first frame): frames read and inferred per second, the fraction dropped, windows closed,
published and left unfitted, and how long after a window closed (the frame that closed it was
read) its result was published (sent on ZeroMQ and to the WebSocket clients; p50, p99, and the share
of closed windows published within 10 ms, which counts a window left unfitted as late). No "as fast
as it reads" run: acquisition would spin reading frames only to drop them, and measure that rather
than the pipeline.

Then, since wall-clock rates on a shared machine say more about the neighbours than about us, the
CPU time (``time.thread_time``) each stage costs per frame, run one after another on one thread:
reading the replay, inference per configuration, the measures, segmentation, and the fit per window.

With ``--refine`` every run is made twice, one after the other: the refinement lane off, then on
(``serve --refine``), with, for the lane, how long after a window closed its refined update was
published (p50, p90), refined windows per minute, and the windows it skipped.

Writes ``serve.json`` and ``serve.md`` to ``--out`` and prints the tables.
"""

from __future__ import annotations

import argparse
import asyncio
import itertools
import os
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from pydantic import ValidationError

from service.analysis.results import FitSettings
from service.bench import parse_pairs
from service.bench.results import write_results
from service.errors import MeniscopeError
from service.recordings import open_recording
from service.server.settings import ServiceSettings, default_data_dir
from service.sources.replay import replay_uri

if TYPE_CHECKING:
    from service.pipeline.runtime import PipelineStats

CONFIGS = "512x1,512x2,128x1"
#: The issue's target: a window's result published within this many ms of its close.
ON_TIME_MS = 10.0


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "serve", help="the live pipeline end to end: frames/s and publish latency", description=__doc__
    )
    p.add_argument("--source", type=Path, help="recording to replay (default: the demo recording)")
    p.add_argument("--seconds", type=float, default=20.0, help="length of each run (default 20)")
    p.add_argument(
        "--configs", default=CONFIGS, help=f"BATCHxTHREADS inference settings, comma-separated (default {CONFIGS})"
    )
    p.add_argument("--speeds", default="1", help="replay speeds, x the recorded rate, comma-separated (default 1)")
    p.add_argument("--fit-workers", type=int, default=1, help="fit worker processes (default 1)")
    fit_nice = ServiceSettings.model_fields["fit_nice"].default
    p.add_argument(
        "--fit-nice",
        type=int,
        default=fit_nice,
        help=f"niceness of the fit workers (default {fit_nice}, the service's)",
    )
    p.add_argument(
        "--max-modes",
        default="2",
        help="fit model orders to compare, comma-separated: 1 fits half the "
        "models of 2 (default 2, the service's default)",
    )
    p.add_argument(
        "--variants",
        default="",
        help="service settings to compare, KEY=VALUE pairs joined by ',', "
        "variants by ';' (default: one variant, the defaults)",
    )
    p.add_argument(
        "--refine",
        action="store_true",
        help="each run with the refinement lane off and then on (serve --refine): the lane's latency and what it "
        "costs the frame path",
    )
    p.add_argument("--out", type=Path, default=Path("bench-serve"), help="folder for the results")
    p.set_defaults(func=run)


#: Steady state: frames read and inferred no faster than this x the stream's own rate over a :data:`SETTLE_STEP_S`.
SETTLE_RATE, SETTLE_STEP_S, SETTLE_MAX_S = 1.05, 0.5, 30.0


def _settle(stats: PipelineStats, due_per_s: float) -> float:
    """Wait until the run is past its start (s waited): the replay runs on a drift-free schedule, so a pipeline
    that fell behind while its fit workers warmed catches up in a burst, and counting through that burst would
    credit it with more frames a second than the camera makes. Steady: over one step, frames read and inferred at
    no more than :data:`SETTLE_RATE` x ``due_per_s`` (a pipeline slower than the camera is steady at once)."""
    t0 = time.monotonic()
    time.sleep(SETTLE_STEP_S)
    while True:
        t, acquired, inferred = time.monotonic(), stats.frames_acquired, stats.frames_inferred
        time.sleep(SETTLE_STEP_S)
        span = time.monotonic() - t
        rates = ((stats.frames_acquired - acquired) / span, (stats.frames_inferred - inferred) / span)
        if due_per_s <= 0 or max(rates) <= SETTLE_RATE * due_per_s or time.monotonic() - t0 > SETTLE_MAX_S:
            return time.monotonic() - t0


def measure(settings: ServiceSettings, seconds: float, due_per_s: float) -> dict:
    """One run: start the pipeline with publishers, wait until frames flow at the stream's rate ``due_per_s``
    (frames/s), count for ``seconds``."""
    from service.pipeline.refining import RefinedUpdate
    from service.pipeline.runtime import FittedWindow, PipelineStats
    from service.pipeline.supervisor import Supervisor
    from service.server.history import History, StoredWindow
    from service.server.hub import Hub
    from service.server.metrics import REFINE_SKIPPED, Metrics
    from service.server.publishers import Publishers
    from service.server.zmq_publisher import ZmqPublisher

    stages: list[tuple[float, ...]] = []  # per published window: its times from closed to published (s)
    refined: list[tuple[float, ...]] = []  # per refined update: closed, taken by the lane, refined, published (s)

    class Timed(Publishers):
        def _send(self, fitted: FittedWindow) -> tuple[StoredWindow, float]:
            stored, sent = super()._send(fitted)
            stages.append(
                (
                    fitted.closed_at,
                    fitted.dispatched_at,
                    fitted.fit_started_at,
                    fitted.fit_finished_at,
                    fitted.fitted_at,
                    sent,
                )
            )
            return stored, sent

        def _send_refined(self, update: RefinedUpdate, window_id: int) -> StoredWindow:
            stored = super()._send_refined(update, window_id)
            refined.append((update.closed_at, update.taken_at, update.started_at, update.finished_at, time.monotonic()))
            return stored

    stats = PipelineStats()
    supervisor: Supervisor | None = None
    loop = asyncio.new_event_loop()  # the hub's; no client connects, so it never runs
    with tempfile.TemporaryDirectory(prefix="meniscope-bench-") as tmp:
        history = History(Path(tmp) / "history.sqlite", 1.0, 1_000_000)
        zmq = ZmqPublisher("tcp://127.0.0.1:*")
        metrics = Metrics(stats, lambda: supervisor.health(), lambda: (0, 0))  # type: ignore[union-attr]
        publishers = Timed(history, metrics, zmq, Hub(loop, 1)).start()
        supervisor = Supervisor(settings, publishers, stats).start()
        try:
            deadline = time.monotonic() + 120
            while stats.frames_inferred == 0:
                if time.monotonic() > deadline:
                    raise MeniscopeError("bench serve", f"no frames inferred in 120 s: {supervisor.health().reason}")
                time.sleep(0.05)
            settled_s = _settle(stats, due_per_s)

            def snapshot() -> tuple:
                """When, the load, the counters and the stage timings taken so far: one end of the measured run."""
                return (
                    time.monotonic(),
                    os.getloadavg()[0],
                    stats.frames_acquired,
                    stats.frames_inferred,
                    stats.frames_dropped,
                    stats.windows_closed,
                    stats.windows_skipped,
                    len(stages),
                    len(refined),
                    sum(
                        metrics.registry.get_sample_value("meniscope_windows_refine_skipped_total", {"reason": r})
                        or 0.0
                        for r in REFINE_SKIPPED
                    ),
                )

            start = snapshot()
            time.sleep(seconds)
            end = snapshot()
        finally:
            supervisor.stop()
            publishers.stop()
            zmq.close()
            history.close()
            loop.close()
    elapsed = end[0] - start[0]
    acquired, inferred, dropped, closed, skipped, published, _, lane_skipped = (
        e - s for e, s in zip(end[2:], start[2:])
    )
    lane = np.array(refined[start[8] : end[8]]).reshape(-1, 5)
    refine_latency = lane[:, 4] - lane[:, 0]
    refine_cpu = lane[:, 3] - lane[:, 2]
    times = np.array(stages[start[7] : end[7]]).reshape(-1, 6) * 1e3
    closed_at, dispatched_at, started_at, finished_at, fitted_at, published_at = times.T
    window_latency = published_at - closed_at
    # where it goes: the closing frame waiting for inference and segmentation, the hand-off to the fit worker and
    # back (NaN for a fit that raised), the fit in its worker, publishing
    parts = {
        "to_fit": dispatched_at - closed_at,
        "handoff": (started_at - dispatched_at) + (fitted_at - finished_at),
        "fit": finished_at - started_at,
        "publish": published_at - fitted_at,
    }
    pct = lambda v, q: float(np.nanpercentile(v, q)) if np.isfinite(v).any() else None
    return {
        "seconds": elapsed,
        "settled_s": settled_s,
        "load_average": [start[1], end[1]],
        "frames_per_s_in": acquired / elapsed,
        "frames_per_s_inferred": inferred / elapsed,
        "dropped_fraction": dropped / max(acquired, 1),
        "windows_closed": closed,
        "windows_published": published,
        "windows_skipped": skipped,
        "publish_latency_ms_p50": pct(window_latency, 50),
        "publish_latency_ms_p99": pct(window_latency, 99),
        # what the printer sees: of the windows that closed, those whose result it had within the target
        "on_time_fraction": float((window_latency <= ON_TIME_MS).sum()) / max(closed, 1),
        **{f"{stage}_ms_p{q}": pct(part, q) for stage, part in parts.items() for q in (50, 99)},
        "inference_calls": metrics.registry.get_sample_value("meniscope_inference_latency_seconds_count"),
        "refine": settings.refine,
        "windows_refined": len(lane),
        "refined_per_minute": len(lane) / elapsed * 60,
        "refine_skipped": lane_skipped,
        "refine_latency_s_p50": pct(refine_latency, 50),
        "refine_latency_s_p90": pct(refine_latency, 90),
        "refine_wall_s_p50": pct(refine_cpu, 50),  # taken by the lane's process -> refined: its share of the cores
    }


def stage_costs(recording: Path, configs: list[tuple[int, int]], frames: int = 3 * 19000) -> dict:
    """CPU microseconds per frame of each stage (one thread at a time), and the fit's milliseconds per window: the
    pipeline's own stages (:class:`FrameStages`, the segmenter, :func:`job_for`, :func:`fit_job`) called in turn."""
    from service import DEFAULT_MODELS, DEFAULT_SCENE
    from service.inverse.network import NetworkMethod
    from service.inverse.window_model import FILE as WINDOW_MODEL
    from service.inverse.window_model import WindowModel
    from service.pipeline.runtime import segmenter_for
    from service.pipeline.stages import FrameStages
    from service.pipeline.windows import fit_job, job_for
    from service.scene import Scene
    from service.sources import FrameBatch, open_source

    def cpu_us_per_frame(work, count: int = frames) -> tuple[float, list]:  # type: ignore[no-untyped-def]
        t0, t0_process = time.thread_time(), time.process_time()
        out = work()
        own, process = time.thread_time() - t0, time.process_time() - t0_process
        return max(own, process) / count * 1e6, out  # onnxruntime's own threads count through process time

    with open_source(replay_uri(recording, speed="max", loop=1)) as source:
        fps, stream = source.fps, source.format
        read_us, reads = cpu_us_per_frame(lambda: [source.read(128) for _ in range(frames // 128)])
    costs: dict = {"read_128": read_us}
    batch = FrameBatch.concatenate(reads)
    scene = Scene.load(DEFAULT_SCENE)
    stages = None
    for size_, threads in configs:
        method = NetworkMethod(DEFAULT_MODELS, scene, threads=threads, batch=size_)
        stages = FrameStages(scene, stream, str(recording), method)
        method.infer(batch.pixels[:size_])
        costs[f"infer_{size_}x{threads}"], _ = cpu_us_per_frame(lambda: method.infer(batch.pixels), len(batch))
    parts = [batch.select(slice(lo, lo + 512)) for lo in range(0, len(batch), 512)]
    costs["measures"], measured = cpu_us_per_frame(lambda: [stages.measure(part) for part in parts], len(batch))
    records = [stages.infer(inputs, m) for m, inputs in measured]
    segmenter = segmenter_for(ServiceSettings(), fps)
    costs["segmentation"], closed = cpu_us_per_frame(
        lambda: [
            w
            for part, r in zip(parts, records)
            for w in segmenter.push(part.indices, r, r["change"], np.zeros(len(part)), novelty=r["novelty"])
        ],
        len(batch),
    )
    settings = FitSettings()
    skip = settings.transient_frames(fps)
    jobs = [job_for(c.window, c.values, scene.nozzle.radius_mm, skip) for c in closed]
    if (DEFAULT_MODELS / WINDOW_MODEL).is_file():  # making a job with the window model (issue 17), all of it
        model = WindowModel.of_folder(DEFAULT_MODELS)
        job_us, _ = cpu_us_per_frame(
            lambda: [job_for(c.window, c.values, scene.nozzle.radius_mm, skip, model=model) for c in closed],
            len(closed),
        )
        costs["job_with_window_model_ms_per_window"] = job_us / 1e3
    fit_us, _ = cpu_us_per_frame(lambda: [fit_job(job, fps, settings) for job in jobs], len(jobs))
    costs["fit_ms_per_window"] = fit_us / 1e3
    costs["fit_per_frame_at_100_hz"] = fit_us * 100 / fps
    costs["windows_fitted"] = len(closed)
    return costs


def parse_variants(text: str) -> list[tuple[str, dict[str, str]]]:
    """ "batch_ms=1000,read_frames=128;batch_ms=2" -> [(its text, {key: value}), ...]; "" -> one variant of no
    changes. The values stay text: the settings parse them."""
    variants = []
    for group in text.split(";"):
        pairs = [item.strip() for item in group.split(",") if item.strip()]
        if any("=" not in item for item in pairs):
            raise MeniscopeError(
                "--variants", f"expected KEY=VALUE pairs like batch_ms=2,read_frames=64, got {group!r}"
            )
        variants.append((",".join(pairs), dict(item.split("=", 1) for item in pairs)))
    return variants


def _fmt(x: float | None, spec: str = ".0f") -> str:
    return "-" if x is None else format(x, spec)


def markdown(results: dict) -> str:
    lines = [
        f"Serve benchmark: {results['source']}, {results['seconds']:g} s per run, fit workers {results['fit_workers']} "
        f"at nice {results['fit_nice']}, "
        f"{os.cpu_count()} CPUs.",
        "",
        "| batch x threads | variant | lane | speed | fit modes | frames/s in | frames/s inferred | dropped | windows closed / published / unfitted "
        f"| publish latency p50 / p99 (ms) | closed windows published within {ON_TIME_MS:g} ms | of which: to the fit / hand-off / fit / publishing, p50 (p99) "
        "| load average |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results["runs"]:
        lines.append(
            f"| {r['batch']} x {r['threads']} | {r.get('variant') or 'defaults'} | {'on' if r.get('refine') else 'off'} "
            f"| {r['run']} | {r.get('max_modes', 2)} | {_fmt(r['frames_per_s_in'])} | "
            f"{_fmt(r['frames_per_s_inferred'])} | {r['dropped_fraction']:.1%} | {r['windows_closed']} / "
            f"{r['windows_published']} / {r['windows_skipped']} | {_fmt(r['publish_latency_ms_p50'], '.1f')} / "
            f"{_fmt(r['publish_latency_ms_p99'], '.1f')} | {r['on_time_fraction']:.1%} | "
            + " / ".join(
                f"{_fmt(r[f'{k}_ms_p50'], '.1f')} ({_fmt(r[f'{k}_ms_p99'], '.1f')})"
                for k in ("to_fit", "handoff", "fit", "publish")
            )
            + f" | {r['load_average'][0]:.1f} -> {r['load_average'][1]:.1f} |"
        )
    lanes = [r for r in results["runs"] if r.get("refine")]
    if lanes:
        lines += [
            "",
            "The refinement lane (serve --refine; latency: closing frame read -> refined update published):",
            "",
            "| batch x threads | variant | speed | refined | per minute | skipped | latency p50 / p90 (s) "
            "| in the lane's process p50 (s) |",
            "|---|---|---|---|---|---|---|---|",
        ]
        lines += [
            f"| {r['batch']} x {r['threads']} | {r.get('variant') or 'defaults'} | {r['run']} | {r['windows_refined']} "
            f"| {r['refined_per_minute']:.1f} | {r['refine_skipped']:.0f} | {_fmt(r['refine_latency_s_p50'], '.1f')} / "
            f"{_fmt(r['refine_latency_s_p90'], '.1f')} | {_fmt(r['refine_wall_s_p50'], '.1f')} |"
            for r in lanes
        ]
    c = results["stage_costs"]
    lines += [
        "",
        f"CPU per frame, each stage alone on one thread ({c['windows_fitted']} windows fitted):",
        "",
        "| stage | CPU us/frame |",
        "|---|---|",
    ]
    lines += [
        f"| {name} | {value:.1f} |" for name, value in c.items() if name not in ("windows_fitted", "fit_ms_per_window")
    ]
    lines += [
        "",
        f"The fit: {c['fit_ms_per_window']:.1f} ms CPU per window (mean); at 19,000 frames/s "
        f"two cores give {2e6 / 19000:.0f} us per frame in all.",
    ]
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> int:
    from service.pipeline.demo import demo_recording

    configs = parse_pairs(args.configs, "--configs", "BATCHxTHREADS like 512x1")
    try:
        speeds = [float(v) for v in args.speeds.split(",")]
    except ValueError:
        raise MeniscopeError("--speeds", f"expected numbers like 1,0.5, got {args.speeds!r}") from None
    try:
        max_modes = [int(v) for v in args.max_modes.split(",")]
        [FitSettings(max_modes=m) for m in max_modes]
    except ValueError:
        raise MeniscopeError("--max-modes", f"expected orders 0 to 2 like 1,2, got {args.max_modes!r}") from None
    variants = parse_variants(args.variants)
    recording = (args.source or demo_recording(default_data_dir())).resolve()
    if not recording.is_file():
        raise MeniscopeError(recording, "no such recording")
    with open_recording(recording) as rec:
        fps = rec.fps
    args.out.mkdir(parents=True, exist_ok=True)
    results: dict = {
        "source": str(recording),
        "seconds": args.seconds,
        "fit_workers": args.fit_workers,
        "fit_nice": args.fit_nice,
        "runs": [],
    }
    for batch, threads in configs:
        lanes = (False, True) if args.refine else (False,)
        for speed, modes, (variant, overrides), lane in itertools.product(speeds, max_modes, variants, lanes):
            name = f"x{speed:g}"
            try:
                settings = ServiceSettings(
                    **{
                        "source": replay_uri(recording, speed=speed, loop=1),
                        "recordings_dir": recording.parent,
                        "batch": batch,
                        "threads": threads,
                        "fit": FitSettings(max_modes=modes),
                        "fit_workers": args.fit_workers,
                        "fit_nice": args.fit_nice,
                        "zmq_publish": None,
                        "refine": lane,
                        **overrides,
                    }
                )
            except ValidationError as exc:
                raise MeniscopeError("--variants", f"{variant!r}: {exc.errors()[0]['msg']}") from None
            print(
                f"bench serve: batch {batch} x {threads} threads, {variant or 'defaults'}, {name}, "
                f"up to {modes} modes{', refinement lane on' if lane else ''} ...",
                flush=True,
            )
            results["runs"].append(
                {
                    "batch": batch,
                    "threads": threads,
                    "variant": variant,
                    "run": name,
                    "max_modes": modes,
                    **measure(settings, args.seconds, fps * speed),
                }
            )
    results["stage_costs"] = stage_costs(recording, configs)
    write_results(args.out / "serve.json", results, markdown(results))
    return 0
