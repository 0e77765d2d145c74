"""Live segmentation: the ejection detector and the streaming segmenter cut a stream as the offline analysis would."""

from __future__ import annotations

import json

import numpy as np
import pytest

from service.analysis.segment import windows_between
from service.pipeline.demo import DEMO_AVI, DEMO_TRUTH
from service.pipeline.ejections import PERIOD_WAIT_S, EjectionDetector, novelty_lags
from service.pipeline.measures import PixelMeasures
from service.pipeline.segmenter import StreamingSegmenter
from service.recordings import open_recording

FPS = 19_000.0


def segment(
    segmenter: StreamingSegmenter,
    indices: np.ndarray,
    values: np.ndarray,
    change: np.ndarray,
    batch: int,
    novelty: np.ndarray | None = None,
) -> list:
    closed = []
    for lo in range(0, len(indices), batch):
        part = slice(lo, lo + batch)
        arrival = np.full(len(indices[part]), float(lo))
        closed += segmenter.push(
            indices[part], values[part], change[part], arrival, novelty=None if novelty is None else novelty[part]
        )
    return closed


def bursts(at: list[int], n: int, seed: int = 0) -> np.ndarray:
    """Frame change as a video gives it: noise about 8, and a 5-frame burst of 40-60 at each of ``at``."""
    rng = np.random.default_rng(seed)
    change = rng.normal(8.0, 0.5, n)
    for e in at:
        change[e : e + 5] += rng.uniform(40, 60, 5)
    return change


@pytest.mark.parametrize("batch", [1, 37, 128, 1000])
def test_the_demo_recording_is_cut_at_its_true_ejections_whatever_the_batching(batch: int) -> None:
    with open_recording(DEMO_AVI) as rec:
        frames = rec.read(0, len(rec))
    frames = np.concatenate([frames, frames])  # as the looping replay delivers them
    indices = np.arange(len(frames))
    truth = json.loads(DEMO_TRUTH.read_text())
    fps = truth["recording"]["fps"]
    measures = PixelMeasures(*novelty_lags(fps))
    parts = [measures.update(frames[i : i + batch], indices[i : i + batch]) for i in range(0, len(frames), batch)]
    change, novelty = (np.concatenate([part[k] for part in parts]) for k in (0, 3))
    seg = StreamingSegmenter(950, EjectionDetector(fps, refractory=95))
    closed = segment(seg, indices, indices.astype(float), change, batch, novelty)
    truth = truth["ejections"]
    expected = truth[1:] + [t + len(frames) // 2 for t in truth]
    # frame 0's ejection has no frame before it to differ from: cuts that early are not checked
    starts = [c.window.start for c in closed if c.window.starts_at_ejection and c.window.start >= 95]
    assert starts == expected[:-1]  # the last ejection opens the window still in progress
    for c in closed:  # every window holds its own frames' values, in order
        assert np.array_equal(c.values, np.arange(c.window.start, c.window.end))


def test_windows_match_the_offline_windows_between_the_same_ejections() -> None:
    ejections = [100, 290, 480, 700]
    seg = StreamingSegmenter(10_000, EjectionDetector(FPS))
    closed = segment(seg, np.arange(1000), np.zeros(1000), bursts(ejections, 1000), 64)
    offline = windows_between(ejections, 1000)
    assert [c.window for c in closed] == offline[:-1]  # the trailing window has not closed
    assert [c.window for c in seg.finish(0.0)] == offline[-1:]


def test_frames_wait_for_the_streams_period_then_only_for_the_detectors_look_ahead() -> None:
    detector = EjectionDetector(FPS)
    seg = StreamingSegmenter(10_000, detector)
    change = bursts([100, 290, 480, 700], 800)
    closed = segment(seg, np.arange(700 + detector.latency), np.zeros(800), change, 1)
    assert [c.window.end for c in closed] == [100, 290, 480]  # held until two intervals agreed on a period
    closed = seg.push(
        np.array([700 + detector.latency]), np.zeros(1), change[700 + detector.latency :][:1], np.zeros(1)
    )
    assert [c.window.end for c in closed] == [700]  # closed as soon as the look-ahead after the ejection is in
    assert detector.latency <= 12  # a few frames at 19,000 frames/s


def test_lost_frames_become_missing_samples_and_a_long_gap_cuts_the_window() -> None:
    seg = StreamingSegmenter(max_frames=100)
    idx = np.r_[0:20, 25:40]
    closed = seg.push(idx, idx.astype(float), np.zeros(idx.size), np.zeros(idx.size))
    assert closed == []
    (window,) = seg.push(np.array([40]), np.array([40.0]), np.zeros(1), np.array([1.0]), np.array([40]))
    assert (window.window.start, window.window.end, window.window.ends_at_ejection) == (0, 40, True)
    assert np.isnan(window.values[20:25]).all() and np.isfinite(np.delete(window.values, range(20, 25))).all()
    (cut,) = seg.push(np.array([500]), np.array([1.0]), np.zeros(1), np.array([2.0]))
    assert (cut.window.start, cut.window.end, cut.window.ends_at_ejection) == (40, 41, False)


def test_a_window_longer_than_the_limit_is_cut_and_memory_stays_bounded() -> None:
    seg = StreamingSegmenter(max_frames=100, detector=EjectionDetector(FPS))
    n = int(PERIOD_WAIT_S * FPS) + 150  # the stream's first frames wait for its period, at most PERIOD_WAIT_S
    closed = segment(seg, np.arange(n), np.zeros(n), np.zeros(n), 64)
    assert [(c.window.start, c.window.end) for c in closed] == [(k, k + 100) for k in range(0, n - 100, 100)]
    assert not any(c.window.ends_at_ejection or c.window.starts_at_ejection for c in closed)


def test_bursts_within_the_refractory_time_are_one_ejection() -> None:
    change = bursts([50, 60, 70, 200], 300)
    seg = StreamingSegmenter(10_000, EjectionDetector(FPS, refractory=100))
    closed = segment(seg, np.arange(300), np.zeros(300), change, 300) + seg.finish(0.0)
    assert [(c.window.start, c.window.end) for c in closed] == [(0, 50), (50, 200), (200, 300)]
