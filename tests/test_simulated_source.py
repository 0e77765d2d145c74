"""``sim://``: a camera rendered live from the physics model, with ground truth.

Its frames are the truth it reports, rendered and through the camera; ejections fall every period as
in a simulated recording; the seed fixes every frame however the stream is read; pacing follows the
scene's frame rate times ``speed`` (checked on a simulated clock). What every source does is checked
in tests/test_sources_conformance.py.
"""

from __future__ import annotations

import numpy as np

from service.camera_effects import noise_preset
from service.render import Renderer
from service.scene import Scene
from service.simulate import ejection_frames
from service.sources import FrameBatch, SimulatedSource, open_source
from service.validation.truth import truth_coefficients
from tests.clocks import SimulatedClock

FPS = 19000.0


def read_frames(source: SimulatedSource, frames: int, max_frames: int = 64) -> FrameBatch:
    """The next ``frames`` frames of an unpaced source, in reads of at most ``max_frames``."""
    batches, count = [], 0
    while count < frames:
        batch = source.read(min(max_frames, frames - count))
        assert batch is not None, "a simulated stream never ends"
        batches.append(batch)
        count += len(batch)
    return FrameBatch.concatenate(batches)


def test_frames_are_the_truth_it_reports_rendered_through_the_camera(scene: Scene) -> None:
    renderer, camera = Renderer(scene, supersample=1, sun_samples=4, threads=1), noise_preset("none", 12)
    with open_source("sim://?noise=none&seed=2&timeout=30") as source:
        for k in range(2):  # each window from its own ejection: the second one's time starts at frame 190
            frames = read_frames(source, 190, max_frames=190)
            info = source.describe()
            window = info["window"]
            assert (window["index"], window["start_frame"], window["end_frame"]) == (k, 190 * k, 190 * (k + 1))
            truth = {
                "recording": {"fps": info["fps"], "frames": window["end_frame"]},
                "transient": {"frames": info["transient_frames"]},
                "windows": [window],
            }
            coeffs = truth_coefficients(truth)[window["start_frame"] :]
            np.testing.assert_array_equal(frames.indices, np.arange(190 * k, 190 * (k + 1)))
            np.testing.assert_allclose(frames.timestamps, frames.indices / FPS, rtol=0, atol=1e-12)
            expected = camera.apply(renderer.render(coeffs), np.random.default_rng())
            assert np.abs(frames.pixels.astype(np.int64) - expected).max() <= 1  # rounding of the same floats
            # the truth of the other window no longer fits: the check above can fail
            assert np.abs(frames.pixels.astype(np.int64) - np.roll(expected, 1, axis=0)).max() > 100


def test_ejections_fall_every_period_rounded_to_the_nearest_frame() -> None:
    hz = FPS / 63.5  # windows of 64 and 63 frames
    ejections = ejection_frames(5, FPS, hz)
    assert list(ejections) == [0, 64, 127, 191, 254, 318]
    starts, frames = [], []
    with open_source(f"sim://?noise=none&ejection_hz={hz!r}") as source:
        for _ in range(318):  # a frame at a time: the window each frame lies in
            frames.append(read_frames(source, 1).pixels[0].astype(np.float64))
            starts.append(source.describe()["window"]["start_frame"])
    assert starts == [int(ejections[np.searchsorted(ejections, i, side="right") - 1]) for i in range(318)]
    change = np.abs(np.diff(frames, axis=0)).mean(axis=(1, 2))  # change[i]: frame i -> i + 1
    for start, end in zip(ejections[1:-1], ejections[2:]):  # each ejection stands out in the video
        assert change[start - 1 : start + 4].max() > 2 * change[start + 20 : end - 1].max()


def test_the_same_seed_gives_the_same_frames_however_they_are_read() -> None:
    with open_source("sim://?seed=5") as a, open_source("sim://?seed=5") as b, open_source("sim://?seed=6") as c:
        first = read_frames(a, 300, max_frames=7)
        np.testing.assert_array_equal(read_frames(b, 300, max_frames=100).pixels, first.pixels)
        assert not np.array_equal(read_frames(c, 300).pixels, first.pixels)


def test_reopening_starts_the_same_stream_again() -> None:
    with open_source("sim://?seed=5") as source:
        first = read_frames(source, 40)
        read_frames(source, 200)
        source.close()
        source.open()
        again = read_frames(source, 40)
    np.testing.assert_array_equal(again.indices, first.indices)
    np.testing.assert_array_equal(again.pixels, first.pixels)


def test_a_sensor_larger_than_the_roi_is_black_around_it(scene: Scene, tmp_path) -> None:  # type: ignore[no-untyped-def]
    shifted = tmp_path / "roi.json"
    shifted.write_text(
        scene.model_copy(update={"camera": scene.camera.model_copy(update={"roi": (24, 8)})}).model_dump_json()
    )
    with (
        open_source(f"sim://?noise=none&seed=2&scene={shifted}") as wide,
        open_source("sim://?noise=none&seed=2") as roi,
    ):
        assert (wide.width, wide.height) == (120, 104)
        sensor, inside = read_frames(wide, 40).pixels, read_frames(roi, 40).pixels
    np.testing.assert_array_equal(sensor[:, 8:, 24:], inside)
    assert not sensor[:, :8].any() and not sensor[:, :, :24].any()


def test_unpaced_it_never_waits_and_paced_it_keeps_speed_times_the_frame_rate() -> None:
    clock = SimulatedClock()
    with SimulatedSource(clock=clock, sleep=clock.sleep) as unpaced:
        assert len(unpaced.read(200)) == 200 and clock.sleeps == []  # type: ignore[arg-type]
    clock = SimulatedClock()
    with SimulatedSource(speed=0.01, clock=clock, sleep=clock.sleep) as paced:  # 190 frames/s of the clock
        start, frames = clock.now, []
        while sum(map(len, frames)) < 190:
            batch = paced.read(64)
            assert batch is not None and (not len(batch) or batch.timestamps[-1] <= (clock.now - start) * 0.01 + 1e-12)
            frames.append(batch)
    assert max(clock.sleeps) <= paced.timeout
    # frame 189 fell due 189 / 190 s after the stream started, and was read within one timeout of that
    assert 189 / 190 - 1e-9 <= clock.now - start <= 189 / 190 + paced.timeout


def test_a_read_returns_with_what_rendered_by_its_timeout() -> None:
    with open_source("sim://?timeout=0.05") as source:
        batch = source.read(4096)  # far more than renders in 50 ms
    assert batch is not None and 0 < len(batch) < 4096
