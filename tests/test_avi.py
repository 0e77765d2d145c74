"""AVI through OpenCV: 8-bit grey frames round-trip exactly (FFV1) at high-speed camera rates."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from service.errors import MeniscopeError
from service.recordings import open_recording, open_writer

_names = itertools.count()


def fresh(folder: Path) -> Path:
    return folder / f"written{next(_names)}.avi"


def noise(shape: tuple[int, ...], seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, shape).astype(np.uint8)


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    frames=arrays(
        np.uint8,
        st.tuples(st.integers(1, 4), st.sampled_from([2, 16, 34]), st.sampled_from([2, 24])),
        elements=st.integers(0, 255),
    ),
    fps=st.sampled_from([30.0, 1000.0, 1200.0, 19000.0, 18939.39, 90000.0, 19000 / 3]),
)
@example(frames=np.zeros((1, 2, 2), np.uint8), fps=30.0)  # one frame: OpenCV cannot seek back to it
def test_frames_and_rate_read_back_exactly(tmp_path: Path, frames: np.ndarray, fps: float) -> None:
    path = fresh(tmp_path)
    with open_writer(path, frames.shape[2], frames.shape[1], fps) as w:
        w.write(frames)
    with open_recording(path) as rec:
        assert (len(rec), rec.height, rec.width, rec.dtype, rec.bit_depth) == (*frames.shape, np.uint8, 8)
        assert rec.fps == pytest.approx(fps, rel=1e-12)
        np.testing.assert_array_equal(rec.read(0, len(rec)), frames)


def test_random_access_seeks_both_ways(tmp_path: Path) -> None:
    frames = noise((30, 16, 24))
    path = fresh(tmp_path)
    with open_writer(path, 24, 16, 19000.0) as w:
        w.write(frames[:10])
        w.write(frames[10:], timestamps=np.arange(10, 30) / 19000.0)  # the nominal times are accepted
    with open_recording(path) as rec:
        for start, count in [(20, 5), (3, 2), (5, 10), (29, 1), (0, 30)]:
            np.testing.assert_array_equal(rec.read(start, count), frames[start : start + count])
        np.testing.assert_array_equal(rec[-1], frames[-1])
        np.testing.assert_allclose(rec.timestamps, np.arange(30) / 19000.0)
        info = rec.info()
        assert info["codec"] == "ffv1" and info["timestamps"]["source"] == "frame_rate"
        json.dumps(info, allow_nan=False)


@pytest.mark.parametrize(
    ("args", "problem"),
    [
        (dict(bit_depth=12), "8-bit grey frames only"),
        (dict(trigger_frame=3), "no trigger frame"),
        (dict(width=25), "even width and height"),
    ],
)
def test_what_avi_cannot_hold_is_refused(tmp_path: Path, args: dict, problem: str) -> None:
    settings_ = dict(width=24, height=16, fps=19000.0) | args
    with pytest.raises(MeniscopeError, match=problem):
        open_writer(fresh(tmp_path), **settings_)


def test_uneven_times_are_refused(tmp_path: Path) -> None:
    with open_writer(fresh(tmp_path), 24, 16, 100.0) as w:
        with pytest.raises(MeniscopeError, match="constant frame rate"):
            w.write(noise((2, 16, 24)), timestamps=np.array([0.0, 0.5]))


def test_truncated_or_foreign_files_give_one_line(tmp_path: Path) -> None:
    path = fresh(tmp_path)
    with open_writer(path, 48, 32, 19000.0) as w:
        w.write(noise((20, 32, 48)))
    data = path.read_bytes()
    cut = fresh(tmp_path)
    cut.write_bytes(data[: len(data) // 2])  # header and index claim 20 frames, half are gone
    with pytest.raises(MeniscopeError, match="truncated or corrupt"):
        with open_recording(cut) as rec:
            rec.read(0, len(rec))
    cut.write_bytes(data[:100])
    with pytest.raises(MeniscopeError, match="truncated or corrupt"):
        open_recording(cut)
    cut.write_bytes(b"CI" + data[2:])
    with pytest.raises(MeniscopeError, match="not an AVI file"):
        open_recording(cut)


def test_rgb_video_is_refused_and_yuv_video_gives_its_luma(tmp_path: Path) -> None:
    grey = noise((3, 32, 48))
    rgb, yuv = fresh(tmp_path), fresh(tmp_path)
    for path, fourcc in ((rgb, "FFV1"), (yuv, "MJPG")):
        writer = cv2.VideoWriter(
            str(path), cv2.CAP_FFMPEG, cv2.VideoWriter_fourcc(*fourcc), 30.0, (48, 32), isColor=True
        )
        for frame in grey:
            writer.write(np.stack([frame, frame // 2, frame], axis=-1))
        writer.release()
    with pytest.raises(MeniscopeError, match="only 8-bit grey"):
        open_recording(rgb)
    with open_recording(yuv) as rec:
        assert rec.read(0, 3).shape == grey.shape
