"""The interfaces every recording reader and writer follows: pixel words exactly as stored, rows top first.

Readers expose the file's own facts (frame rate, bit depth, per-frame times, trigger frame, header
fields) and random access to frames; writers append frame batches and finish the file on close.
"""

from __future__ import annotations

import math
import operator
from abc import ABC, abstractmethod
from pathlib import Path
from types import TracebackType
from typing import Any, ClassVar

import numpy as np

from service.errors import MeniscopeError, require_folder_of

#: Bayer pattern (display order) -> the name of OpenCV's demosaicing to grey (OpenCV loads when a mosaic is read,
#: not to open a file); OpenCV names the patterns by their sensor layout in its 4.x aliases (the older names counted
#: from the second row and column).
BAYER_TO_GREY = {
    "rggb": "COLOR_BayerRGGB2GRAY",
    "grbg": "COLOR_BayerGRBG2GRAY",
    "gbrg": "COLOR_BayerGBRG2GRAY",
    "bggr": "COLOR_BayerBGGR2GRAY",
}

#: Largest frame side any writer accepts (16-bit fields in the .cine SETUP; FFmpeg's own limit is larger).
MAX_SIDE = 65535
#: Frame rates a recording may claim, frames per second: beyond them a header is corrupt (the fastest
#: Phantom records a few million frames/s), and times computed from them would not be finite.
FPS_RANGE = (1e-3, 1e8)


class Recording(ABC):
    """A recorded video opened for reading: frame count, rate, size, depth, times and random access.

    Attributes
    ----------
    path : Path
        The file.
    frame_count : int
        Number of frames, N (also ``len(recording)``).
    fps : float
        Rate of the stored frames in frames per second (after any decimation when the file was saved).
    width, height : int
        Frame size in pixels.
    bit_depth : int
        Significant bits per pixel (a 12-bit camera stores 12 in 16-bit words).
    dtype : numpy.dtype
        ``uint8`` or ``uint16``: the type :meth:`read` returns.
    timestamps : ndarray of shape (N,), float64
        Seconds from the trigger (frame ``trigger_frame`` is at 0); from the file when it stores
        per-frame times (``timestamps_source == "file"``), else ``(i - trigger_frame) / fps``.
    trigger_frame : int
        Index of the trigger frame; may lie outside ``0..N-1`` when the file holds only part of a take.
    cfa : str or None
        A colour camera's raw mosaic: its 2 x 2 Bayer pattern in display order ("rggb", "gbrg",
        "grbg", "bggr"); None for grey frames.
    header : dict
        Further header fields, JSON-safe (camera, software version, decimation, ...).
    """

    format: ClassVar[str]

    def __init__(
        self,
        path: Path,
        *,
        frame_count: int,
        fps: float,
        width: int,
        height: int,
        bit_depth: int,
        dtype: np.dtype,
        timestamps: np.ndarray | None,
        trigger_frame: int,
        header: dict[str, Any],
        cfa: str | None = None,
    ) -> None:
        low, high = FPS_RANGE
        if not (math.isfinite(fps) and low <= fps <= high):
            raise MeniscopeError(path, f"corrupt header: frame rate {fps} is outside {low:g}..{high:g} frames/s")
        size = Path(path).stat().st_size
        if not 0 <= frame_count <= size:  # every frame takes at least one byte
            raise MeniscopeError(path, f"corrupt header: {frame_count} frames cannot fit in a file of {size} bytes")
        self.path = Path(path)
        self.frame_count = int(frame_count)
        self.fps = float(fps)
        self.width = int(width)
        self.height = int(height)
        self.bit_depth = int(bit_depth)
        self.dtype = np.dtype(dtype)
        self.trigger_frame = int(trigger_frame)
        self.timestamps_source = "frame_rate" if timestamps is None else "file"
        if timestamps is None:
            timestamps = (np.arange(self.frame_count) - self.trigger_frame) / self.fps
        self.timestamps = np.asarray(timestamps, dtype=np.float64)
        self.timestamps.setflags(write=False)
        self.cfa = cfa
        self.header = header
        self.closed = False

    def __len__(self) -> int:
        return self.frame_count

    def frame_range(self, start: int, count: int) -> range:
        """The frame indices ``start .. start + count - 1``, or an error naming the file when they do not exist."""
        start, count = operator.index(start), operator.index(count)
        if self.closed:
            raise MeniscopeError(self.path, "the recording is closed")
        if start < 0 or count < 0 or start + count > self.frame_count:
            raise MeniscopeError(
                self.path,
                f"cannot read {count} frame(s) from frame {start}: the recording has frames 0..{self.frame_count - 1}",
            )
        return range(start, start + count)

    def read(self, start: int, count: int) -> np.ndarray:
        """Frames ``start .. start + count - 1`` as stored (no scaling), rows top first.

        Returns
        -------
        ndarray of shape (count, height, width), ``self.dtype``
            A new array (one copy of the stored words).
        """
        frames = self.frame_range(start, count)
        if not frames:
            return np.empty((0, self.height, self.width), self.dtype)
        return self._read(frames.start, len(frames))

    def read_grey(self, start: int, count: int) -> np.ndarray:
        """Frames as the inverse models see them: :meth:`read`'s, with a raw mosaic demosaiced to grey.

        OpenCV's bilinear Bayer demosaicing to grey (0.299 R + 0.587 G + 0.114 B, in the stored
        units; the recorded white balance is a viewing setting and is not applied), so a colour
        camera's frames keep the shape, type and range of a grey camera's.
        """
        frames = self.read(start, count)
        if self.cfa is None:
            return frames
        import cv2

        code = getattr(cv2, BAYER_TO_GREY[self.cfa])
        return np.stack([cv2.cvtColor(frame, code) for frame in frames]) if len(frames) else frames

    def view_grey(self, start: int, count: int) -> np.ndarray:
        """:meth:`read_grey`'s frames without a copy where the reader can give them so: a read-only view of the file's
        mapping (:meth:`_view`), valid after :meth:`close`; else :meth:`read_grey`'s copy."""
        frames = self.frame_range(start, count)
        view = self._view(frames.start, len(frames)) if frames and self.cfa is None else None
        return self.read_grey(start, count) if view is None else view

    def _view(self, start: int, count: int) -> np.ndarray | None:
        """Frames ``start .. start + count - 1`` (range-checked, ``count >= 1``) as a read-only view of the mapped
        file, (count, height, width) in display order, or None where the reader cannot view them."""
        return None

    def __getitem__(self, index: int) -> np.ndarray:
        """One frame, shape (height, width); negative indices count from the end."""
        i = operator.index(index)
        if i < 0:
            i += self.frame_count
        if not 0 <= i < self.frame_count:
            raise IndexError(f"frame {index} out of range for {self.frame_count} frames")
        return self.read(i, 1)[0]

    def info(self) -> dict[str, Any]:
        """What ``meniscope info`` prints: the common facts, a summary of the times, then the header fields."""
        t = self.timestamps
        first, last = (float(t[0]), float(t[-1])) if len(t) else (None, None)
        span = last - first if len(t) > 1 else 0.0
        return {
            "path": str(self.path),
            "format": self.format,
            "frames": self.frame_count,
            "fps": self.fps,
            "width": self.width,
            "height": self.height,
            "bit_depth": self.bit_depth,
            "dtype": self.dtype.name,
            "cfa": self.cfa,
            "trigger_frame": self.trigger_frame,
            "timestamps": {
                "source": self.timestamps_source,
                "first_s": first,
                "last_s": last,
                "mean_fps": (len(t) - 1) / span if span > 0 else None,
            },
            **self.header,
        }

    @abstractmethod
    def _read(self, start: int, count: int) -> np.ndarray:
        """Frames ``start .. start + count - 1`` (range-checked, ``count >= 1``), shape (count, height, width)."""

    @property
    def mapped(self) -> np.ndarray | None:
        """The whole file's bytes (uint8) as this reader holds them mapped in memory, or None where it does not map
        the file: what a digest of the file can read without mapping it again."""
        return None

    @abstractmethod
    def _release(self) -> None:
        """Let go of the file (frames already returned stay valid)."""

    def close(self) -> None:
        """Release the file; reading afterwards is an error, closing again does nothing."""
        if not self.closed:
            self.closed = True
            self._release()

    def __enter__(self) -> Recording:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


class RecordingWriter(ABC):
    """A recording being written: frame batches appended with :meth:`write`, the file finished by :meth:`close`.

    Frames are integer arrays of shape (N, height, width) whose values fit in ``bit_depth`` bits; they
    are stored as uint8 (``bit_depth`` 8) or uint16 words, rows top first. Times are seconds from the
    trigger; without them frame ``i`` (counted over the whole file) is at ``(i - trigger_frame) / fps``.
    """

    #: The bit depths the format stores.
    BIT_DEPTHS: ClassVar[tuple[int, ...]] = (8, 12, 16)

    def __init__(self, path: Path, width: int, height: int, fps: float, bit_depth: int, trigger_frame: int) -> None:
        self.path = Path(path)
        require_folder_of(self.path)
        for name, side in (("width", width), ("height", height)):
            if operator.index(side) < 1 or side > MAX_SIDE:
                raise MeniscopeError(self.path, f"{name} {side} px is outside 1..{MAX_SIDE}")
        if not (math.isfinite(fps) and fps > 0):
            raise MeniscopeError(self.path, f"frame rate {fps} is not a positive number")
        if bit_depth not in self.BIT_DEPTHS:
            raise MeniscopeError(
                self.path, f"bit depth {bit_depth} is not one of {', '.join(map(str, self.BIT_DEPTHS))}"
            )
        self.width, self.height = int(width), int(height)
        self.fps = float(fps)
        self.bit_depth = int(bit_depth)
        self.trigger_frame = operator.index(trigger_frame)
        self.dtype = np.dtype(np.uint8 if bit_depth == 8 else np.uint16)
        self.frames_written = 0
        self.closed = False

    def write(self, frames: np.ndarray, timestamps: np.ndarray | None = None) -> None:
        """Append frames, shape (N, height, width), with their times (N,) in seconds from the trigger, or None."""
        if self.closed:
            raise MeniscopeError(self.path, "the writer is closed")
        frames = self._checked_frames(frames)
        if timestamps is not None:
            timestamps = np.asarray(timestamps, dtype=np.float64)
            if timestamps.shape != frames.shape[:1]:
                raise MeniscopeError(
                    self.path, f"{timestamps.shape} timestamps given for {len(frames)} frames; need one per frame"
                )
            if not np.isfinite(timestamps).all():
                raise MeniscopeError(self.path, "timestamps must be finite numbers of seconds")
        if len(frames):
            self._append(frames, timestamps)
            self.frames_written += len(frames)

    def nominal_times(self, count: int) -> np.ndarray:
        """Seconds from the trigger of the next ``count`` frames at the nominal rate, shape (count,)."""
        return (self.frames_written + np.arange(count) - self.trigger_frame) / self.fps

    def _checked_frames(self, frames: np.ndarray) -> np.ndarray:
        """The batch as ``self.dtype``, after checking its shape, integer type and value range."""
        frames = np.asarray(frames)
        if frames.ndim != 3 or frames.shape[1:] != (self.height, self.width):
            raise MeniscopeError(
                self.path, f"frames have shape {frames.shape}; this writer takes (N, {self.height}, {self.width})"
            )
        if not np.issubdtype(frames.dtype, np.integer):
            raise MeniscopeError(self.path, f"frames are {frames.dtype}; give integer pixel values (quantise first)")
        if frames.size and (frames.min() < 0 or frames.max() >= 2**self.bit_depth):
            raise MeniscopeError(
                self.path,
                f"pixel values {frames.min()}..{frames.max()} do not fit in {self.bit_depth} bits (0..{2**self.bit_depth - 1})",
            )
        return frames.astype(self.dtype, copy=False)

    @abstractmethod
    def _append(self, frames: np.ndarray, timestamps: np.ndarray | None) -> None:
        """Store a checked, non-empty batch (N, height, width) of ``self.dtype`` and its times (N,) or None."""

    @abstractmethod
    def _finish(self) -> None:
        """Complete the file (headers, indices) and release it."""

    def close(self) -> None:
        """Finish the file; later calls do nothing."""
        if not self.closed:
            self.closed = True
            self._finish()

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()
