"""The live pipeline (service.pipeline.runtime) between a source and the publishers: what each published
window says about where it came from, and a camera larger than the scene's region of interest."""

from __future__ import annotations

import asyncio
import gc
import math
import shutil
import threading
import weakref
from pathlib import Path

import numpy as np
import pytest

from service import DEFAULT_MODELS
from service.analysis.results import FitSettings
from service.errors import MeniscopeError
from service.inverse.base import InverseMethod, InverseOutput
from service.inverse.network import NetworkMethod
from service.pipeline.demo import DEMO_AVI
from service.pipeline.fitting import OnFitted
from service.pipeline.runtime import BatchBudget, FittedWindow, Pipeline, PipelineStats, TraceSnippet
from service.pipeline.supervisor import Health
from service.pipeline.windows import WindowJob, fit_job
from service.recordings import open_recording, open_writer
from service.scene import Scene
from service.server.history import History
from service.server.hub import Hub
from service.server.metrics import Metrics
from service.server.publishers import Publishers
from service.server.settings import ServiceSettings
from service.sources import FrameBatch, ReplaySource, open_source


class HeldFits:
    """Fit workers that keep every window until :meth:`release`, as slow ones do: its fit comes back later."""

    def __init__(self, settings: FitSettings) -> None:
        self.settings = settings
        self.held: list[tuple[WindowJob, float, OnFitted]] = []

    def submit(self, closed: WindowJob, fps: float, on_fitted: OnFitted) -> bool:
        self.held.append((closed, fps, on_fitted))
        return True

    def release(self) -> None:
        for closed, fps, on_fitted in self.held:
            on_fitted(closed, fit_job(closed, fps, self.settings), math.nan, math.nan)
        self.held.clear()


@pytest.fixture()
def publishers(tmp_path: Path) -> Publishers:
    """The service's publishers on a history database of their own (no ZeroMQ, no WebSocket client)."""
    history = History(tmp_path / "history.sqlite", 1.0, 1000)
    metrics = Metrics(PipelineStats(), lambda: Health("running", None, 0.0, 0), lambda: (0, 0))
    loop = asyncio.new_event_loop()
    publishers = Publishers(history, metrics, None, Hub(loop, 1)).start()
    yield publishers
    publishers.stop()
    history.close()
    loop.close()


def test_windows_fitted_after_the_source_changed_name_the_source_their_frames_came_from(
    tmp_path: Path, scene: Scene, publishers: Publishers
) -> None:
    method, fits = NetworkMethod(DEFAULT_MODELS, scene), HeldFits(FitSettings())
    uris, counts = [], []
    for name in ("first.avi", "second.avi"):  # the source changed between two runs, as PUT /api/v1/config does
        shutil.copy(DEMO_AVI, tmp_path / name)
        settings = ServiceSettings(
            source=f"file://{tmp_path / name}?speed=max", recordings_dir=tmp_path, data_dir=tmp_path
        )
        with open_source(settings.source) as source:
            assert Pipeline(settings, scene, source, method, fits, publishers, PipelineStats()).run(threading.Event())
        uris.append(settings.source)
        counts.append(len(fits.held) - sum(counts))
    assert counts[0] > 0 and counts[1] > 0
    fits.release()  # the first source's windows come back only now, after the second one ran
    publishers.stop()
    stored = publishers.history.latest()
    assert [w.source for w in stored] == [uris[0]] * counts[0] + [uris[1]] * counts[1]


class Collected:
    """A pipeline sink that keeps the windows and trace snippets it is handed."""

    def __init__(self) -> None:
        self.windows: list[FittedWindow] = []
        self.traces: list[TraceSnippet] = []

    def on_window(self, fitted: FittedWindow) -> None:
        self.windows.append(fitted)

    def on_trace(self, trace: TraceSnippet) -> None:
        self.traces.append(trace)

    def on_inference(self, seconds: float, frames: int) -> None:
        pass


class Watched(ReplaySource):
    """A replay that keeps a weak reference to each batch of whole frames it hands out and says when it has
    handed out ``enough``: which of them the pipeline still holds shows through the references."""

    def __init__(self, path: Path, enough: int) -> None:
        super().__init__(path, speed=0.0)
        self.handed_out: list[weakref.ref] = []
        self.enough, self.reached = enough, threading.Event()

    def _read(self, max_frames: int) -> FrameBatch | None:
        batch = super()._read(max_frames)
        if batch is not None and len(batch):
            self.handed_out.append(weakref.ref(batch.pixels))
            if len(self.handed_out) >= self.enough:
                self.reached.set()
        return batch


class Gate(InverseMethod):
    """An inverse method that records the frames it is given (D(0, t): their mean brightness, um). Its first
    call waits until the source has handed out enough batches, then counts how many of them, all but the
    last two (the acquisition thread may still be on those), are still in memory."""

    name = "gate"

    def __init__(self, source: Watched) -> None:
        self.source, self.frames, self.whole_frames_held = source, [], None

    def infer(self, frames: np.ndarray) -> InverseOutput:
        if self.whole_frames_held is None:
            assert self.source.reached.wait(30), "the source was not read while inference waited"
            gc.collect()
            self.whole_frames_held = sum(ref() is not None for ref in self.source.handed_out[:-2])
        self.frames.append(frames.copy())
        return InverseOutput(np.zeros((len(frames), 4)), frames.mean(axis=(1, 2)) * 1e-3)


def test_a_camera_larger_than_the_roi_has_only_its_roi_queued_inferred_and_shown(tmp_path: Path, scene: Scene) -> None:
    roi = scene.model_copy(update={"camera": scene.camera.model_copy(update={"roi": (24, 8)})})  # 96 x 96 at (24, 8)
    with open_recording(DEMO_AVI) as demo:
        inside = demo.read(0, len(demo))  # (N, 96, 96)
    sensor = np.random.default_rng(0).integers(0, 256, (len(inside), 112, 128), dtype=np.uint8)  # 128 x 112
    sensor[:, 8:104, 24:120] = inside
    with open_writer(tmp_path / "sensor.cine", 128, 112, demo.fps) as writer:
        writer.write(sensor)
    settings = ServiceSettings(read_frames=16, queue_batches=64)  # room for every read: nothing dropped
    stats = PipelineStats()
    with Watched(tmp_path / "sensor.cine", enough=8) as source:
        method = Gate(source)
        pipeline = Pipeline(settings, roi, source, method, HeldFits(settings.fit), Collected(), stats)
        assert pipeline.run(threading.Event())
    assert method.whole_frames_held == 0  # read 8 batches while the first was inferred: only their ROIs waited
    assert stats.frames_dropped == 0
    np.testing.assert_array_equal(np.concatenate(method.frames), inside)
    assert stats.latest.index == len(inside) - 1
    np.testing.assert_array_equal(stats.latest.pixels, inside[-1])  # the dashboard's latest frame: the ROI


def test_a_camera_smaller_than_the_roi_is_one_error_naming_the_source(tmp_path: Path, scene: Scene) -> None:
    with open_writer(tmp_path / "small.cine", 64, 64, 19000.0) as writer:
        writer.write(np.zeros((4, 64, 64), np.uint8))
    with Watched(tmp_path / "small.cine", enough=1) as source:
        with pytest.raises(MeniscopeError) as err:
            Pipeline(
                ServiceSettings(), scene, source, Gate(source), HeldFits(FitSettings()), Collected(), PipelineStats()
            )
    assert str(err.value) == f"{tmp_path / 'small.cine'}: scene ROI 96x96 at (0, 0) lies outside the 64x64 frame"


class Calls(InverseMethod):
    """An inverse method that keeps the frames of each call and infers nothing (zeros)."""

    name = "calls"

    def __init__(self) -> None:
        self.calls: list[np.ndarray] = []

    def infer(self, frames: np.ndarray) -> InverseOutput:
        self.calls.append(frames.copy())
        return InverseOutput(np.zeros((len(frames), 4)), np.zeros(len(frames)))


class Dispatched(HeldFits):
    """Fit workers that note, for each window handed to them, how many frames had been inferred by then."""

    def __init__(self, settings: FitSettings, stats: PipelineStats) -> None:
        super().__init__(settings)
        self.stats = stats
        self.inferred_at: list[int] = []

    def submit(self, closed: WindowJob, fps: float, on_fitted: OnFitted) -> bool:
        self.inferred_at.append(self.stats.frames_inferred)
        return super().submit(closed, fps, on_fitted)


def split_reads(recording: Path, scene: Scene, method: InverseMethod) -> tuple[PipelineStats, np.ndarray]:
    """The pipeline's stats over ``recording`` read 16 frames at a time and inferred by ``method`` in calls of at most
    5 (a budget no call of 5 frames comes near: calls join parts of reads and split others), and its frames."""
    settings = ServiceSettings(read_frames=16, batch=5, batch_ms=1000, queue_batches=1024)
    stats = PipelineStats()
    with open_source(f"file://{recording}?speed=max") as source:
        assert Pipeline(settings, scene, source, method, HeldFits(settings.fit), Collected(), stats).run(
            threading.Event()
        )
    with open_recording(recording) as demo:
        return stats, demo.read(0, len(demo))


def test_a_read_larger_than_the_inference_cap_is_split_across_calls_losing_and_repeating_no_frame(
    demo_cine: Path, scene: Scene
) -> None:
    method = Calls()
    stats, everything = split_reads(demo_cine, scene, method)
    assert max(len(c) for c in method.calls) == 5
    np.testing.assert_array_equal(np.concatenate(method.calls), everything)
    assert stats.frames_inferred == stats.frames_acquired == len(everything)


def test_a_window_goes_to_the_fit_with_at_most_one_call_of_frames_inferred_past_its_closing_frame(
    demo_cine: Path, scene: Scene
) -> None:
    # the queue holds the whole recording at once (read as fast as it reads): a cap by frames read would take it all
    settings = ServiceSettings(read_frames=128, batch=8, batch_ms=1000, queue_batches=1024)
    stats = PipelineStats()
    fits = Dispatched(settings.fit, stats)
    with open_source(f"file://{demo_cine}?speed=max") as source:
        pipeline = Pipeline(settings, scene, source, Calls(), fits, Collected(), stats)
        assert pipeline.run(threading.Event())
    latency = pipeline.segmenter.detector.latency  # frames after an ejection that decide it (its burst)
    closed_at_ejection = [
        (closed.window.end, at)
        for (closed, _, _), at in zip(fits.held, fits.inferred_at)
        if closed.window.ends_at_ejection
    ]
    # the demo's 4 windows: the first (its ejection, frame 0, unseen) is no window, the last ends with the file
    assert len(closed_at_ejection) >= 2
    # the stream's first windows wait for its period, two intervals between the ejections after its first frame
    # (190, 380, 570), and close once the third is found; then frame ``end + latency`` (the next ejection decided)
    known = sorted(end for end, _ in closed_at_ejection)[2]
    for end, inferred in closed_at_ejection:
        if end < known:
            assert known < inferred <= known + latency + 8
        else:
            assert end + latency + 1 <= inferred <= end + latency + 8


class Pooled(InverseMethod):
    """An inverse method whose input is each frame's mean (its :meth:`prepare`), noting the threads that prepare and
    the inputs each call infers."""

    name = "pooled"

    def __init__(self) -> None:
        self.prepared_on: set[str] = set()
        self.calls: list[np.ndarray] = []

    def prepare(self, frames: np.ndarray) -> np.ndarray:
        self.prepared_on.add(threading.current_thread().name)
        return frames.mean(axis=(1, 2))

    def infer_prepared(self, inputs: np.ndarray) -> InverseOutput:
        self.calls.append(inputs.copy())
        return InverseOutput(np.zeros((len(inputs), 4)), inputs * 1e-3)

    def infer(self, frames: np.ndarray) -> InverseOutput:
        return self.infer_prepared(self.prepare(frames))


def test_the_inverse_input_is_prepared_where_frames_are_read_and_inference_takes_only_it(
    demo_cine: Path, scene: Scene
) -> None:
    method = Pooled()
    stats, everything = split_reads(demo_cine, scene, method)
    assert method.prepared_on == {"meniscope-acquire"}
    np.testing.assert_array_equal(np.concatenate(method.calls), everything.mean(axis=(1, 2)))
    assert stats.latest.index == len(everything) - 1
    np.testing.assert_array_equal(stats.latest.pixels, everything[-1])


def test_the_inference_cap_is_the_frames_the_measured_cost_allows_within_the_budget() -> None:
    budget = BatchBudget(0.002, most=512, first=128, smoothing=0.5)
    assert budget.frames() == 128  # nothing measured yet: one read
    budget.record(0.010, 100)  # 100 us a frame: 20 frames in 2 ms
    assert budget.frames() == 20
    budget.record(0.030, 100)  # a slower call (a busy machine) halfway in: 200 us a frame
    assert budget.frames() == 10
    budget.record(10.0, 1)
    assert budget.frames() == 1  # never below one frame
    fast = BatchBudget(0.002, most=512, first=1024)
    assert fast.frames() == 512  # never above ``most``
    fast.record(1e-6, 1000)
    assert fast.frames() == 512


def test_a_window_whose_frames_show_no_highlight_is_unresolved_not_settled() -> None:
    """A dark or unlit camera's window would fit as a flat, settled meniscus; without a highlight nothing of the
    meniscus was seen, so it is unresolved and says why. A window with highlights is fitted as before."""
    from service.analysis.segment import Window

    flat = np.zeros(190)
    unseen = fit_job(WindowJob(Window(0, 0, 190, True, True), flat, flat, highlight=0.03), 19000.0, FitSettings())
    assert unseen.status == "unresolved" and "no highlight" in unseen.reason and not unseen.modes
    seen = fit_job(WindowJob(Window(0, 0, 190, True, True), flat, flat, highlight=0.9), 19000.0, FitSettings())
    assert seen.status == "settled"
