"""The live pipeline (service.pipeline.runtime) between a source and the publishers: what each published
window says about where it came from."""
from __future__ import annotations

import asyncio
import shutil
import threading
from pathlib import Path

import pytest

from service import DEFAULT_MODELS
from service.analysis.results import FitSettings
from service.inverse.network import NetworkMethod
from service.pipeline.demo import DEMO_AVI
from service.pipeline.fitting import OnFitted, fit_one
from service.pipeline.runtime import Pipeline, PipelineStats
from service.pipeline.segmenter import ClosedWindow
from service.pipeline.supervisor import Health
from service.scene import Scene
from service.server.history import History
from service.server.hub import Hub
from service.server.metrics import Metrics
from service.server.publishers import Publishers
from service.settings import ServiceSettings
from service.sources import open_source


class HeldFits:
    """Fit workers that keep every window until :meth:`release`, as slow ones do: its fit comes back later."""

    def __init__(self, settings: FitSettings) -> None:
        self.settings = settings
        self.held: list[tuple[ClosedWindow, float, OnFitted]] = []

    def submit(self, closed: ClosedWindow, fps: float, on_fitted: OnFitted) -> bool:
        self.held.append((closed, fps, on_fitted))
        return True

    def release(self) -> None:
        for closed, fps, on_fitted in self.held:
            on_fitted(closed, fit_one(closed.window, closed.values, fps, self.settings))
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
        tmp_path: Path, scene: Scene, publishers: Publishers) -> None:
    method, fits = NetworkMethod(DEFAULT_MODELS, scene), HeldFits(FitSettings())
    uris, counts = [], []
    for name in ("first.avi", "second.avi"):  # the source changed between two runs, as PUT /api/v1/config does
        shutil.copy(DEMO_AVI, tmp_path / name)
        settings = ServiceSettings(source=f"file://{tmp_path / name}?speed=max", recordings_dir=tmp_path,
                                   data_dir=tmp_path)
        with open_source(settings.source) as source:
            assert Pipeline(settings, scene, source, method, fits, publishers, PipelineStats()).run(threading.Event())
        uris.append(settings.source)
        counts.append(len(fits.held) - sum(counts))
    assert counts[0] > 0 and counts[1] > 0
    fits.release()  # the first source's windows come back only now, after the second one ran
    publishers.stop()
    stored = publishers.history.latest()
    assert [w.source for w in stored] == [uris[0]] * counts[0] + [uris[1]] * counts[1]
