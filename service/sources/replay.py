"""Replay of a recording (.cine, .avi) as if it were a live camera: paced by its own timestamps, looping on request.

``speed`` scales the recorded rate (1 = as recorded, 0.1 = ten times slower, 0 or "max" = as fast as the
file reads). Frame indices are positions in the file (0..N-1); with ``loop`` they keep increasing across
passes and the timestamps continue, each pass one recorded duration plus one frame period after the last.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any
from urllib.parse import SplitResult, unquote, urlencode

import numpy as np

from service.errors import MeniscopeError
from service.recordings import Recording, open_recording
from service.sources.base import FrameBatch, FrameSource, SourceOptions, StreamFormat, parse_options
from service.sources.pacing import Pacer, Speed


def replay_uri(path: Path | str, **options: Any) -> str:
    """The source URI replaying the recording at ``path`` (relative paths made absolute, the path quoted) with
    ``options`` (``speed``, ``loop``, ...) as its query."""
    uri = Path(path).resolve().as_uri()
    return f"{uri}?{urlencode(options)}" if options else uri


class ReplayOptions(SourceOptions):
    speed: Speed = 1.0
    loop: bool = False


class ReplaySource(FrameSource):
    """A recording delivered at ``speed`` x its recorded rate, in batches, on a drift-free schedule.

    With ``views``, batches are read-only views of the reader's mapping of the file where it has one
    (:meth:`Recording.view_grey`: no copy), checked against the file's size when read; a file cut shorter after
    that, while its frames are still read, ends the process with SIGBUS instead of an error: for a reader that
    measures each batch at once (``meniscope analyze``), not for a long-running service."""

    kind = "replay"

    def __init__(
        self,
        path: str | Path,
        *,
        speed: float = 1.0,
        loop: bool = False,
        timeout: float = 0.1,
        uri: str | None = None,
        views: bool = False,
    ) -> None:
        super().__init__(uri or str(path), timeout)
        self.path = Path(path)
        self.speed, self.loop, self.views = speed, loop, views
        self._recording: Recording | None = None
        self._times = np.empty(0)
        self._period = 0.0
        self._next = 0
        self._pacer = Pacer(speed)
        self._identity: tuple[int, int, int, int] | None = None  # the file's (device, inode, size, mtime) when opened

    @classmethod
    def from_uri(cls, uri: str, parts: SplitResult, options: Mapping[str, Any]) -> ReplaySource:
        if parts.netloc not in ("", "localhost"):
            raise MeniscopeError(uri, "a file URI names a local file: file:///path/to/rec.cine")
        opts = parse_options(ReplayOptions, uri, options)
        return cls(unquote(parts.path), speed=opts.speed, loop=opts.loop, timeout=opts.timeout, uri=uri)

    def _open(self) -> StreamFormat:
        rec = open_recording(self.path)
        self._identity = self._file_identity()
        n = len(rec)
        if n == 0:
            rec.close()
            raise MeniscopeError(self.path, "the recording has no frames to replay")
        times = rec.timestamps
        if not np.all(np.diff(times) > 0):  # a file whose clock stalls or jumps back: pace by the frame rate
            times = (np.arange(n) - rec.trigger_frame) / rec.fps
        self._recording, self._times, self._next = rec, times, 0
        self._period = float(times[-1] - times[0]) + 1.0 / rec.fps
        self._pacer.start(float(times[0]))
        return StreamFormat(rec.width, rec.height, rec.dtype, rec.bit_depth, rec.fps)

    @property
    def mapped(self) -> np.ndarray | None:
        """The open recording's file as its reader holds it mapped in memory (:attr:`Recording.mapped`), or None."""
        return None if self._recording is None else self._recording.mapped

    @property
    def frames(self) -> int:
        """Frames in one pass of the recording."""
        if not self.is_open:
            raise MeniscopeError(self.uri, "the source is not open")
        return len(self._times)

    def _file_identity(self) -> tuple[int, int, int, int]:
        try:
            st = os.stat(self.path)
        except OSError as exc:
            raise MeniscopeError(self.path, f"the recording is gone while replayed: {exc.strerror or exc}") from None
        return st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns

    def _read(self, max_frames: int) -> FrameBatch | None:
        if self._file_identity() != self._identity:
            raise MeniscopeError(
                self.path,
                "the recording changed on disk while replayed (truncated, overwritten or "
                "replaced): it will be opened afresh",
            )
        n = len(self._times)
        start = self._next
        if not self.loop:
            if start >= n:
                return None
            max_frames = min(max_frames, n - start)
        indices = np.arange(start, start + max_frames, dtype=np.int64)
        times = self._time(indices)
        self._pacer.wait(float(times[-1]), self.timeout)
        due = int(np.searchsorted(times, self._pacer.now(), side="right"))
        if due == 0:
            return self.empty_batch()
        self._next += due
        return FrameBatch(self._pixels(start, due), indices[:due], times[:due])

    def _time(self, indices: np.ndarray) -> np.ndarray:
        """Timestamps (s) of frame indices (N,) counted across loop passes."""
        passes, pos = np.divmod(indices, len(self._times))
        return self._times[pos] + passes * self._period

    def _pixels(self, start: int, count: int) -> np.ndarray:
        """Frames ``start .. start + count - 1`` counted across passes, shape (count, H, W)."""
        assert self._recording is not None
        n = len(self._times)
        pieces = []
        while count > 0:
            pos = start % n
            take = min(count, n - pos)
            read = self._recording.view_grey if self.views else self._recording.read_grey
            pieces.append(read(pos, take))
            start, count = start + take, count - take
        return pieces[0] if len(pieces) == 1 else np.concatenate(pieces)

    def _close(self) -> None:
        if self._recording is not None:
            self._recording.close()
            self._recording = None

    def _details(self) -> dict[str, Any]:
        return {
            "path": str(self.path),
            "speed": self.speed,
            "loop": self.loop,
            "frames_in_file": len(self._times),
            "position": self._next,
        }
