"""One pipeline behind every front door: the live pipeline and ``meniscope analyze`` make the same windows of the
same recording, field for field, and a live start publishes no fragment of a window as a failure."""

from __future__ import annotations

import math
import threading
from pathlib import Path

import numpy as np
import pytest

from service import DEFAULT_MODELS, DEFAULT_SCENE
from service.analysis.offline import analyse_recording
from service.analysis.results import FitSettings
from service.inverse.network import NetworkMethod
from service.inverse.window_model import FILE as WINDOW_MODEL
from service.pipeline.fitting import OnFitted
from service.pipeline.runtime import FittedWindow, Pipeline, PipelineStats
from service.pipeline.windows import WindowJob, fit_job
from service.scene import Scene
from service.server.settings import ServiceSettings
from service.sources import open_source


class InProcessFits:
    """Fit workers that fit each window at once in this process, with the function the workers run."""

    def __init__(self, settings: FitSettings) -> None:
        self.settings = settings

    def submit(self, job: WindowJob, fps: float, on_fitted: OnFitted) -> bool:
        on_fitted(job, fit_job(job, fps, self.settings), math.nan, math.nan)
        return True


class Published:
    """A sink that keeps the fitted windows."""

    def __init__(self) -> None:
        self.windows: list[FittedWindow] = []

    def on_window(self, fitted: FittedWindow) -> None:
        self.windows.append(fitted)

    def on_trace(self, trace: object) -> None:
        pass

    def on_inference(self, seconds: float, frames: int) -> None:
        pass


@pytest.fixture(scope="module", params=["steady", "window"])
def live_and_offline(request: pytest.FixtureRequest, demo_cine: Path) -> tuple[list[FittedWindow], object]:
    """Both front doors on one recording, fitting each window's steady series or the window model's (issue 17)."""
    if request.param == "window" and not (DEFAULT_MODELS / WINDOW_MODEL).is_file():
        pytest.skip(f"no {WINDOW_MODEL} in {DEFAULT_MODELS}")
    scene = Scene.load(DEFAULT_SCENE)
    # odd reads; room for every one: none dropped
    settings = ServiceSettings(read_frames=37, queue_batches=1024, fit=FitSettings(series_model=request.param))
    method = NetworkMethod(DEFAULT_MODELS, scene)
    published, stats = Published(), PipelineStats()
    with open_source(f"file://{demo_cine}?speed=max") as source:
        assert Pipeline(settings, scene, source, method, InProcessFits(settings.fit), published, stats).run(
            threading.Event()
        )
    assert stats.frames_dropped == 0
    offline = analyse_recording(
        demo_cine,
        scene,
        "network",
        DEFAULT_MODELS,
        settings=settings.fit,
        progress=False,
        opened=(method, None),
        workers=1,
    )
    return published.windows, offline


def test_every_live_window_is_the_offline_window_of_the_same_frames_in_every_field(live_and_offline) -> None:
    live, offline = live_and_offline
    by_frames = {(w.start_frame, w.end_frame): w for w in offline.report.windows}
    assert len(live) >= 3
    for fitted in live:
        result = fitted.result
        twin = by_frames.get((result.start_frame, result.end_frame))
        assert twin is not None, f"offline has no window {result.start_frame}..{result.end_frame}"
        assert result.model_dump() == twin.model_dump()  # every field: index, bounds, status, modes, settling, ...
        np.testing.assert_array_equal(fitted.values, offline.fitted[result.start_frame : result.end_frame])


def test_a_live_start_publishes_no_failed_fragment_before_the_first_ejection(live_and_offline) -> None:
    live, offline = live_and_offline
    assert all(f.result.status != "failed" for f in live)
    assert all(f.result.starts_at_ejection for f in live)  # the frames before the first ejection are no window
    first = min(f.result.start_frame for f in live)
    assert [w.index for w in offline.report.windows if w.start_frame == first] == [
        min(f.result.index for f in live)
    ]  # the dropped fragment keeps its index: live counts as offline does


def test_an_analysis_opens_its_recording_once(demo_cine: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Opening a .cine reads every image's offset, ~1 us of CPU per frame: ``analyze`` opens it once and replays
    that; its digest, the file's XXH3-128, is hashed from that opening's mapping of the file, not a second one."""
    from xxhash import xxh3_128

    from service.analysis import offline
    from service.recordings import cine

    opened: list[Path] = []
    original = cine.CineRecording.__init__

    def counted(self: cine.CineRecording, path: Path, *args: object, **kwargs: object) -> None:
        opened.append(Path(path))
        original(self, path, *args, **kwargs)

    monkeypatch.setattr(cine.CineRecording, "__init__", counted)
    hashed: list[bool] = []
    digest = offline.xxh3_file

    def from_mapping(path: Path, mapped: np.ndarray | None = None) -> str:
        hashed.append(mapped is not None)
        return digest(path, mapped)

    monkeypatch.setattr(offline, "xxh3_file", from_mapping)
    scene = Scene.load(DEFAULT_SCENE)
    analysis = analyse_recording(
        demo_cine, scene, "network", DEFAULT_MODELS, progress=False, opened=(NetworkMethod(DEFAULT_MODELS, scene), None)
    )
    assert analysis.report.windows and opened == [demo_cine]
    assert hashed == [True] and analysis.report.source.xxh3_128 == xxh3_128(demo_cine.read_bytes()).hexdigest()


def test_an_analysis_lets_go_of_its_recording_on_the_hash_thread(
    demo_cine: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The recording's mapping is released on the hash's thread once the frames are read and the hash is done, not
    by the caller as it returns (unmapping a 701 MB recording cost ~12 ms of a ~1 s analysis, a core idle beside
    it); the digest and windows as ever."""
    import weakref

    from xxhash import xxh3_128

    from service.recordings import cine

    released: list[str] = []
    original = cine.CineRecording.__init__

    def tracked(self: cine.CineRecording, path: Path, *args: object, **kwargs: object) -> None:
        original(self, path, *args, **kwargs)
        weakref.finalize(self.mapped, lambda: released.append(threading.current_thread().name))

    monkeypatch.setattr(cine.CineRecording, "__init__", tracked)
    scene = Scene.load(DEFAULT_SCENE)
    analysis = analyse_recording(
        demo_cine, scene, "network", DEFAULT_MODELS, progress=False, opened=(NetworkMethod(DEFAULT_MODELS, scene), None)
    )
    assert analysis.report.windows and analysis.report.source.xxh3_128 == xxh3_128(demo_cine.read_bytes()).hexdigest()
    assert len(released) == 1 and released[0].startswith("meniscope-hash")
