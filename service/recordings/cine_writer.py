"""Phantom .cine writer: grey or raw CFA (Bayer) frames, 8- or 16-bit words or packed 10/12-bit, streamed to disk.

The structures are those of :mod:`service.recordings.cine`, each found through the file header's
offsets as the format intends; their order lets batches go straight to disk::

    CINEFILEHEADER, BITMAPINFOHEADER   at 0 and 44; written on open, the file header patched on close
    images, in write order             AnnotationSize 8, ImageSize, pixels: words bottom row first (BI_RGB),
                                       or packed 10/12-bit top row first, most significant bit first
    SETUP (10,412 B), tagged blocks    on close: 1002 (a TIME64 per image), 1003 (exposure per image,
                                       0: unknown; PIMS requires the block)
    image offsets (int64 per image)    on close

The price of images first: the header's offsets of SETUP and of the offset table are 32-bit, so a
file holds at most 4 GiB; :meth:`CineWriter.write` refuses a batch that would pass it. SETUP says
BlackLevel 0 and WhiteLevel ``2**bit_depth - 1``, so pycine's linear rescaling returns the words as
written; SoftwareVersion 751 names the SETUP layout used (through dFrameRate), CreatedBy "meniscope".
The trigger time is the moment the writer was opened; frame times are stored relative to it.
A colour camera's raw mosaic (``cfa``) is written as Phantom does: Compression 2 (uninterpolated),
SETUP.CFA naming the pattern, bEnableColor set and the white balance's red and blue gains in WBGain[0].
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
    CC_UNINT,
    CFA_PATTERNS,
    FILE_HEADER,
    MAGIC,
    PACKED,
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
#: Pattern -> the SETUP.CFA code written for it (grbg has no code of its own: see CFA_PATTERNS).
CFA_CODES = {pattern: code for code, pattern in sorted(CFA_PATTERNS.items())}
#: Packed bit depth -> BITMAPINFOHEADER.biCompression.
PACKED_COMPRESSION = {bits: compression for compression, (_, bits) in PACKED.items()}
#: Bit depths stored in 8- or 16-bit words.
WORD_BIT_DEPTHS = (8, 12, 16)


def pack_msb_first(frames: np.ndarray, bits: int) -> np.ndarray:
    """Phantom's packed layout: each value's ``bits`` bits, most significant first, one stream per frame.

    Parameters
    ----------
    frames : ndarray of shape (N, H, W), values below ``2**bits`` (``H * W * bits`` a multiple of 8)

    Returns
    -------
    ndarray of shape (N, H * W * bits // 8), uint8
    """
    n = len(frames)
    planes = (frames.reshape(n, -1, 1).astype(np.uint16) >> np.arange(bits - 1, -1, -1, dtype=np.uint16)) & 1
    return np.packbits(planes.astype(np.uint8).reshape(n, -1), axis=1)


#: Bytes per image behind the images: a TIME64, an exposure (uint32) and an offset (int64).
PER_IMAGE_INDEX_BYTES = 8 + 4 + 8


class CineWriter(RecordingWriter):
    """Streams frames into a new .cine file; :meth:`close` writes SETUP, time stamps and offsets."""

    BIT_DEPTHS = (8, 10, 12, 16)  # 10 packed only

    def __init__(
        self,
        path: Path,
        width: int,
        height: int,
        fps: float,
        bit_depth: int = 8,
        trigger_frame: int = 0,
        *,
        packed: bool = False,
        cfa: str | None = None,
        white_balance: tuple[float, float] = (1.0, 1.0),
    ) -> None:
        """``packed``: 10 or 12 bits per pixel in one bit stream (Phantom's packed formats) instead of
        8/16-bit words; ``cfa``: the frames are a colour sensor's raw mosaic with this Bayer pattern
        (display order; see :data:`CFA_CODES`), ``white_balance`` its red and blue gains."""
        super().__init__(path, width, height, fps, bit_depth, trigger_frame)
        if not -(2**31) < self.trigger_frame < 2**31:
            raise MeniscopeError(self.path, f"trigger frame {self.trigger_frame} does not fit the header's 32 bits")
        if bit_depth not in (PACKED_COMPRESSION if packed else WORD_BIT_DEPTHS):
            raise MeniscopeError(
                self.path,
                f"bit depth {bit_depth} cannot be stored {'packed' if packed else 'in words'}: "
                "packed takes 10 or 12 bits, words 8, 12 or 16",
            )
        if packed and self.width * self.height * bit_depth % 8:
            raise MeniscopeError(
                self.path, f"packed {bit_depth}-bit images of {self.width} x {self.height} px do not fill whole bytes"
            )
        if cfa is not None and cfa not in CFA_CODES:
            raise MeniscopeError(self.path, f"CFA pattern {cfa!r} is not one of {', '.join(CFA_CODES)}")
        self.packed, self.cfa, self.white_balance = packed, cfa, white_balance
        self._word = np.dtype("<u1" if bit_depth == 8 else "<u2")
        self._frame_bytes = self.width * self.height * (bit_depth if packed else 8 * self._word.itemsize) // 8
        self._trigger = int(time.time() * TIME64_ONE_SECOND)  # TIME64 of the trigger: now
        self._offsets = [np.empty(0, np.int64)]
        self._ticks = [np.empty(0, np.uint64)]
        bitmap = BITMAP_INFO.pack(
            BITMAP_INFO.size,
            self.width,
            self.height,
            1,
            bit_depth if packed else 8 * self._word.itemsize,
            PACKED_COMPRESSION[bit_depth] if packed else BI_RGB,
            self._frame_bytes,
            0,
            0,
            0,
            2**bit_depth,
        )
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
        if self.packed:  # top row first
            batch[:, ANNOTATION.size :] = pack_msb_first(frames, self.bit_depth)
        else:  # bottom row first
            batch[:, ANNOTATION.size :] = (
                np.ascontiguousarray(frames[:, ::-1], dtype=self._word).reshape(n, -1).view(np.uint8)
            )
        self._put(batch)
        self._offsets.append(self._end + record * np.arange(n, dtype=np.int64))
        self._ticks.append(ticks)
        self._end += n * record

    def _time64(self, seconds: np.ndarray) -> np.ndarray:
        """Seconds from the trigger as absolute TIME64 (32.32 fixed point), shape like ``seconds``, uint64."""
        trigger_s = self._trigger / TIME64_ONE_SECOND
        if not (
            (seconds >= -trigger_s) & (seconds < TIME64_SECONDS_LIMIT - trigger_s) & (np.abs(seconds) < 2**31)
        ).all():
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
        return FILE_HEADER.pack(
            MAGIC,
            FILE_HEADER.size,
            CC_RGB if self.cfa is None else CC_UNINT,
            VERSION,
            first,
            count,
            first,
            count,
            FILE_HEADER.size,
            off_setup,
            off_offsets,
            self._trigger,
        )

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
        if self.cfa is not None:
            values |= {
                "CFA": CFA_CODES[self.cfa],
                "bEnableColor": 1,
                "WBGainR": self.white_balance[0],
                "WBGainB": self.white_balance[1],
            }
        setup = bytearray(SETUP_LENGTH)
        SETUP_MARK_AND_LENGTH.pack_into(setup, SETUP_MARK_OFFSET, SETUP_MARK, SETUP_LENGTH)
        for name, value in values.items():
            offset, fmt = SETUP_FIELDS[name]
            struct.pack_into(fmt, setup, offset, value)
        return bytes(setup)
