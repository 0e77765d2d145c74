"""The .cine reader: the stored words, rows top first, the file's own rate, depth and times.

Oracles: PIMS (same words, rows in display order) on real Phantom files and on files built here by
an independent writer (:func:`cine_bytes`, bit packing by :func:`pack_msb_first`, straight from the
layout in the Vision Research "Cine File Format" document); pycine, whose documented scaling is
predicted from our words.
"""

from __future__ import annotations

import itertools
import json
import os
import struct
import warnings
from pathlib import Path

import numpy as np
import pims
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from pycine.linLUT import linLUT
from pycine.raw import read_frames

from service.errors import MeniscopeError
from service.recordings import open_recording
from service.recordings.cine import CineRecording

REAL = {  # from shared/data/cine/README.md
    "cine_781.cine": dict(frames=15, width=256, height=256, bit_depth=12, acquisition_fps=90000.0, decimation=10.0),
    "cine_legacy.cine": dict(frames=97, width=128, height=128, bit_depth=14, acquisition_fps=35087.0, decimation=1.0),
}
_names = itertools.count()


@pytest.fixture(params=sorted(REAL))
def real_cine(request: pytest.FixtureRequest, shared_dir: Path) -> Path:
    path = shared_dir / "data" / "cine" / request.param
    if not path.is_file():
        pytest.skip(f"real Phantom file {path} is absent")
    return path


def pims_frames(path: Path) -> np.ndarray:
    """Every frame as PIMS reads it, shape (N, H, W)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cine = pims.Cine(str(path))
        try:
            return np.stack([np.asarray(cine[i]) for i in range(len(cine))])
        finally:
            cine.close()


def pack_msb_first(values: np.ndarray, bits: int) -> bytes:
    """Phantom's packed layout: each value's ``bits`` bits, most significant first, one continuous bit stream."""
    planes = (values.ravel()[:, None].astype(np.uint32) >> np.arange(bits - 1, -1, -1)) & 1
    return np.packbits(planes.astype(np.uint8).ravel()).tobytes()


def cine_bytes(
    frames: np.ndarray,
    *,
    storage: str = "16",
    real_bpp: int = 12,
    frame_rate: int = 1000,
    setup_length: int = 10412,
    annotations: list[int] | None = None,
    time64: np.ndarray | None = None,
    trigger: int = 0,
    first_no: int = 0,
) -> bytes:
    """A .cine in the canonical order (header, bitmap, SETUP, tagged blocks, offsets, images), written here.

    ``storage``: "8" or "16" (words, bottom row first) or "p10"/"p12" (packed, top row first).
    ``time64``: per-image TIME64 (uint64) for tagged block 1002; None writes no tagged blocks.
    """
    n, height, width = frames.shape
    if storage.startswith("p"):
        bits = int(storage[1:])
        pixels = [pack_msb_first(f, bits) for f in frames]
        bit_count, compression = 16, {10: 256, 12: 1024}[bits]
    else:
        bit_count, compression = int(storage), 0
        pixels = [f[::-1].astype(f"<u{bit_count // 8}").tobytes() for f in frames]
    setup = bytearray(setup_length)
    struct.pack_into("<H", setup, 0, min(frame_rate, 65535))  # FrameRate16
    struct.pack_into("<2sH", setup, 140, b"ST", setup_length)  # Mark, Length
    struct.pack_into("<I", setup, 768, frame_rate)  # FrameRate
    struct.pack_into("<I", setup, 800, 781 if setup_length >= 10412 else 649)  # SoftwareVersion
    struct.pack_into("<I", setup, 896, real_bpp)  # RealBPP
    if setup_length >= 10408:
        struct.pack_into("<d", setup, 10400, float(frame_rate))  # dFrameRate
    blocks = b""
    if time64 is not None:  # BlockSize, Type, Reserved (1: more blocks follow), data
        blocks = (
            struct.pack("<IHH", 8 + 8 * n, 1002, 1)
            + time64.astype("<u8").tobytes()
            + struct.pack("<IHH", 8 + 4 * n, 1003, 0)
            + bytes(4 * n)
        )
    off_setup = 44 + 40
    off_offsets = off_setup + setup_length + len(blocks)
    images, offsets = b"", []
    for px, annotation in zip(pixels, annotations or [8] * n):
        offsets.append(off_offsets + 8 * n + len(images))
        images += struct.pack("<I", annotation) + bytes(annotation - 8) + struct.pack("<I", len(px)) + px
    header = struct.pack(
        "<2sHHHiIiIIIIQ", b"CI", 44, 0, 1, first_no, n, first_no, n, 44, off_setup, off_offsets, trigger
    )
    bitmap = struct.pack(
        "<IiiHHIIiiII", 40, width, height, 1, bit_count, compression, len(pixels[0]), 0, 0, 0, 2**real_bpp
    )
    return header + bitmap + bytes(setup) + blocks + struct.pack(f"<{n}q", *offsets) + images


def write(folder: Path, data: bytes) -> Path:
    path = folder / f"built{next(_names)}.cine"
    path.write_bytes(data)
    return path


# ---------------------------------------------------------------- real files


def test_real_file_reads_as_pims_reads_it(real_cine: Path) -> None:
    with open_recording(real_cine) as rec:
        frames = rec.read(0, len(rec))
    expected = pims_frames(real_cine)
    assert frames.dtype == expected.dtype == np.uint16
    np.testing.assert_array_equal(frames, expected)


def test_real_file_header_facts(real_cine: Path) -> None:
    facts = REAL[real_cine.name]
    with open_recording(real_cine) as rec:
        info = rec.info()
        assert (len(rec), rec.width, rec.height, rec.bit_depth) == (
            facts["frames"],
            facts["width"],
            facts["height"],
            facts["bit_depth"],
        )
        assert info["acquisition_fps"] == facts["acquisition_fps"]
        assert info["decimation"] == facts["decimation"]
        assert rec.fps == facts["acquisition_fps"] / facts["decimation"]
        # the per-frame time stamps agree with the rate of the stored frames (within 1 %)
        assert rec.timestamps_source == "file"
        assert np.median(np.diff(rec.timestamps)) == pytest.approx(1 / rec.fps, rel=0.01)
    json.dumps(info, allow_nan=False)


def test_real_time_stamps_match_pims(real_cine: Path) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cine = pims.Cine(str(real_cine))
        expected = np.array([cine.get_time_to_trigger(i) for i in range(len(cine))])
        cine.close()
    with open_recording(real_cine) as rec:
        np.testing.assert_allclose(rec.timestamps, expected, atol=1e-6)  # PIMS goes through float datetimes
        assert rec.trigger_frame == -rec.header["first_image_no"]


def test_legacy_setup_is_shorter_and_lacks_the_newer_fields(shared_dir: Path) -> None:
    path = shared_dir / "data" / "cine" / "cine_legacy.cine"
    if not path.is_file():
        pytest.skip(f"real Phantom file {path} is absent")
    with open_recording(path) as rec:
        assert rec.header["setup_length"] < 10412
        assert rec.header["camera_model"] is None and rec.header["black_level"] is None


def test_pycine_scales_black_to_white_level_onto_the_full_range(shared_dir: Path) -> None:
    path = shared_dir / "data" / "cine" / "cine_781.cine"
    if not path.is_file():
        pytest.skip(f"real Phantom file {path} is absent")
    images, _, bpp = read_frames(str(path))
    theirs = np.stack(list(images))
    with open_recording(path) as rec:
        ours = rec.read(0, len(rec))
        black, white = rec.header["black_level"], rec.header["white_level"]
    assert (black, white, bpp) == (64, 4064, 12)
    expected = np.interp(ours, [black, white], [0, 2**bpp - 1]).astype(np.uint16)
    np.testing.assert_array_equal(theirs, expected)


# ---------------------------------------------------------------- built files


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data(), bits=st.sampled_from([10, 12]))
def test_packed_pixels_unpack_to_the_values_packed(tmp_path: Path, data: st.DataObject, bits: int) -> None:
    shape = data.draw(st.tuples(st.integers(1, 3), st.integers(1, 5), st.sampled_from([4, 8, 12])))
    frames = data.draw(arrays(np.uint16, shape, elements=st.integers(0, 2**bits - 1)))
    path = write(
        tmp_path, cine_bytes(frames, storage=f"p{bits}", real_bpp=bits, time64=np.zeros(len(frames), np.uint64))
    )
    with open_recording(path) as rec:
        assert (rec.bit_depth, rec.dtype, rec.header["pixel_storage"]) == (bits, np.uint16, f"packed {bits}-bit")
        np.testing.assert_array_equal(rec.read(0, len(rec)), frames)
    np.testing.assert_array_equal(pims_frames(path), frames)  # PIMS unpacks them the same way


def test_pycine_maps_packed_10_bit_codes_through_its_table(tmp_path: Path) -> None:
    codes = np.arange(1024, dtype=np.uint16).reshape(1, 32, 32)
    path = write(tmp_path, cine_bytes(codes, storage="p10", real_bpp=10, time64=np.zeros(1, np.uint64)))
    with open_recording(path) as rec:
        ours = rec[0]
    images, _, _ = read_frames(str(path))
    expected = np.interp(linLUT[ours], [64, 4064], [0, 4095]).astype(np.uint16)
    np.testing.assert_array_equal(next(images), expected)


@pytest.mark.parametrize(("storage", "dtype", "real_bpp"), [("8", np.uint8, 8), ("16", np.uint16, 14)])
def test_words_come_back_top_row_first(tmp_path: Path, storage: str, dtype: type, real_bpp: int) -> None:
    frames = np.arange(2 * 3 * 4, dtype=dtype).reshape(2, 3, 4)
    path = write(tmp_path, cine_bytes(frames, storage=storage, real_bpp=real_bpp, time64=np.zeros(2, np.uint64)))
    with open_recording(path) as rec:
        assert (rec.dtype, rec.bit_depth) == (np.dtype(dtype), real_bpp)
        np.testing.assert_array_equal(rec.read(0, 2), frames)
        assert rec[0][0, 0] == 0  # the first stored row is the bottom one


def test_annotations_of_any_length_are_skipped(tmp_path: Path) -> None:
    frames = np.random.default_rng(1).integers(0, 4096, (4, 6, 8)).astype(np.uint16)
    path = write(tmp_path, cine_bytes(frames, annotations=[8, 24, 12, 8], time64=np.zeros(4, np.uint64)))
    with open_recording(path) as rec:
        np.testing.assert_array_equal(rec.read(0, 4), frames)  # unevenly spaced images
        np.testing.assert_array_equal(rec.read(1, 2), frames[1:3])
    np.testing.assert_array_equal(pims_frames(path), frames)


def test_time_stamps_are_seconds_from_the_trigger(tmp_path: Path) -> None:
    trigger = (1_700_000_000 << 32) + 123
    time64 = trigger + np.array([-(2**32), -1, 0, 3 * 2**31], dtype=np.int64)
    path = write(
        tmp_path,
        cine_bytes(np.zeros((4, 2, 2), np.uint16), time64=time64.astype(np.uint64), trigger=trigger, first_no=-2),
    )
    with open_recording(path) as rec:
        assert rec.timestamps.tolist() == [-1.0, -(2.0**-32), 0.0, 1.5]
        assert rec.trigger_frame == 2
        assert rec.info()["trigger_time_utc"].startswith("2023-11-14T22:13:20")


def test_without_time_stamps_times_follow_the_frame_rate(tmp_path: Path) -> None:
    path = write(tmp_path, cine_bytes(np.zeros((3, 2, 2), np.uint16), frame_rate=35087, setup_length=5692, first_no=-1))
    with open_recording(path) as rec:
        assert rec.fps == 35087.0 and rec.timestamps_source == "frame_rate"
        np.testing.assert_allclose(rec.timestamps, (np.arange(3) - 1) / 35087)


def test_random_access_matches_one_full_read(tmp_path: Path) -> None:
    frames = np.random.default_rng(2).integers(0, 256, (9, 5, 7)).astype(np.uint8)
    path = write(tmp_path, cine_bytes(frames, storage="8", real_bpp=8, time64=np.zeros(9, np.uint64)))
    with open_recording(path) as rec:
        for start, count in [(0, 9), (3, 4), (8, 1), (5, 0)]:
            np.testing.assert_array_equal(rec.read(start, count), frames[start : start + count])
        np.testing.assert_array_equal(rec[-1], frames[-1])
        copy = rec[2]
        copy[:] = 0  # frames are copies: changing one changes neither the file nor later reads
        np.testing.assert_array_equal(rec[2], frames[2])
        with pytest.raises(IndexError):
            rec[9]
        with pytest.raises(MeniscopeError, match="frames 0..8"):
            rec.read(7, 3)
    with pytest.raises(MeniscopeError, match="closed"):
        rec.read(0, 1)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data(), storage=st.sampled_from(["8", "16", "p10", "p12"]))
def test_views_are_the_frames_read_and_copy_nothing_where_words_lie_at_one_stride(
    tmp_path: Path, data: st.DataObject, storage: str
) -> None:
    """:meth:`view_grey` of any run of frames is :meth:`read`'s frames: where the images are 8- or 16-bit words at one
    stride (the annotations between them of one length), a read-only view of the reader's mapping that outlives the reader; packed
    images, and runs whose annotations differ in length, come as copies."""
    n = data.draw(st.integers(1, 6))
    height, width = data.draw(st.integers(1, 5)), data.draw(st.sampled_from([4, 8, 12]))
    even = data.draw(st.booleans())
    annotations = (
        [data.draw(st.sampled_from([8, 12, 24]))] * n
        if even
        else data.draw(st.lists(st.sampled_from([8, 12, 24]), min_size=n, max_size=n))
    )
    bits = {"8": 8, "16": 12, "p10": 10, "p12": 12}[storage]
    dtype = np.uint8 if storage == "8" else np.uint16
    frames = np.random.default_rng(n).integers(0, 2**bits, (n, height, width)).astype(dtype)
    path = write(tmp_path, cine_bytes(frames, storage=storage, real_bpp=bits, annotations=annotations))
    start = data.draw(st.integers(0, n - 1))
    count = data.draw(st.integers(1, n - start))
    with open_recording(path) as rec:
        view = rec.view_grey(start, count)
        np.testing.assert_array_equal(view, rec.read(start, count))
        spaced = len(set(annotations[start + 1 : start + count])) <= 1  # the annotations between the images alike
        assert np.shares_memory(view, rec.mapped) == (storage in ("8", "16") and spaced)
        assert not view.flags.writeable or not np.shares_memory(view, rec.mapped)
    np.testing.assert_array_equal(view, frames[start : start + count])  # still readable once the reader is closed


def test_a_view_of_frames_a_shrunken_file_no_longer_holds_is_an_error(tmp_path: Path) -> None:
    frames = np.zeros((4, 6, 8), np.uint16)
    path = write(tmp_path, cine_bytes(frames))
    with open_recording(path) as rec:
        os.truncate(path, path.stat().st_size - 10)
        with pytest.raises(MeniscopeError, match="shrank"):
            rec.view_grey(2, 2)


def test_info_is_json_and_its_header_fields_extend_the_common_ones(tmp_path: Path) -> None:
    path = write(tmp_path, cine_bytes(np.zeros((2, 4, 4), np.uint16), time64=np.zeros(2, np.uint64)))
    with open_recording(path) as rec:
        info = rec.info()
        common = {
            "path",
            "format",
            "frames",
            "fps",
            "width",
            "height",
            "bit_depth",
            "dtype",
            "trigger_frame",
            "timestamps",
        }
        assert common <= info.keys() and not common & rec.header.keys()
        assert json.loads(json.dumps(info, allow_nan=False)) == info


@pytest.mark.parametrize(
    ("change", "problem"),
    [
        (lambda b: b"XX" + b[2:], "not a Phantom cine file"),
        (lambda b: b[:6] + struct.pack("<H", 0) + b[8:], "version 0 is not supported"),
        (lambda b: b[:4] + struct.pack("<H", 1) + b[6:], r"compression 1 \(JPEG\)"),
        (lambda b: b[:58] + struct.pack("<H", 24) + b[60:], "colour cine"),
        (lambda b: b[:-1], "truncated: image 1"),
        (lambda b: b[:40], "truncated: the cine file header"),
    ],
)
def test_bad_files_give_one_line_naming_the_problem(tmp_path: Path, change, problem: str) -> None:
    good = cine_bytes(np.zeros((2, 4, 4), np.uint16), time64=np.zeros(2, np.uint64))
    path = write(tmp_path, change(good))
    with pytest.raises(MeniscopeError, match=problem) as error:
        CineRecording(path)
    assert str(path) in str(error.value) and "\n" not in str(error.value)
