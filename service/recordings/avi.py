"""AVI recordings through OpenCV's FFmpeg backend: 8-bit grey frames, written losslessly as FFV1.

What this OpenCV build does (opencv-contrib-python-headless 4.14.0, FFmpeg avcodec 62.28, checked by
writing and reading back 8-bit grey noise): FFV1 (``gray`` pixel format), PNG and raw Y800 round-trip
exactly, FFV1 being the smallest on camera-like frames; HFYU and FFVH come back off by one, MJPG and
XVID lossy. Three quirks shape this module:

- above 1,000 fps OpenCV gives the AVI stream a 1/600 s time base (it reads back as 600 fps, and
  between 1,000 and 1,200 fps frames are dropped as duplicates), so frames are written at a nominal
  25 fps and the stream header's rate (``strh`` dwRate/dwScale, ``avih`` dwMicroSecPerFrame) is
  patched to the true rate afterwards; FFmpeg and OpenCV then report it exactly;
- odd widths and heights are silently cropped to even, so the writer refuses them;
- AVI keeps a constant rate and has no trigger: times are ``i / fps`` and the trigger frame is 0.

Reading asks OpenCV for frames unconverted: grey video comes back as stored, YUV video (MJPG, H.264,
...) as its luma plane, and RGB video is refused. OpenCV trusts the headers, so the reader first holds
them against the stream (:mod:`service.recordings.avi_riff`): a frame count or frame size that the
stream does not bear out is refused, never read as garbage or as a huge allocation.
"""

from __future__ import annotations

import math
import struct
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np

from service.errors import MeniscopeError
from service.recordings.avi_riff import scan
from service.recordings.base import Recording, RecordingWriter
from service.recordings.ffmpeg_log import decoder_errors

FOURCC = "FFV1"
#: The rate handed to OpenCV; the header is patched to the real one on close (see the module notes).
NOMINAL_FPS = 25.0
RIFF_MAGIC = b"RIFF"
CHUNK = struct.Struct("<4sI")  # chunk id, size of the data that follows


class AviRecording(Recording):
    """An AVI file read frame by frame through OpenCV (FFmpeg), as 8-bit grey."""

    format = "avi"

    def __init__(self, path: Path) -> None:
        path = Path(path)
        layout = scan(path)
        if layout.header_frames != layout.stream_frames:
            raise MeniscopeError(
                path,
                f"corrupt header: the stream header says {layout.header_frames} frames, the "
                f"stream holds {layout.stream_frames}",
            )
        self._capture = capture = _capture(path)
        self._next = 0  # index of the frame the next capture.read() returns
        count = max(int(capture.get(cv2.CAP_PROP_FRAME_COUNT)), 0)
        width, height = int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)), int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT))
        problem = (
            f"FFmpeg counts {count} frames, the stream holds {layout.stream_frames}"
            if count != layout.stream_frames
            else f"the main header says {layout.main_size[0]} x {layout.main_size[1]} px, the stream header "
            f"{layout.width} x {layout.height}"
            if layout.main_size != (layout.width, layout.height)
            else f"FFmpeg decodes {width} x {height} px, the stream header says {layout.width} x {layout.height}"
            if (width, height) != (layout.width, layout.height)
            else None
        )
        try:
            if problem is not None:
                raise MeniscopeError(path, f"corrupt or unsupported AVI: {problem}")
            self._open(path, capture, count, width, height)
        except MeniscopeError:
            capture.release()
            raise

    def _open(self, path: Path, capture: cv2.VideoCapture, count: int, width: int, height: int) -> None:
        """The common facts from the checked capture; frame 0 decoded now, not mid-analysis (colour, undecodable)."""
        fourcc = int(capture.get(cv2.CAP_PROP_FOURCC))
        super().__init__(
            path,
            frame_count=count,
            fps=capture.get(cv2.CAP_PROP_FPS),
            width=width,
            height=height,
            bit_depth=8,
            dtype=np.dtype(np.uint8),
            timestamps=None,
            trigger_frame=0,
            header={"codec": fourcc.to_bytes(4, "little").decode("latin-1").strip("\0 ") or None},
        )
        if self.frame_count:
            self._read(0, 1)

    def _read(self, start: int, count: int) -> np.ndarray:
        if start == 0 and self._next != 0:  # OpenCV cannot seek back to the start of a one-frame file
            self._capture.release()
            self._capture = _capture(self.path)
        elif start != self._next:
            self._capture.set(cv2.CAP_PROP_POS_FRAMES, start)
        self._next = -1  # unknown until the batch is complete
        frames = []  # decoded before any array of the claimed size is made
        with decoder_errors() as errors:
            for k in range(count):
                ok, frame = self._capture.read()
                if not ok:
                    raise MeniscopeError(
                        self.path, f"frame {start + k} cannot be decoded: the file is truncated or corrupt"
                    )
                if frame.shape != (self.height, self.width):
                    raise MeniscopeError(
                        self.path,
                        f"frame {start + k} decodes to shape {frame.shape}: only 8-bit grey AVI of the "
                        f"header's {self.width} x {self.height} px is supported",
                    )
                frames.append(frame)
        if errors:
            raise MeniscopeError(
                self.path,
                f"reading frames {start}..{start + count - 1}, FFmpeg reported damage it "
                f"concealed (in one of them or the next): {errors[0]}",
            )
        self._next = start + count
        return np.stack(frames)

    def _release(self) -> None:
        self._capture.release()


def _capture(path: Path) -> cv2.VideoCapture:
    """An OpenCV capture of ``path`` at frame 0 that returns frames unconverted (grey stays grey)."""
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)  # not its warning that conversion is off
    try:
        capture = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG, [cv2.CAP_PROP_CONVERT_RGB, 0])
    finally:
        cv2.utils.logging.setLogLevel(level)
    if not capture.isOpened():
        raise MeniscopeError(path, "OpenCV cannot open this AVI (corrupt, or a codec its FFmpeg lacks)")
    return capture


class AviWriter(RecordingWriter):
    """Writes 8-bit grey frames as lossless FFV1 in AVI; :meth:`close` stamps the true frame rate."""

    def __init__(
        self, path: Path, width: int, height: int, fps: float, bit_depth: int = 8, trigger_frame: int = 0
    ) -> None:
        super().__init__(path, width, height, fps, bit_depth, trigger_frame)
        if bit_depth != 8:
            raise MeniscopeError(self.path, f"AVI holds 8-bit grey frames only, not {bit_depth}-bit: write .cine")
        if self.trigger_frame != 0:
            raise MeniscopeError(self.path, "AVI has no trigger frame: write .cine to keep one")
        if self.width % 2 or self.height % 2:
            raise MeniscopeError(
                self.path,
                f"{self.width} x {self.height} px: OpenCV crops odd sizes in AVI, give an even width and height",
            )
        self._writer = cv2.VideoWriter(
            str(self.path),
            cv2.CAP_FFMPEG,
            cv2.VideoWriter_fourcc(*FOURCC),
            NOMINAL_FPS,
            (self.width, self.height),
            isColor=False,
        )
        if not self._writer.isOpened():
            raise MeniscopeError(self.path, f"this OpenCV build cannot write {FOURCC} AVI: write .cine")

    def _append(self, frames: np.ndarray, timestamps: np.ndarray | None) -> None:
        if timestamps is not None and not np.allclose(
            timestamps, self.nominal_times(len(frames)), rtol=0, atol=1e-3 / self.fps
        ):
            raise MeniscopeError(self.path, "AVI keeps a constant frame rate: timestamps must be frame index / fps")
        for frame in frames:
            self._writer.write(np.ascontiguousarray(frame))

    def _finish(self) -> None:
        self._writer.release()
        set_frame_rate(self.path, self.fps)


def set_frame_rate(path: Path, fps: float) -> None:
    """Stamp ``fps`` into an AVI's main header (µs per frame) and its video stream header (dwRate / dwScale).

    The stream's frames keep their order and count; only the time between them changes.
    """
    rate = Fraction(fps).limit_denominator(1000)
    if not (0 < rate.numerator < 2**32 and math.isclose(float(rate), fps, rel_tol=1e-6)):
        raise MeniscopeError(path, f"frame rate {fps} cannot be stored in an AVI header")
    with open(path, "r+b") as f:
        head = f.read(CHUNK.size + 4 + CHUNK.size + 4)  # RIFF AVI, LIST hdrl
        kind, size = CHUNK.unpack_from(head, CHUNK.size + 4)
        if head[:4] != RIFF_MAGIC or kind != b"LIST" or head[-4:] != b"hdrl":
            raise MeniscopeError(path, "the AVI written has no header list where expected")
        hdrl = f.read(size - 4)
        base = len(head)
        avih = _chunk(path, hdrl, b"avih")
        strl = _chunk(path, hdrl, b"LIST", b"strl")
        strh = strl + _chunk(path, hdrl[strl:], b"strh")
        f.seek(base + avih)
        f.write(struct.pack("<I", round(1e6 / fps)))
        f.seek(base + strh + 20)  # after fccType, fccHandler, dwFlags, wPriority, wLanguage, dwInitialFrames
        f.write(struct.pack("<II", rate.denominator, rate.numerator))


def _chunk(path: Path, data: bytes, kind: bytes, list_type: bytes | None = None) -> int:
    """Offset in ``data`` of the first data byte of chunk ``kind`` (after a LIST's type when ``list_type``)."""
    pos = 0
    while pos + CHUNK.size <= len(data):
        found, size = CHUNK.unpack_from(data, pos)
        start = pos + CHUNK.size
        if found == kind and (list_type is None or data[start : start + 4] == list_type):
            return start + (4 if list_type else 0)
        pos = start + size + size % 2
    raise MeniscopeError(path, f"the AVI header has no {(list_type or kind).decode()} chunk")
