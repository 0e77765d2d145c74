"""The .cine writer: what it writes, our reader, PIMS and pycine read back as written.

pycine rescales words from SETUP's [BlackLevel, WhiteLevel] to [0, 2**RealBPP - 1] and reads 16-bit
words only; the writer stores BlackLevel 0 and WhiteLevel 2**bit_depth - 1, so for 12- and 16-bit
files pycine must return the words unchanged.
"""

from __future__ import annotations

import itertools
import warnings
from pathlib import Path

import numpy as np
import pims
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from pycine.raw import read_frames

from service.errors import MeniscopeError
from service.recordings import cine_writer, open_recording, open_writer

_names = itertools.count()


def fresh(folder: Path) -> Path:
    return folder / f"written{next(_names)}.cine"


@st.composite
def recordings(draw: st.DrawFn) -> tuple[int, np.ndarray, np.ndarray | None, list[int]]:
    """(bit depth, frames (N, H, W), times (N,) or None, batch boundaries)."""
    bits = draw(st.sampled_from([8, 12, 16]))
    shape = draw(st.tuples(st.integers(1, 6), st.integers(1, 7), st.integers(1, 9)))
    frames = draw(arrays(np.uint8 if bits == 8 else np.uint16, shape, elements=st.integers(0, 2**bits - 1)))
    times = draw(st.none() | arrays(np.float64, shape[:1], elements=st.floats(-1e3, 1e3)))
    cuts = sorted(draw(st.lists(st.integers(0, shape[0]), max_size=3)))
    return bits, frames, times, cuts


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    recording=recordings(),
    fps=st.floats(1e-3, 1e7, allow_nan=False),
    trigger_frame=st.integers(-5, 10),
)
def test_written_frames_read_back_identically(tmp_path: Path, recording: tuple, fps: float, trigger_frame: int) -> None:
    bits, frames, times, cuts = recording
    path = fresh(tmp_path)
    with open_writer(path, frames.shape[2], frames.shape[1], fps, bit_depth=bits, trigger_frame=trigger_frame) as w:
        for a, b in zip([0, *cuts], [*cuts, len(frames)]):  # streamed in batches (some empty)
            w.write(frames[a:b], None if times is None else times[a:b])
    with open_recording(path) as rec:
        assert (len(rec), rec.height, rec.width) == frames.shape
        assert (rec.fps, rec.bit_depth, rec.dtype, rec.trigger_frame) == (fps, bits, frames.dtype, trigger_frame)
        np.testing.assert_array_equal(rec.read(0, len(rec)), frames)
        expected = (np.arange(len(frames)) - trigger_frame) / fps if times is None else times
        np.testing.assert_allclose(rec.timestamps, expected, rtol=0, atol=2**-32)  # TIME64 resolution
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cine = pims.Cine(str(path))
        np.testing.assert_array_equal(np.stack([np.asarray(cine[i]) for i in range(len(cine))]), frames)
        cine.close()
    if bits > 8:
        images, _, bpp = read_frames(str(path))
        assert bpp == bits
        np.testing.assert_array_equal(np.stack(list(images)), frames)


def test_the_header_is_completed_on_close(tmp_path: Path) -> None:
    path = fresh(tmp_path)
    writer = open_writer(path, 4, 2, 19000.0, bit_depth=16)
    writer.write(np.ones((3, 2, 4), np.uint16))
    with pytest.raises(MeniscopeError):  # no SETUP or offsets yet: not a readable file
        open_recording(path)
    writer.close()
    writer.close()  # a second close does nothing
    with open_recording(path) as rec:
        assert len(rec) == 3
        assert rec.header["created_by"] == "meniscope"
        assert (rec.header["black_level"], rec.header["white_level"]) == (0, 65535)


def test_a_file_with_no_frames_is_valid(tmp_path: Path) -> None:
    path = fresh(tmp_path)
    open_writer(path, 8, 8, 100.0).close()
    with open_recording(path) as rec:
        assert len(rec) == 0 and rec.read(0, 0).shape == (0, 8, 8)
        assert rec.info()["timestamps"] == {"source": "file", "first_s": None, "last_s": None, "mean_fps": None}


def test_smaller_integer_types_are_widened(tmp_path: Path) -> None:
    path = fresh(tmp_path)
    with open_writer(path, 3, 2, 10.0, bit_depth=12) as w:
        w.write(np.full((1, 2, 3), 255, np.uint8))
        w.write(np.full((1, 2, 3), 4095, np.int64))
    with open_recording(path) as rec:
        assert rec.read(0, 2)[:, 0, 0].tolist() == [255, 4095]


@pytest.mark.parametrize(
    ("frames", "times", "problem"),
    [
        (np.zeros((1, 2, 3), np.float32), None, "give integer pixel values"),
        (np.full((1, 2, 3), 4096, np.uint16), None, r"do not fit in 12 bits \(0..4095\)"),
        (np.full((1, 2, 3), -1, np.int16), None, "do not fit in 12 bits"),
        (np.zeros((2, 3), np.uint16), None, r"this writer takes \(N, 2, 3\)"),
        (np.zeros((2, 2, 3), np.uint16), np.zeros(3), "need one per frame"),
        (np.zeros((1, 2, 3), np.uint16), np.array([np.nan]), "finite"),
        (np.zeros((1, 2, 3), np.uint16), np.array([1e10]), "within 68 years"),
    ],
)
def test_bad_batches_are_refused(tmp_path: Path, frames: np.ndarray, times, problem: str) -> None:
    with open_writer(fresh(tmp_path), 3, 2, 10.0, bit_depth=12) as w:
        with pytest.raises(MeniscopeError, match=problem):
            w.write(frames, times)


@pytest.mark.parametrize(
    ("args", "problem"),
    [
        (dict(bit_depth=10), "bit depth 10 cannot be stored in words"),
        (dict(fps=0.0), "frame rate 0.0"),
        (dict(fps=float("nan")), "frame rate nan"),
        (dict(width=0), "width 0 px"),
        (dict(trigger_frame=2**31), "trigger frame"),
    ],
)
def test_bad_settings_are_refused(tmp_path: Path, args: dict, problem: str) -> None:
    settings_ = dict(width=4, height=4, fps=10.0, bit_depth=8, trigger_frame=0) | args
    with pytest.raises(MeniscopeError, match=problem):
        open_writer(fresh(tmp_path), **settings_)


def test_writing_after_close_or_into_a_missing_folder_is_refused(tmp_path: Path) -> None:
    writer = open_writer(fresh(tmp_path), 2, 2, 10.0)
    writer.close()
    with pytest.raises(MeniscopeError, match="closed"):
        writer.write(np.zeros((1, 2, 2), np.uint8))
    with pytest.raises(MeniscopeError, match="does not exist"):
        open_writer(tmp_path / "missing" / "a.cine", 2, 2, 10.0)


def test_a_batch_that_would_pass_the_32_bit_offsets_is_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(cine_writer, "OFFSET_LIMIT", 20_000)  # stands for 4 GiB
    path = fresh(tmp_path)
    with open_writer(path, 10, 10, 10.0) as w:
        w.write(np.zeros((50, 10, 10), np.uint8))
        with pytest.raises(MeniscopeError, match="4 GiB"):
            w.write(np.zeros((50, 10, 10), np.uint8))
    with open_recording(path) as rec:  # what was written before stays readable
        assert len(rec) == 50
