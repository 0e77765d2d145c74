"""Colour Phantom cameras: raw CFA (Bayer) .cine frames, as stored and as the inverse models see them.

Files are written by our writer in each layout a colour Phantom stores (16-bit words, packed 10-bit,
packed 12-bit, 8-bit words); read back as the mosaic, rows top first; checked against pycine, which
reads raw 16-bit mosaics, and against PIMS for the header (PIMS refuses uninterpolated frames).
Inference sees OpenCV's demosaicing to grey.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import cv2
import numpy as np
import pims
import pytest
from pycine.raw import read_frames

from service.cli import main
from service.errors import MeniscopeError
from service.recordings import open_recording
from service.recordings.cine_writer import CFA_CODES, CineWriter
from service.recordings.roi import roi_frames
from service.scene import Scene

LAYOUTS = [
    (16, False, "16-bit"),
    (12, False, "16-bit"),
    (10, True, "packed 10-bit"),
    (12, True, "packed 12-bit"),
    (8, False, "8-bit"),
]
WHITE_BALANCE = (1.75, 2.25)


def mosaic_of(rgb: np.ndarray, pattern: str) -> np.ndarray:
    """What a colour sensor with this Bayer pattern stores of an RGB image (N, H, W, 3): (N, H, W)."""
    channel = {"r": 0, "g": 1, "b": 2}
    out = np.empty(rgb.shape[:-1], rgb.dtype)
    for k, (dy, dx) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
        out[:, dy::2, dx::2] = rgb[:, dy::2, dx::2, channel[pattern[k]]]
    return out


def write_colour(path: Path, frames: np.ndarray, bits: int, packed: bool, pattern: str) -> Path:
    _, height, width = frames.shape
    with CineWriter(
        path, width, height, 19000.0, bits, packed=packed, cfa=pattern, white_balance=WHITE_BALANCE
    ) as writer:
        writer.write(frames)
    return path


@pytest.mark.parametrize("pattern", sorted(CFA_CODES))
@pytest.mark.parametrize(("bits", "packed", "storage"), LAYOUTS)
def test_the_mosaic_reads_back_as_written_with_its_pattern_and_white_balance(
    tmp_path: Path, bits: int, packed: bool, storage: str, pattern: str
) -> None:
    frames = np.random.default_rng(bits).integers(0, 2**bits, (4, 6, 10))
    path = write_colour(tmp_path / "colour.cine", frames, bits, packed, pattern)
    with open_recording(path) as rec:
        np.testing.assert_array_equal(rec.read(0, 4), frames)
        info = rec.info()
    assert info["cfa"] == pattern and info["pixel_storage"] == storage
    assert info["white_balance"]["red_gain"] == WHITE_BALANCE[0]
    assert info["white_balance"]["blue_gain"] == WHITE_BALANCE[1]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cine = pims.Cine(str(path))  # PIMS reads the header; it refuses uninterpolated frames
    try:
        assert cine.cfa == CFA_CODES[pattern] and cine.compression == 2
        assert cine.setup_fields_dict["wb_gain"][:2] == pytest.approx(WHITE_BALANCE)
        with pytest.raises(ValueError, match="un-interpolated"):
            cine[0]
    finally:
        cine.close()


@pytest.mark.parametrize("pattern", sorted(CFA_CODES))
def test_pycine_reads_the_same_16_bit_mosaic(tmp_path: Path, pattern: str) -> None:
    frames = np.random.default_rng(1).integers(0, 4096, (3, 8, 12))
    path = write_colour(tmp_path / "colour.cine", frames, 12, False, pattern)
    images, setup, _ = read_frames(str(path))
    np.testing.assert_array_equal(np.stack(list(images)), frames)
    assert setup.CFA == CFA_CODES[pattern]


@pytest.mark.parametrize("pattern", sorted(CFA_CODES))
def test_inference_sees_opencv_grey_of_the_scene_the_sensor_filmed(tmp_path: Path, pattern: str) -> None:
    """A uniform colour demosaics to 0.299 R + 0.587 G + 0.114 B; the pattern decides which sites are which."""
    rgb = np.broadcast_to(np.array([3000, 1200, 400], np.uint16), (2, 8, 10, 3))
    path = write_colour(tmp_path / "colour.cine", mosaic_of(rgb, pattern), 12, True, pattern)
    with open_recording(path) as rec:
        grey = rec.read_grey(0, 2)
    assert grey.shape == (2, 8, 10) and grey.dtype == np.uint16
    assert np.abs(grey[:, 2:-2, 2:-2].astype(int) - round(0.299 * 3000 + 0.587 * 1200 + 0.114 * 400)).max() <= 1


def test_the_scene_roi_of_a_colour_recording_is_demosaiced_before_cropping(tmp_path: Path, scene: Scene) -> None:
    cam = scene.camera
    x, y = cam.roi
    width, height = x + cam.width_px + 3, y + cam.height_px + 5
    frames = np.random.default_rng(2).integers(0, 4096, (2, height, width))
    path = write_colour(tmp_path / "colour.cine", frames, 12, False, "gbrg")
    with open_recording(path) as rec:
        roi = roi_frames(rec, scene, 0, 2)
    whole = np.stack([cv2.cvtColor(f, cv2.COLOR_BayerGBRG2GRAY) for f in frames.astype(np.uint16)])
    np.testing.assert_array_equal(roi, whole[:, y : y + cam.height_px, x : x + cam.width_px])


def test_frames_and_info_verbs_give_the_mosaic_and_its_pattern(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    frames = np.random.default_rng(4).integers(0, 1024, (5, 6, 8))
    path = write_colour(tmp_path / "colour.cine", frames, 10, True, "rggb")
    assert main(["frames", str(path), "--start", "1", "--count", "3", "--out", str(tmp_path / "f.npy")]) == 0
    np.testing.assert_array_equal(np.load(tmp_path / "f.npy"), frames[1:4])
    capsys.readouterr()
    assert main(["info", str(path)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["cfa"] == "rggb" and info["white_balance"]["red_gain"] == WHITE_BALANCE[0]


def test_raw_cfa_without_a_known_pattern_is_one_clear_error(tmp_path: Path) -> None:
    path = write_colour(tmp_path / "colour.cine", np.zeros((1, 4, 4), int), 16, False, "rggb")
    data = bytearray(path.read_bytes())
    off_setup = int.from_bytes(data[28:32], "little")
    data[off_setup + 808 : off_setup + 812] = (0).to_bytes(4, "little")  # SETUP.CFA: none
    path.write_bytes(bytes(data))
    with pytest.raises(MeniscopeError, match="unknown colour filter array"):
        open_recording(path)


@pytest.mark.parametrize(
    ("kwargs", "problem"),
    [
        ({"bit_depth": 10}, "cannot be stored in words"),
        ({"bit_depth": 16, "packed": True}, "cannot be stored packed"),
        ({"bit_depth": 12, "cfa": "cmyk"}, "CFA pattern 'cmyk'"),
    ],
)
def test_the_writer_refuses_layouts_phantom_has_not(tmp_path: Path, kwargs: dict, problem: str) -> None:
    with pytest.raises(MeniscopeError, match=problem):
        CineWriter(tmp_path / "x.cine", 8, 4, 1000.0, **kwargs)
