"""An AVI's own account of itself, read from its RIFF structure: what the headers claim and what the stream holds.

OpenCV (FFmpeg) trusts the headers: a frame count of 3 in ``strh`` makes it read 3 of 760 frames, a
frame count of 10**9 makes the reader allocate gigabytes, a bogus ``biWidth`` decodes frames that wide.
:func:`scan` walks the chunks (the ``hdrl`` headers and every ``movi`` list, OpenDML ``AVIX`` segments
included) so that the reader can hold the headers against the stream and refuse a file where they
disagree. Only chunk headers are read: 8 bytes per frame, no pixels.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from service.errors import MeniscopeError

CHUNK = struct.Struct("<4sI")  # chunk id, size of the data that follows
AVIH = struct.Struct("<IIIIIIIIII")  # dwMicroSecPerFrame .. dwWidth, dwHeight
STRH = struct.Struct("<4s4sIHHIIIIIIII")  # fccType, fccHandler, .., dwScale, dwRate, dwStart, dwLength, ..
BITMAP = struct.Struct("<Iii")  # biSize, biWidth, biHeight


@dataclass(frozen=True)
class AviLayout:
    """The video stream as the headers describe it and as its chunks hold it."""

    width: int  # strf biWidth
    height: int  # |strf biHeight| (negative: top-down rows)
    main_size: tuple[int, int]  # avih dwWidth, dwHeight
    header_frames: int  # strh dwLength of the video stream
    total_frames: int  # avih dwTotalFrames (the first RIFF segment only, in OpenDML files)
    stream_frames: int  # video chunks found in the movi lists


def scan(path: Path) -> AviLayout:
    """The layout of the AVI at ``path``, or an error naming the first chunk that is missing or runs past its end."""
    try:
        with open(path, "rb") as f:
            size = f.seek(0, 2)
            return _Walk(path, f, size).run()
    except OSError as exc:
        raise MeniscopeError(path, f"cannot read: {exc.strerror or exc}") from None


class _Walk:
    """One pass over the chunks of a file of ``size`` bytes."""

    def __init__(self, path: Path, f: BinaryIO, size: int) -> None:
        self.path, self.f, self.size = path, f, size
        self.video: int | None = None  # index of the video stream
        self.header: tuple[int, int, int, int] | None = None  # width, height, dwLength, dwTotalFrames
        self.main_size = (0, 0)
        self.frames = 0

    def run(self) -> AviLayout:
        pos, segment = 0, 0
        while pos + CHUNK.size + 4 <= self.size:
            kind, length = self._chunk(pos)
            form = self._read(pos + CHUNK.size, 4)
            if kind != b"RIFF" or form != (b"AVI " if segment == 0 else b"AVIX"):
                if segment == 0:
                    raise MeniscopeError(self.path, "not an AVI file (it does not start with 'RIFF....AVI ')")
                break  # trailing bytes after the last segment: FFmpeg ignores them too
            self._list(pos + CHUNK.size + 4, self._end(pos, length, "RIFF segment"))
            pos += CHUNK.size + length + length % 2
            segment += 1
        if segment == 0:
            raise MeniscopeError(self.path, "truncated: no complete RIFF header")
        if self.header is None or self.video is None:
            raise MeniscopeError(self.path, "the AVI has no video stream header (hdrl/strl/strh 'vids' and strf)")
        width, height, length, total = self.header
        return AviLayout(width, height, self.main_size, length, total, self.frames)

    def _end(self, pos: int, length: int, what: str) -> int:
        end = pos + CHUNK.size + length
        if end > self.size:
            raise MeniscopeError(
                self.path,
                f"truncated or corrupt: the {what} at byte {pos} claims {length} bytes, past the end "
                f"of the file ({self.size} bytes)",
            )
        return end

    def _read(self, pos: int, count: int) -> bytes:
        self.f.seek(pos)
        return self.f.read(count)

    def _chunk(self, pos: int) -> tuple[bytes, int]:
        return CHUNK.unpack(self._read(pos, CHUNK.size))

    def _list(self, pos: int, end: int) -> None:
        """The chunks from ``pos`` to ``end``: headers parsed in ``hdrl``, video chunks counted in ``movi``."""
        while pos + CHUNK.size <= end:
            kind, length = self._chunk(pos)
            chunk_end = pos + CHUNK.size + length
            if chunk_end > end:
                raise MeniscopeError(
                    self.path,
                    f"truncated or corrupt: chunk {kind!r} at byte {pos} claims {length} "
                    f"bytes, past the end of its list at byte {end}",
                )
            if kind == b"LIST" and length >= 4:
                form = self._read(pos + CHUNK.size, 4)
                if form == b"hdrl" and self.header is None:
                    self._headers(pos + CHUNK.size + 4, chunk_end)
                elif form in (b"movi", b"rec "):
                    self._list(pos + CHUNK.size + 4, chunk_end)
            elif self.video is not None and kind[:2] == b"%02d" % self.video and kind[2:] in (b"dc", b"db"):
                self.frames += 1
            pos = chunk_end + length % 2

    def _headers(self, pos: int, end: int) -> None:
        """``avih`` and the first video stream's ``strh`` and ``strf`` in the header list."""
        total, stream = 0, 0
        while pos + CHUNK.size <= end:
            kind, length = self._chunk(pos)
            body = pos + CHUNK.size
            if body + length > end:
                raise MeniscopeError(
                    self.path, f"corrupt header: chunk {kind!r} at byte {pos} runs past the header list"
                )
            if kind == b"avih" and length >= AVIH.size:
                fields = AVIH.unpack(self._read(body, AVIH.size))
                total, self.main_size = fields[4], (fields[8], fields[9])
            elif kind == b"LIST" and self._read(body, 4) == b"strl":
                if self.video is None:
                    self._stream(stream, body + 4, body + length, total)
                stream += 1
            pos = body + length + length % 2

    def _stream(self, index: int, pos: int, end: int, total: int) -> None:
        """A stream list: when it is video, its index, size and frame count."""
        is_video, length_frames = False, 0
        while pos + CHUNK.size <= end:
            kind, length = self._chunk(pos)
            body = pos + CHUNK.size
            if kind == b"strh" and length >= STRH.size:
                fields = STRH.unpack(self._read(body, STRH.size))
                is_video, length_frames = fields[0] == b"vids", fields[9]
            elif kind == b"strf" and is_video and length >= BITMAP.size:
                _, width, height = BITMAP.unpack(self._read(body, BITMAP.size))
                self.video, self.header = index, (width, abs(height), length_frames, total)
                return
            pos = body + length + length % 2
