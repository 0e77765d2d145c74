"""V4L2 cameras (webcams, capture cards, USB machine-vision cameras) through OpenCV: ``v4l2:///dev/video0``, ``v4l2://0``.

Colour frames are converted to grey (ITU-R BT.601 luma). OpenCV hides the driver's sequence numbers,
so indices come from the buffer timestamps: each frame advances the index by the number of nominal
frame periods since the previous one (at least one), and a frame the driver dropped shows as a gap.
A read waits for the frame in flight, so it may overrun ``timeout`` by up to one frame period.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Any
from urllib.parse import SplitResult, unquote

import cv2
import numpy as np
from pydantic import Field

from service.errors import MeniscopeError
from service.sources.base import Frame, FrameBatch, FrameSource, SourceOptions, StreamFormat, parse_options


class V4l2Options(SourceOptions):
    width: int | None = Field(None, ge=1, description="frame width to ask the driver for, px")
    height: int | None = Field(None, ge=1, description="frame height to ask the driver for, px")
    fps: float | None = Field(None, gt=0, allow_inf_nan=False, description="frame rate to ask for")


class V4l2Source(FrameSource):
    """A V4L2 capture device opened with OpenCV's V4L2 back end, delivering grey frames."""

    kind = "v4l2"

    def __init__(self, device: int | str, options: V4l2Options = V4l2Options(), uri: str | None = None) -> None:
        super().__init__(uri or f"v4l2://{device}", options.timeout)
        self.device, self.options = device, options
        self._capture: cv2.VideoCapture | None = None
        self._pending: Frame | None = None
        self._t0, self._fps = 0.0, 0.0
        self._t_prev: float | None = None  # time of the previous frame; None before the first
        self._index = 0

    @classmethod
    def from_uri(cls, uri: str, parts: SplitResult, options: Mapping[str, Any]) -> V4l2Source:
        opts = parse_options(V4l2Options, uri, options)
        if parts.netloc.isdigit() and not parts.path:
            return cls(int(parts.netloc), opts, uri)
        if not parts.netloc and parts.path.startswith("/dev/"):
            return cls(unquote(parts.path), opts, uri)
        raise MeniscopeError(uri, "a V4L2 source is v4l2:///dev/videoN or v4l2://N")

    def _open(self) -> StreamFormat:
        cap = cv2.VideoCapture(self.device, cv2.CAP_V4L2)
        try:
            if not cap.isOpened():
                raise MeniscopeError(self.uri, "cannot open the device (missing, busy, or not a capture device)")
            for prop, value in (
                (cv2.CAP_PROP_FRAME_WIDTH, self.options.width),
                (cv2.CAP_PROP_FRAME_HEIGHT, self.options.height),
                (cv2.CAP_PROP_FPS, self.options.fps),
            ):
                if value is not None:
                    cap.set(prop, value)
            fps = cap.get(cv2.CAP_PROP_FPS)
            if not fps > 0:
                raise MeniscopeError(self.uri, "the device does not report its frame rate")
            self._capture, self._fps, self._index, self._t_prev = cap, fps, 0, None
            first = self._grab()
            if first is None:
                raise MeniscopeError(self.uri, "the device opened but delivers no frames")
        except BaseException:
            cap.release()
            self._capture = None
            raise
        self._pending = first
        height, width = first.pixels.shape
        dtype = first.pixels.dtype
        return StreamFormat(width, height, dtype, 8 * dtype.itemsize, self._fps)

    def _grab(self) -> Frame | None:
        """The next frame in grey with its index and time, or None when the device delivers none."""
        assert self._capture is not None
        ok, image = self._capture.read()
        if not ok:
            return None
        if image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        # the driver's buffer time (CLOCK_MONOTONIC, like time.monotonic) when OpenCV has one
        stamp = self._capture.get(cv2.CAP_PROP_POS_MSEC) * 1e-3 or time.monotonic()
        if self._t_prev is None:
            self._t0 = stamp
        else:
            self._index += max(1, round((stamp - self._t_prev) * self._fps))
        self._t_prev = stamp
        return Frame(np.ascontiguousarray(image), self._index, stamp - self._t0)

    def _read(self, max_frames: int) -> FrameBatch:
        frames: list[Frame] = []
        if self._pending is not None:
            frames.append(self._pending)
            self._pending = None
        deadline = time.monotonic() + self.timeout
        while len(frames) < max_frames and time.monotonic() < deadline:
            frame = self._grab()
            if frame is None:
                break
            frames.append(frame)
        return FrameBatch.from_frames(frames, self.height, self.width, self.dtype)

    def _close(self) -> None:
        if self._capture is not None:
            self._capture.release()
            self._capture, self._pending = None, None

    def _details(self) -> dict[str, Any]:
        return {"device": self.device}
