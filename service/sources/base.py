"""The camera-adapter seam (ARCHITECTURE.md, "FrameSource"): frame batches, one base class, one URI factory.

Every adapter (replay, V4L2, Aravis, ZeroMQ, simulated) subclasses :class:`FrameSource` and fills in
``_open``, ``_read`` and ``_close``; the base keeps the open/closed state, the stream's format and the
gap statistics, so they behave the same everywhere. :func:`open_source` picks the adapter by URI scheme.
"""

from __future__ import annotations

import importlib
from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from types import TracebackType
from typing import Any, ClassVar, TypeVar
from urllib.parse import SplitResult, parse_qsl, quote, urlsplit

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from service.errors import MeniscopeError

#: Pixel types a source delivers: 8-bit cameras store uint8, deeper ones uint16 words.
PIXEL_DTYPES = (np.dtype(np.uint8), np.dtype(np.uint16))

#: Adapter per URI scheme ("module:Class", imported on first use so optional libraries load only when needed).
ADAPTERS: dict[str, str] = {
    "file": "service.sources.replay:ReplaySource",
    "v4l2": "service.sources.v4l2:V4l2Source",
    "aravis": "service.sources.aravis:AravisSource",
    "zmq+tcp": "service.sources.zmq_source:ZmqSource",
    "sim": "service.sources.simulated:SimulatedSource",
}


@dataclass(frozen=True)
class Frame:
    """One frame: pixels uint8 or uint16 (H, W) in display order (top row first), its index and time (s)."""

    pixels: np.ndarray
    index: int
    timestamp: float


@dataclass(frozen=True)
class FrameBatch:
    """N frames read at once from a source; N may be 0 (nothing arrived before the read timed out).

    Attributes
    ----------
    pixels : ndarray of shape (N, H, W), uint8 or uint16
        As the camera delivers them (no scaling), rows in display order; may be a read-only view.
    indices : ndarray of shape (N,), int64
        Frame numbers, increasing; a jump of more than one is a gap (frames lost upstream).
    timestamps : ndarray of shape (N,), float64
        Seconds on the source's clock, increasing.
    """

    pixels: np.ndarray
    indices: np.ndarray
    timestamps: np.ndarray

    def __post_init__(self) -> None:
        n = self.pixels.shape[0] if self.pixels.ndim == 3 else -1
        if self.pixels.dtype not in PIXEL_DTYPES or n < 0:
            raise ValueError(f"pixels must be uint8 or uint16 (N, H, W), got {self.pixels.dtype} {self.pixels.shape}")
        if self.indices.dtype != np.int64 or self.indices.shape != (n,):
            raise ValueError(f"indices must be int64 ({n},), got {self.indices.dtype} {self.indices.shape}")
        if self.timestamps.dtype != np.float64 or self.timestamps.shape != (n,):
            raise ValueError(f"timestamps must be float64 ({n},), got {self.timestamps.dtype} {self.timestamps.shape}")

    def __len__(self) -> int:
        return int(self.indices.shape[0])

    def __getitem__(self, i: int) -> Frame:
        return Frame(self.pixels[i], int(self.indices[i]), float(self.timestamps[i]))

    def select(self, which: slice | np.ndarray) -> FrameBatch:
        """The frames a slice, boolean mask (N,) or index array picks, as a batch (views where numpy can)."""
        return FrameBatch(self.pixels[which], self.indices[which], self.timestamps[which])

    @classmethod
    def concatenate(cls, batches: Sequence[FrameBatch]) -> FrameBatch:
        """One batch of the frames of several (at least one), in order."""
        if len(batches) == 1:
            return batches[0]
        return cls(*(np.concatenate([getattr(b, f) for b in batches]) for f in ("pixels", "indices", "timestamps")))

    @classmethod
    def from_frames(cls, frames: Sequence[Frame], height: int, width: int, dtype: np.dtype) -> FrameBatch:
        """Stack single frames (as cameras deliver them) into one batch; an empty list gives an empty batch."""
        pixels = np.empty((len(frames), height, width), dtype)
        for k, frame in enumerate(frames):
            pixels[k] = frame.pixels
        return cls(
            pixels,
            np.array([f.index for f in frames], np.int64),
            np.array([f.timestamp for f in frames], np.float64),
        )


@dataclass(frozen=True)
class StreamFormat:
    """What every frame of an open stream looks like: size (px), pixel type, significant bits, nominal rate."""

    width: int
    height: int
    dtype: np.dtype
    bit_depth: int
    fps: float


@dataclass
class SourceStats:
    """Counters since the source was opened: frames delivered, gaps (index jumps) and frames lost in them."""

    frames: int = 0
    gaps: int = 0
    dropped: int = 0

    def count(self, indices: np.ndarray, last: int | None) -> None:
        """Add a batch of frame indices (N,) that follows frame ``last`` (None for the first batch)."""
        steps = np.diff(indices, prepend=indices[:1] - 1 if last is None else np.int64(last))
        jumps = steps[steps > 1]
        self.frames += len(indices)
        self.gaps += len(jumps)
        self.dropped += int((jumps - 1).sum())


class SourceOptions(BaseModel):
    """Options every adapter takes; each adapter's own ``Options`` adds its fields (URI query or keywords)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    timeout: float = Field(0.1, gt=0, allow_inf_nan=False, description="longest a read waits for frames, s")


_O = TypeVar("_O", bound=SourceOptions)


def parse_options(model: type[_O], uri: str, raw: Mapping[str, Any]) -> _O:
    """``raw`` validated as ``model``; a bad or unknown option is one error line naming the URI."""
    try:
        return model.model_validate(dict(raw))
    except ValidationError as exc:
        err = exc.errors()[0]
        name = ".".join(str(part) for part in err["loc"]) or "options"
        allowed = ", ".join(model.model_fields)
        problem = (
            f"unknown option {name!r} (options: {allowed})"
            if err["type"] == "extra_forbidden"
            else (f"bad option {name}={err.get('input')!r}: {str(err['msg']).removeprefix('Value error, ')}")
        )
        raise MeniscopeError(uri, problem) from None


class FrameSource(ABC):
    """A stream of frame batches from one camera, file or socket; open it, read batches, close it.

    Subclasses implement ``_open`` (acquire the device, return the :class:`StreamFormat`), ``_read``
    and ``_close``, and the classmethod ``from_uri``. Properties are valid while the source is open.
    """

    #: what ``describe()`` calls this adapter
    kind: ClassVar[str]

    def __init__(self, uri: str, timeout: float) -> None:
        self.uri = uri
        self.timeout = timeout
        self._format: StreamFormat | None = None
        self._stats = SourceStats()
        self._last_index: int | None = None

    @classmethod
    @abstractmethod
    def from_uri(cls, uri: str, parts: SplitResult, options: Mapping[str, Any]) -> FrameSource:
        """A new, unopened source for ``uri`` (already split into ``parts``) with ``options`` (strings or values)."""

    @abstractmethod
    def _open(self) -> StreamFormat:
        """Acquire the device or file (releasing what it took if it fails) and say what its frames look like."""

    @abstractmethod
    def _read(self, max_frames: int) -> FrameBatch | None:
        """Up to ``max_frames`` frames, waiting at most ``self.timeout`` s for them; None at the end of the stream."""

    @abstractmethod
    def _close(self) -> None:
        """Release the device or file."""

    def _details(self) -> dict[str, Any]:
        """Adapter-specific, JSON-safe facts for :meth:`describe`."""
        return {}

    @property
    def is_open(self) -> bool:
        return self._format is not None

    def open(self) -> FrameSource:
        """Start a new stream (statistics from zero); opening an open source does nothing."""
        if self._format is None:
            fmt = self._open()
            self._stats, self._last_index = SourceStats(), None
            self._format = fmt
        return self

    def close(self) -> None:
        """Stop the stream and release the device; closing again does nothing."""
        if self._format is not None:
            self._format = None
            self._close()

    def __enter__(self) -> FrameSource:
        return self.open()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def read(self, max_frames: int = 64) -> FrameBatch | None:
        """The next 0..``max_frames`` frames, after waiting at most ``timeout`` s for them; None at the end.

        Returns as soon as ``max_frames`` frames are there, else when the timeout passes with what
        arrived by then (an empty batch when nothing did). Once it returns None it keeps doing so.
        """
        if max_frames < 1:
            raise ValueError(f"max_frames must be at least 1, got {max_frames}")
        if self._format is None:
            raise MeniscopeError(self.uri, "cannot read: the source is not open")
        batch = self._read(max_frames)
        if batch is not None and len(batch):
            self._stats.count(batch.indices, self._last_index)
            self._last_index = int(batch.indices[-1])
        return batch

    @property
    def format(self) -> StreamFormat:
        if self._format is None:
            raise MeniscopeError(self.uri, "the source is not open")
        return self._format

    @property
    def fps(self) -> float:
        """Nominal frame rate, frames per second."""
        return self.format.fps

    @property
    def width(self) -> int:
        return self.format.width

    @property
    def height(self) -> int:
        return self.format.height

    @property
    def dtype(self) -> np.dtype:
        """``uint8`` or ``uint16``."""
        return self.format.dtype

    @property
    def bit_depth(self) -> int:
        """Significant bits per pixel (12 for a 12-bit camera delivering uint16 words)."""
        return self.format.bit_depth

    @property
    def stats(self) -> SourceStats:
        """Frames, gaps and dropped frames since the source was opened (a copy)."""
        return SourceStats(**asdict(self._stats))

    def empty_batch(self) -> FrameBatch:
        """A batch of no frames in this stream's format (what a read that timed out returns)."""
        return FrameBatch.from_frames([], self.height, self.width, self.dtype)

    def describe(self) -> dict[str, Any]:
        """JSON-safe summary: URI, adapter, format (when open), statistics and adapter details."""
        fmt = self._format
        return {
            "uri": self.uri,
            "kind": self.kind,
            "open": fmt is not None,
            **(
                {}
                if fmt is None
                else {
                    "width": fmt.width,
                    "height": fmt.height,
                    "dtype": fmt.dtype.name,
                    "bit_depth": fmt.bit_depth,
                    "fps": fmt.fps,
                }
            ),
            "stats": asdict(self._stats),
            **self._details(),
        }


def _adapter(uri: str) -> tuple[type[FrameSource], SplitResult, dict[str, str]]:
    """The adapter class a URI names, its parts and its query options."""
    if "://" not in uri:  # a plain path: no query string, '?' may be part of the file name
        parts, query = SplitResult("file", "", quote(uri), "", ""), {}
    else:
        parts = urlsplit(uri)
        query = dict(parse_qsl(parts.query, keep_blank_values=True))
    target = ADAPTERS.get(parts.scheme.lower())
    if target is None:
        raise MeniscopeError(
            uri,
            f"unknown source scheme {parts.scheme!r}: use a path or one of {', '.join(s + '://' for s in ADAPTERS)}",
        )
    module, name = target.split(":")
    return getattr(importlib.import_module(module), name), parts, query


def probe_source(uri: str) -> None:
    """Check that ``uri`` names a source that can open, without taking a device: its scheme and options, and for
    a recording the file itself (opened and closed). A camera or socket is checked only when it opens."""
    adapter, parts, query = _adapter(uri)
    source = adapter.from_uri(uri, parts, query)
    if source.kind == "replay":
        source.open().close()


def open_source(uri: str, **options: Any) -> FrameSource:
    """Open the source a URI names; options come from the URI's query string and/or keywords (keywords win).

    ``file:///path/rec.cine`` or a plain path: replay of a recording; ``v4l2:///dev/video0`` or
    ``v4l2://0``: a V4L2 camera; ``aravis://`` (the first camera) or ``aravis://<device-id>``: a GigE
    Vision / USB3 Vision camera; ``zmq+tcp://host:port``: frames published by ``meniscope
    publish-frames`` or another process; ``sim://``: frames rendered live from the physics model.
    The returned source is open; use it as a context manager or call ``close()``.
    """
    adapter, parts, query = _adapter(uri)
    return adapter.from_uri(uri, parts, {**query, **options}).open()
