"""Phantom .cine writer: grey frames (8-bit, or 12/16 significant bits in 16-bit words) streamed to disk.

The structures are those of :mod:`service.recordings.cine`, each found through the file header's
offsets as the format intends; their order lets batches go straight to disk::

    CINEFILEHEADER, BITMAPINFOHEADER   at 0 and 44; written on open, the file header patched on close
    images, in write order             AnnotationSize 8, ImageSize, pixels bottom row first (BI_RGB)
    SETUP (10,412 B), tagged blocks    on close: 1002 (a TIME64 per image), 1003 (exposure per image,
                                       0: unknown; PIMS requires the block)
    image offsets (int64 per image)    on close

The price of images first: the header's offsets of SETUP and of the offset table are 32-bit, so a
file holds at most 4 GiB; :meth:`CineWriter.write` refuses a batch that would pass it. SETUP says
BlackLevel 0 and WhiteLevel ``2**bit_depth - 1``, so pycine's linear rescaling returns the words as
written; SoftwareVersion 751 names the SETUP layout used (through dFrameRate), CreatedBy "meniscope".
The trigger time is the moment the writer was opened; frame times are stored relative to it.
"""
from __future__ import annotations

import struct
import time
from pathlib import Path

import numpy as np

from service.errors import MeniscopeError
from service.recordings.base import RecordingWriter
from service.recordings.cine import (
    ANNOTATION,
    BI_RGB,
    BITMAP_INFO,
    CC_RGB,
    FILE_HEADER,
    MAGIC,
    SETUP_FIELDS,
    SETUP_LENGTH,
    SETUP_MARK,
    SETUP_MARK_AND_LENGTH,
    SETUP_MARK_OFFSET,
    TAG_EXPOSURE_ONLY,
    TAG_TIME_ONLY,
    TAGGED_BLOCK,
    TIME64_ONE_SECOND,
    VERSION,
)

#: Software version whose SETUP layout this writer follows (the last field, dFrameRate, came with 751).
SOFTWARE_VERSION = 751
#: Bytes the header's 32-bit offsets can reach.
OFFSET_LIMIT = 2**32
#: TIME64 counts whole seconds in 32 bits: 1970 to 2106.
TIME64_SECONDS_LIMIT = 2**32
#: Bytes per image behind the images: a TIME64, an exposure (uint32) and an offset (int64).
PER_IMAGE_INDEX_BYTES = 8 + 4 + 8


class CineWriter(RecordingWriter):
    """Streams frames into a new .cine file; :meth:`close` writes SETUP, time stamps and offsets."""

    def __init__(self, path: Path, width: int, height: int, fps: float, bit_depth: int = 8,
                 trigger_frame: int = 0) -> None:
        super().__init__(path, width, height, fps, bit_depth, trigger_frame)
        if not -(2**31) < self.trigger_frame < 2**31:
            raise MeniscopeError(self.path, f"trigger frame {self.trigger_frame} does not fit the header's 32 bits")
        self._word = np.dtype("<u1" if bit_depth == 8 else "<u2")
        self._frame_bytes = self.width * self.height * self._word.itemsize
        self._trigger = int(time.time() * TIME64_ONE_SECOND)  # TIME64 of the trigger: now
        self._offsets = [np.empty(0, np.int64)]
        self._ticks = [np.empty(0, np.uint64)]
        bitmap = BITMAP_INFO.pack(BITMAP_INFO.size, self.width, self.height, 1, 8 * self._word.itemsize, BI_RGB,
                                  self._frame_bytes, 0, 0, 0, 2**bit_depth)
        try:
            self._file = open(self.path, "wb")
        except OSError as exc:
            raise MeniscopeError(self.path, f"cannot write: {exc.strerror or exc}") from None
        self._put(self._file_header(0, 0, 0) + bitmap)
        self._end = FILE_HEADER.size + BITMAP_INFO.size

    def _append(self, frames: np.ndarray, timestamps: np.ndarray | None) -> None:
        n = len(frames)
        ticks = self._time64(self.nominal_times(n) if timestamps is None else timestamps)
        record = ANNOTATION.size + self._frame_bytes
        total = self.frames_written + n
        if self._end + n * record + SETUP_LENGTH + 2 * TAGGED_BLOCK.size + PER_IMAGE_INDEX_BYTES * total > OFFSET_LIMIT:
            raise MeniscopeError(
                self.path,
                f"{total} frames of {self.width} x {self.height} px would pass the 4 GiB a .cine written "
                "images-first can address; split the recording or write a smaller region",
            )
        batch = np.empty((n, record), np.uint8)  # per image: annotation, then pixels bottom row first
        batch[:, : ANNOTATION.size] = np.frombuffer(ANNOTATION.pack(ANNOTATION.size, self._frame_bytes), np.uint8)
        batch[:, ANNOTATION.size :] = np.ascontiguousarray(frames[:, ::-1], dtype=self._word).reshape(n, -1).view(np.uint8)
        self._put(batch)
        self._offsets.append(self._end + record * np.arange(n, dtype=np.int64))
        self._ticks.append(ticks)
        self._end += n * record

    def _time64(self, seconds: np.ndarray) -> np.ndarray:
        """Seconds from the trigger as absolute TIME64 (32.32 fixed point), shape like ``seconds``, uint64."""
        trigger_s = self._trigger / TIME64_ONE_SECOND
        if not ((seconds >= -trigger_s) & (seconds < TIME64_SECONDS_LIMIT - trigger_s) & (np.abs(seconds) < 2**31)).all():
            raise MeniscopeError(
                self.path, "timestamps must lie within 68 years of the trigger and between 1970 and 2106"
            )
        relative = np.rint(seconds * TIME64_ONE_SECOND).astype(np.int64).view(np.uint64)
        return relative + np.uint64(self._trigger)  # modulo 2**64: the sum is in range, checked above

    def _finish(self) -> None:
        count = self.frames_written
        ticks = np.concatenate(self._ticks)
        blocks = (
            TAGGED_BLOCK.pack(TAGGED_BLOCK.size + 8 * count, TAG_TIME_ONLY, 1)  # Reserved 1: another block follows
            + ticks.astype("<u8").tobytes()
            + TAGGED_BLOCK.pack(TAGGED_BLOCK.size + 4 * count, TAG_EXPOSURE_ONLY, 0)
            + bytes(4 * count)
        )
        off_setup = self._end
        off_offsets = off_setup + SETUP_LENGTH + len(blocks)
        try:
            self._put(self._setup() + blocks + np.concatenate(self._offsets).astype("<i8").tobytes())
            self._file.seek(0)
            self._put(self._file_header(count, off_setup, off_offsets))
        finally:
            self._file.close()

    def _put(self, data: bytes | np.ndarray) -> None:
        """Write to the file; a failing disk becomes a one-line error."""
        try:
            self._file.write(data)
        except OSError as exc:
            raise MeniscopeError(self.path, f"cannot write: {exc.strerror or exc}") from None

    def _file_header(self, count: int, off_setup: int, off_offsets: int) -> bytes:
        """CINEFILEHEADER for ``count`` images with the trigger at frame ``trigger_frame``."""
        first = -self.trigger_frame
        return FILE_HEADER.pack(MAGIC, FILE_HEADER.size, CC_RGB, VERSION, first, count, first, count,
                                FILE_HEADER.size, off_setup, off_offsets, self._trigger)

    def _setup(self) -> bytes:
        """The SETUP block: frame rate, size, bit depth, black and white levels, creator."""
        values = {
            "FrameRate16": min(round(self.fps), 0xFFFF),
            "FrameRate": min(round(self.fps), 0xFFFFFFFF),
            "dFrameRate": self.fps,
            "fDecimation": 1.0,
            "ImWidth": self.width,
            "ImHeight": self.height,
            "SoftwareVersion": SOFTWARE_VERSION,
            "RealBPP": self.bit_depth,
            "RecBPP": self.bit_depth,
            "BlackLevel": 0,
            "WhiteLevel": 2**self.bit_depth - 1,
            "CreatedBy": b"meniscope",
        }
        setup = bytearray(SETUP_LENGTH)
        SETUP_MARK_AND_LENGTH.pack_into(setup, SETUP_MARK_OFFSET, SETUP_MARK, SETUP_LENGTH)
        for name, value in values.items():
            offset, fmt = SETUP_FIELDS[name]
            struct.pack_into(fmt, setup, offset, value)
        return bytes(setup)
