"""Every camera adapter keeps the FrameSource contract: one suite of mixin classes, one test class per adapter.

In the manner of pims's tests/test_common.py: ``SourceContract`` holds what every source does; a
class that also inherits ``FiniteContract`` replays a stream that ends, ``EndlessContract`` one that
runs on like a camera, ``GapContract`` one that loses frames on the way. Each adapter's class gives
the ``source`` fixture (an open source) and runs against the real thing: recordings on disk,
ZeroMQ sockets on 127.0.0.1, Aravis's fake GigE Vision camera over loopback, a V4L2 device if any.
"""

from __future__ import annotations

import glob
import json
import shutil
import socket
import subprocess
import threading
import time
import types
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

import service.sources as sources
from service.errors import MeniscopeError
from service.recordings import open_recording, open_writer
from service.scene import Scene
from service.sources import FrameBatch, FrameSender, FrameSource, SourceStats, open_source

CINE_FRAMES, AVI_FRAMES = 120, 60


def collect(source: FrameSource, frames: int, max_frames: int = 16, patience_s: float = 20.0) -> list[FrameBatch]:
    """Batches read until ``frames`` frames arrived or the stream ended; fails if that takes over ``patience_s``."""
    batches, count = [], 0
    deadline = time.monotonic() + patience_s
    while count < frames:
        batch = source.read(max_frames)
        if batch is None:
            break
        batches.append(batch)
        count += len(batch)
        assert time.monotonic() < deadline, f"{source.uri}: only {count} of {frames} frames in {patience_s} s"
    return batches


class SourceContract:
    """What every adapter does, whatever is behind it."""

    #: frames each test reads (cameras deliver slowly, files at once)
    sample_frames = 40

    def test_batches_have_the_declared_size_type_and_range(self, source: FrameSource) -> None:
        for batch in collect(source, self.sample_frames, max_frames=7):
            assert len(batch) <= 7
            assert batch.pixels.shape[1:] == (source.height, source.width)
            assert batch.pixels.dtype == source.dtype
            assert not len(batch) or int(batch.pixels.max()) < 2**source.bit_depth

    def test_format_is_plausible(self, source: FrameSource) -> None:
        assert source.dtype in (np.uint8, np.uint16)
        assert 1 <= source.bit_depth <= 8 * source.dtype.itemsize
        assert source.fps > 0 and source.width > 0 and source.height > 0

    def test_indices_and_timestamps_increase_across_batches(self, source: FrameSource) -> None:
        frames = FrameBatch.concatenate(collect(source, self.sample_frames))
        assert len(frames) >= self.sample_frames
        assert np.all(np.diff(frames.indices) >= 1)
        assert np.all(np.diff(frames.timestamps) > 0)
        assert np.isfinite(frames.timestamps).all()

    def test_stats_agree_with_the_delivered_indices(self, source: FrameSource) -> None:
        indices = FrameBatch.concatenate(collect(source, self.sample_frames)).indices
        steps = np.diff(indices)
        assert source.stats == SourceStats(
            frames=len(indices), gaps=int((steps > 1).sum()), dropped=int((steps - 1).sum())
        )

    def test_describe_is_json_safe_and_names_the_stream(self, source: FrameSource) -> None:
        collect(source, 1)
        info = json.loads(json.dumps(source.describe(), allow_nan=False))
        assert info["uri"] == source.uri and info["kind"] == source.kind and info["open"] is True
        assert (info["width"], info["height"], info["dtype"]) == (source.width, source.height, source.dtype.name)
        assert info["stats"]["frames"] == source.stats.frames

    def test_close_is_idempotent_and_stops_reading(self, source: FrameSource) -> None:
        source.close()
        source.close()
        assert not source.is_open and source.describe()["open"] is False
        with pytest.raises(MeniscopeError, match="not open"):
            source.read()

    def test_read_refuses_a_batch_of_no_frames(self, source: FrameSource) -> None:
        with pytest.raises(ValueError, match="max_frames"):
            source.read(0)


class FiniteContract(SourceContract):
    """A stream that ends: every frame once, in order, then None for good."""

    frames_in_stream: int

    def test_delivers_every_frame_once_then_ends(self, source: FrameSource) -> None:
        frames = FrameBatch.concatenate(collect(source, self.frames_in_stream + 1, max_frames=25))
        np.testing.assert_array_equal(frames.indices, np.arange(self.frames_in_stream))
        assert source.read() is None and source.read() is None
        assert source.stats == SourceStats(frames=self.frames_in_stream)


class EndlessContract(SourceContract):
    """A stream that runs on like a camera: reads keep delivering well past any first batch."""

    def test_keeps_delivering(self, source: FrameSource) -> None:
        frames = FrameBatch.concatenate(collect(source, 3 * self.sample_frames, max_frames=self.sample_frames))
        assert len(frames) >= 3 * self.sample_frames


class GapContract:
    """A stream that loses frames on the way: the losses show as index jumps and are counted."""

    def test_lost_frames_are_counted_as_gaps(self, source: FrameSource) -> None:
        indices: list[np.ndarray] = []
        deadline = time.monotonic() + 20
        while source.stats.gaps == 0 and time.monotonic() < deadline:
            batch = source.read(16)
            assert batch is not None, "the stream ended before losing a frame"
            indices.append(batch.indices)
        steps = np.diff(np.concatenate(indices))
        assert source.stats.gaps == (steps > 1).sum() >= 1
        assert source.stats.dropped == (steps - 1).sum() >= source.stats.gaps


# --- recordings on disk ------------------------------------------------------------------------------


def counting_frames(n: int, height: int, width: int, bits: int) -> np.ndarray:
    """Frames whose words encode their index and position, so a misplaced frame cannot pass unnoticed."""
    k, y, x = np.ogrid[:n, :height, :width]
    return ((k * 37 + y * width + x) % 2**bits).astype(np.uint8 if bits == 8 else np.uint16)


@pytest.fixture(scope="module")
def cine(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 12-bit .cine of 120 frames, 40 x 32 px, at the camera's 19,000 frames/s."""
    path = tmp_path_factory.mktemp("rec") / "counting.cine"
    with open_writer(path, 40, 32, 19000.0, bit_depth=12) as writer:
        writer.write(counting_frames(CINE_FRAMES, 32, 40, 12))
    return path


@pytest.fixture(scope="module")
def avi(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An 8-bit .avi of 60 frames, 40 x 32 px, at 1,000 frames/s."""
    path = tmp_path_factory.mktemp("rec") / "counting.avi"
    with open_writer(path, 40, 32, 1000.0, bit_depth=8) as writer:
        writer.write(counting_frames(AVI_FRAMES, 32, 40, 8))
    return path


class TestReplayCine(FiniteContract):
    frames_in_stream = CINE_FRAMES

    @pytest.fixture
    def source(self, cine: Path) -> Iterator[FrameSource]:
        with open_source(cine.as_uri()) as source:  # paced at the recorded rate: 6 ms in all
            yield source

    def test_delivers_the_recorded_words_and_times(self, source: FrameSource, cine: Path) -> None:
        frames = FrameBatch.concatenate(collect(source, CINE_FRAMES))
        with open_recording(cine) as rec:
            np.testing.assert_array_equal(frames.pixels, rec.read(0, CINE_FRAMES))
            np.testing.assert_array_equal(frames.timestamps, rec.timestamps)
            assert (source.fps, source.bit_depth) == (rec.fps, 12)

    def test_reopening_starts_a_new_stream(self, source: FrameSource) -> None:
        collect(source, 30)
        source.close()
        with source:
            assert source.stats == SourceStats()
            assert source.read(5).indices[0] == 0  # type: ignore[union-attr]


class TestReplayAvi(FiniteContract):
    frames_in_stream = AVI_FRAMES

    @pytest.fixture
    def source(self, avi: Path) -> Iterator[FrameSource]:
        with open_source(str(avi), speed="max") as source:
            yield source

    def test_delivers_the_recorded_words(self, source: FrameSource) -> None:
        frames = FrameBatch.concatenate(collect(source, AVI_FRAMES))
        np.testing.assert_array_equal(frames.pixels, counting_frames(AVI_FRAMES, 32, 40, 8))


class TestReplayLoop(EndlessContract):
    sample_frames = CINE_FRAMES

    @pytest.fixture
    def source(self, cine: Path) -> Iterator[FrameSource]:
        with open_source(f"{cine.as_uri()}?loop=true&speed=0") as source:
            yield source

    def test_passes_continue_indices_and_times(self, source: FrameSource) -> None:
        frames = FrameBatch.concatenate(collect(source, 3 * CINE_FRAMES, max_frames=60))
        np.testing.assert_array_equal(frames.indices, np.arange(3 * CINE_FRAMES))
        passes = frames.pixels.reshape(3, CINE_FRAMES, 32, 40)
        np.testing.assert_array_equal(passes[1], passes[0])
        np.testing.assert_array_equal(passes[2], passes[0])
        # one frame period everywhere, the seams between passes included (.cine stores times to 2**-32 s)
        np.testing.assert_allclose(np.diff(frames.timestamps), 1 / 19000.0, rtol=0, atol=1e-9)


# --- ZeroMQ over loopback -----------------------------------------------------------------------------


@contextmanager
def zmq_stream(recording: Path, keep: Callable[[np.ndarray], np.ndarray] = lambda i: i >= 0) -> Iterator[str]:
    """A thread publishing ``recording`` (the frames ``keep(indices)`` selects) on a free loopback port.

    Yields the ``zmq+tcp://`` URI; the sender waits for a subscriber, sends every batch, then ends
    the stream. Queues are deep enough that nothing is dropped on the way.
    """
    replay = open_source(str(recording), speed=0)
    sender = FrameSender("tcp://127.0.0.1:*", replay.format, hwm=100_000)

    def publish() -> None:
        try:
            if sender.wait_for_subscriber(10.0):
                while (batch := replay.read(32)) is not None:
                    sender.send(batch.select(keep(batch.indices)))
        finally:
            sender.close()
            replay.close()

    thread = threading.Thread(target=publish, daemon=True)
    thread.start()
    yield sender.endpoint.replace("tcp://", "zmq+tcp://")
    thread.join(15)


class TestZmq(FiniteContract):
    frames_in_stream = CINE_FRAMES

    @pytest.fixture
    def source(self, cine: Path) -> Iterator[FrameSource]:
        with zmq_stream(cine) as uri, open_source(uri, hwm=100_000) as source:
            yield source

    def test_delivers_the_sent_words_and_times(self, source: FrameSource, cine: Path) -> None:
        frames = FrameBatch.concatenate(collect(source, CINE_FRAMES))
        with open_recording(cine) as rec:
            np.testing.assert_array_equal(frames.pixels, rec.read(0, CINE_FRAMES))
            np.testing.assert_allclose(frames.timestamps, rec.timestamps, rtol=0, atol=1e-9)  # to the format's 1 ns
            assert (source.fps, source.bit_depth, source.dtype) == (rec.fps, rec.bit_depth, rec.dtype)


class TestZmqWithLostFrames(GapContract):
    @pytest.fixture
    def source(self, cine: Path) -> Iterator[FrameSource]:
        with zmq_stream(cine, keep=lambda i: (i < 50) | (i >= 57)) as uri, open_source(uri, hwm=100_000) as source:
            yield source

    def test_counts_exactly_the_frames_the_sender_skipped(self, source: FrameSource) -> None:
        collect(source, CINE_FRAMES)
        assert source.stats == SourceStats(frames=CINE_FRAMES - 7, gaps=1, dropped=7)


# --- Aravis's fake GigE Vision camera, over loopback ----------------------------------------------------

FAKE_CAMERA = "arv-fake-gv-camera-0.8"
#: GigE Vision's control port (UDP), which the fake camera must own on 127.0.0.1.
GVCP_PORT = 3956


def fake_camera_unavailable() -> str | None:
    """Why Aravis's fake camera cannot run here (what is missing, or who holds its port), or None when it can.

    Checked apart from the adapter, so that an adapter that fails where everything is in place is a failure.
    """
    if shutil.which(FAKE_CAMERA) is None:
        return f"{FAKE_CAMERA} not found: install the Debian package aravis-tools"
    try:
        import gi
    except ImportError:
        return "PyGObject is not installed: pip install 'meniscope[aravis]'"
    if "0.8" not in gi.Repository.get_default().enumerate_versions("Aravis"):
        return "the Aravis 0.8 typelib is not installed: install the Debian package gir1.2-aravis-0.8"
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.bind(("127.0.0.1", GVCP_PORT))
        except OSError as exc:  # a second fake camera would not stop: it would run beside the first
            return f"UDP port {GVCP_PORT} on 127.0.0.1 is taken ({exc.strerror}): another GigE Vision camera runs"
    return None


@contextmanager
def fake_gige_camera(lost_per_thousand: int = 0) -> Iterator[str]:
    """Aravis's fake camera as its own process on 127.0.0.1 (GigE Vision over loopback); yields its URI.

    It must own UDP port 3956 on 127.0.0.1, so one runs at a time on a machine; the test skips,
    saying so, when another holds the port or Aravis is not installed, and fails on anything else.
    """
    if (missing := fake_camera_unavailable()) is not None:
        pytest.skip(missing)
    process = subprocess.Popen(
        [FAKE_CAMERA, "-i", "127.0.0.1", "-s", "MENISCOPE", "-r", str(lost_per_thousand)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        uri = "aravis://127.0.0.1"
        deadline = time.monotonic() + 10
        while True:
            assert process.poll() is None, f"{FAKE_CAMERA} stopped: {process.stdout.read().strip()}"  # type: ignore[union-attr]
            try:
                open_source(uri).close()
                break
            except MeniscopeError as exc:
                assert time.monotonic() < deadline, f"{FAKE_CAMERA} did not answer on 127.0.0.1 within 10 s: {exc}"
                time.sleep(0.1)
        yield uri
    finally:
        process.terminate()
        process.wait(10)


@pytest.fixture(scope="class")
def fake_camera() -> Iterator[str]:
    with fake_gige_camera() as uri:
        yield uri


@pytest.fixture(scope="class")
def lossy_fake_camera() -> Iterator[str]:
    with fake_gige_camera(lost_per_thousand=200) as uri:
        yield uri


class TestAravisFakeCamera(EndlessContract):
    sample_frames = 12

    @pytest.fixture(params=["Mono8", "Mono16"])
    def source(self, fake_camera: str, request: pytest.FixtureRequest) -> Iterator[FrameSource]:
        with open_source(fake_camera, pixel_format=request.param, width=64, height=48, fps=1000) as source:
            yield source

    def test_applies_pixel_format_and_region(self, source: FrameSource) -> None:
        mono16 = source.describe()["pixel_format"] == "Mono16"
        assert (source.width, source.height) == (64, 48)
        assert (source.dtype, source.bit_depth) == ((np.uint16, 16) if mono16 else (np.uint8, 8))
        assert source.describe()["model"] == "Fake"


class TestAravisLossyNetwork(GapContract):
    @pytest.fixture
    def source(self, lossy_fake_camera: str) -> Iterator[FrameSource]:
        with open_source(lossy_fake_camera, width=64, height=48, fps=1000) as source:
            yield source


# --- V4L2, where this machine has a device -----------------------------------------------------------


@pytest.fixture(scope="module")
def v4l2_device() -> str:
    """The first /dev/video* that opens as a capture device, or a skip saying why there is none."""
    devices = sorted(glob.glob("/dev/video*"))
    if not devices:
        pytest.skip("no V4L2 device on this machine (/dev/video* absent)")
    for device in devices:
        try:
            open_source(f"v4l2://{device}").close()
            return f"v4l2://{device}"
        except MeniscopeError:
            continue
    pytest.skip(f"none of {', '.join(devices)} opens as a capture device")


class TestV4l2(EndlessContract):
    sample_frames = 10

    @pytest.fixture
    def source(self, v4l2_device: str) -> Iterator[FrameSource]:
        with open_source(v4l2_device) as source:
            yield source


# --- rendered live from the physics model ---------------------------------------------------------------


class TestSimulated(EndlessContract):
    @pytest.fixture
    def source(self) -> Iterator[FrameSource]:
        with open_source("sim://?seed=1") as source:  # unpaced, as fast as it renders
            yield source

    def test_renders_the_scene_at_its_rate_through_a_12_bit_camera(self, source: FrameSource, scene: Scene) -> None:
        assert (source.width, source.height, source.fps) == (
            scene.camera.width_px,
            scene.camera.height_px,
            scene.camera.fps,
        )
        assert (source.dtype, source.bit_depth) == (np.uint16, 12)
        frames = FrameBatch.concatenate(collect(source, 40))
        np.testing.assert_allclose(frames.timestamps, frames.indices / scene.camera.fps, rtol=0, atol=1e-12)
        assert frames.pixels.std(axis=0).mean() > 0  # it moves


# --- the factory and the public API --------------------------------------------------------------------


class TestOpenSource:
    @pytest.mark.parametrize(
        ("uri", "options", "problem"),
        [
            ("http://camera.local/stream", {}, "unknown source scheme 'http'"),
            ("{cine}", {"sped": 2}, "unknown option 'sped'"),
            ("{cine}", {"speed": -1}, "bad option speed=-1"),
            ("file://{cine}?loop=perhaps", {}, "bad option loop='perhaps'"),
            ("file://otherhost/rec.cine", {}, "local file"),
            ("{cine}.missing", {}, "no such file"),
            ("v4l2://camera", {}, "v4l2:///dev/videoN or v4l2://N"),
            ("v4l2:///dev/video99", {}, "cannot open the device"),
            ("zmq+tcp://127.0.0.1", {}, "zmq+tcp://host:port"),
            ("zmq+tcp://127.0.0.1:1", {"open_timeout": 0.2}, "no frames within 0.2 s"),
            ("aravis://127.0.0.1", {"pixel_format": "RGB8"}, "bad option pixel_format"),
            ("sim://?noize=lab", {}, "unknown option 'noize'"),
            ("sim://?noise=loud", {}, "bad option noise='loud': choose one of none, low, lab, high"),
            ("sim://?bit_depth=11", {}, "bad option bit_depth='11': choose one of 8, 10, 12, 16"),
            ("sim://?speed=fast", {}, "bad option speed='fast'"),
            ("sim://camera", {}, "a simulated source has no host or path"),
            ("sim://?ejection_hz=1500", {}, "lower the ejection rate"),
            ("sim://?scene={cine}.json", {}, "scene file not found"),
        ],
    )
    def test_bad_uris_and_options_are_one_line_errors(self, uri: str, options: dict, problem: str, cine: Path) -> None:
        with pytest.raises(MeniscopeError) as err:
            open_source(uri.format(cine=cine), **options)
        assert problem in str(err.value) and "\n" not in str(err.value)

    def test_keywords_override_the_query_string(self, cine: Path) -> None:
        with open_source(f"{cine.as_uri()}?speed=0.5&loop=1", speed=0) as source:
            assert (source.describe()["speed"], source.describe()["loop"]) == (0.0, True)

    def test_a_plain_path_may_hold_a_question_mark(self, cine: Path, tmp_path: Path) -> None:
        odd = tmp_path / "take?1.cine"
        shutil.copy(cine, odd)
        with open_source(str(odd), speed=0) as source:
            assert source.describe()["path"] == str(odd)

    def test_exports_are_complete(self) -> None:
        public = {
            name
            for name, value in vars(sources).items()
            if not name.startswith("_") and not isinstance(value, types.ModuleType)
        }
        assert set(sources.__all__) == public


class TestFrameBatch:
    def test_refuses_inconsistent_arrays(self) -> None:
        pixels = np.zeros((3, 4, 5), np.uint8)
        with pytest.raises(ValueError, match="indices"):
            FrameBatch(pixels, np.arange(2), np.zeros(3))
        with pytest.raises(ValueError, match="pixels"):
            FrameBatch(pixels.astype(np.float32), np.arange(3), np.zeros(3))

    def test_frames_of_a_batch_carry_index_and_time(self) -> None:
        batch = FrameBatch(np.arange(24, dtype=np.uint16).reshape(2, 3, 4), np.array([7, 9]), np.array([0.5, 0.6]))
        assert (batch[1].index, batch[1].timestamp, int(batch[1].pixels[0, 0])) == (9, 0.6, 12)


def test_a_replay_uri_names_the_recording_absolutely_whatever_the_working_folder(tmp_path, monkeypatch) -> None:
    from service.sources.replay import replay_uri

    monkeypatch.chdir(tmp_path)
    uri = replay_uri("rec with space.cine", speed="max", loop=1)
    assert uri == f"{(tmp_path / 'rec with space.cine').as_uri()}?speed=max&loop=1"
    assert "%20" in uri and uri.startswith("file:///")
