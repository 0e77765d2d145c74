"""A recording that lies or changes under the reader is one error line naming it: never a signal, a huge
allocation or frames that are not in the file.
"""

from __future__ import annotations

import os
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from service.errors import MeniscopeError
from service.recordings import open_recording, open_writer
from service.sources import open_source

REPO = Path(__file__).resolve().parents[1]


def cine(path: Path, frames: int = 400, fps: float = 19000.0) -> Path:
    with open_writer(path, 32, 24, fps, bit_depth=8) as writer:
        writer.write(np.random.default_rng(1).integers(0, 255, (frames, 24, 32)).astype(np.uint8))
    return path


def avi(path: Path, frames: int = 40) -> Path:
    with open_writer(path, 32, 24, 19000.0) as writer:
        writer.write(np.random.default_rng(2).integers(0, 255, (frames, 24, 32)).astype(np.uint8))
    return path


def test_a_cine_that_shrinks_while_open_is_an_error_not_sigbus(tmp_path: Path) -> None:
    """What ``cp new.cine rec.cine`` does to a file being read: truncated to 1,000 bytes (a child process, so
    that a SIGBUS would fail this test rather than end the test run)."""
    path = cine(tmp_path / "rec.cine")
    code = f"""
import os
from service.errors import MeniscopeError
from service.recordings import open_recording
rec = open_recording({str(path)!r})
rec.read(0, 10)
os.truncate({str(path)!r}, 1000)
try:
    rec.read(300, 64)
except MeniscopeError as exc:
    print("error:", exc)
"""
    run = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )
    assert run.returncode == 0, f"the reader died with {run.returncode}: {run.stderr[-500:]}"
    assert "error:" in run.stdout and "shrank" in run.stdout


@pytest.mark.parametrize("change", ["truncate", "replace", "delete", "rewrite"])
def test_a_replayed_recording_that_changes_on_disk_ends_the_stream_with_an_error(tmp_path: Path, change: str) -> None:
    path = cine(tmp_path / "rec.cine")
    with open_source(f"file://{path}?speed=0&loop=1") as source:
        assert len(source.read(64))
        if change == "truncate":
            os.truncate(path, 1000)
        elif change == "replace":
            cine(tmp_path / "new.cine", frames=100).replace(path)
        elif change == "delete":
            path.unlink()
        else:  # overwritten in place with a file of the same size
            path.write_bytes(path.read_bytes())
            os.utime(path, ns=(0, 0))
        with pytest.raises(MeniscopeError, match="rec.cine: the recording (changed on disk|is gone)"):
            source.read(64)


@pytest.mark.parametrize("fps", [5e-324, 1e-9, 1e308, 1e12])
def test_absurd_cine_frame_rates_are_refused(tmp_path: Path, fps: float) -> None:
    path = cine(tmp_path / "rec.cine", frames=4)
    data = bytearray(path.read_bytes())
    setup = struct.unpack_from("<I", data, 28)[0]  # OffSetup
    struct.pack_into("<d", data, setup + 10400, fps)  # dFrameRate
    path.write_bytes(data)
    with pytest.raises(MeniscopeError, match="frame rate .* is outside"):
        open_recording(path)


@pytest.mark.parametrize("length", [3, 39, 41, 10**9, 2**32 - 1])
def test_an_avi_whose_header_miscounts_its_frames_is_refused(tmp_path: Path, length: int) -> None:
    """strh.dwLength of the video stream: 10**9 used to allocate 7.45 GiB; 3 read 3 of the 40 frames."""
    path = avi(tmp_path / "rec.avi")
    data = bytearray(path.read_bytes())
    strh = data.index(b"strh") + 8
    struct.pack_into("<I", data, strh + 32, length)
    path.write_bytes(data)
    with pytest.raises(MeniscopeError, match=f"says {length} frames, the stream holds 40"):
        open_recording(path)


@pytest.mark.parametrize("field", ["avih", "strf"])
def test_an_avi_whose_headers_disagree_on_the_frame_size_is_refused(tmp_path: Path, field: str) -> None:
    """A bogus width in one header used to decode garbage frames that wide."""
    path = avi(tmp_path / "rec.avi")
    data = bytearray(path.read_bytes())
    at = data.index(field.encode()) + 8 + (32 if field == "avih" else 4)  # avih dwWidth, strf biWidth
    struct.pack_into("<i", data, at, 34)
    path.write_bytes(data)
    with pytest.raises(MeniscopeError, match="34 x 24"):
        open_recording(path)


def test_every_truncation_of_an_avi_is_reported(tmp_path: Path) -> None:
    data = avi(tmp_path / "rec.avi", frames=6).read_bytes()
    cut = tmp_path / "cut.avi"
    for length in range(0, len(data), max(1, len(data) // 300)):
        cut.write_bytes(data[:length])
        with pytest.raises(MeniscopeError):
            with open_recording(cut) as rec:
                rec.read(0, len(rec))


def test_a_damaged_avi_frame_that_ffmpeg_conceals_is_reported(tmp_path: Path) -> None:
    """One byte flipped inside the second frame's FFV1 data: FFmpeg logs "slice CRC mismatch" and OpenCV
    returned the garbage frame as good."""
    path = avi(tmp_path / "rec.avi", frames=10)
    data = bytearray(path.read_bytes())
    first = data.index(b"00dc", data.index(b"movi"))
    second = data.index(b"00dc", first + 8)
    data[second + 8 + 40] ^= 0xFF
    path.write_bytes(data)
    with pytest.raises(MeniscopeError, match="concealed .*slice CRC mismatch"):
        with open_recording(path) as rec:
            rec.read(0, len(rec))
