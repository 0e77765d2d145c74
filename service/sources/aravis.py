"""GigE Vision and USB3 Vision cameras through Aravis (PyGObject): ``aravis://`` or ``aravis://<device-id>``.

The device id is what ``arv-tool-0.8`` lists, or a GigE camera's IP address (opened directly, without
a broadcast discovery). Monochrome pixel formats only: Mono8 as uint8, Mono10/12/14/16 as uint16 words.
Frame indices follow the camera's block ids (16-bit GigE Vision ids wrap from 65535 to 1), so frames
the camera or the network lost show as gaps; timestamps are the camera's, in s since the first frame.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from types import ModuleType
from typing import Any, Literal
from urllib.parse import SplitResult, unquote

import numpy as np
from pydantic import Field

from service.errors import MeniscopeError
from service.sources.base import Frame, FrameBatch, FrameSource, SourceOptions, StreamFormat, parse_options

#: Supported pixel formats: numpy type and significant bits.
PIXEL_FORMATS: dict[str, tuple[np.dtype, int]] = {
    "Mono8": (np.dtype(np.uint8), 8),
    "Mono10": (np.dtype(np.uint16), 10),
    "Mono12": (np.dtype(np.uint16), 12),
    "Mono14": (np.dtype(np.uint16), 14),
    "Mono16": (np.dtype(np.uint16), 16),
}
#: GigE Vision 1.x block ids are 16 bits and skip 0: after 65535 comes 1.
_BLOCK_ID_PERIOD = 0xFFFF


class AravisOptions(SourceOptions):
    pixel_format: Literal["Mono8", "Mono10", "Mono12", "Mono14", "Mono16"] = "Mono8"
    fps: float | None = Field(None, gt=0, allow_inf_nan=False, description="acquisition frame rate to set")
    exposure_us: float | None = Field(None, gt=0, allow_inf_nan=False)
    x: int = Field(0, ge=0, description="region of interest: left column")
    y: int = Field(0, ge=0, description="region of interest: top row")
    width: int | None = Field(None, ge=1, description="region width (default: the camera's current)")
    height: int | None = Field(None, ge=1, description="region height (default: the camera's current)")
    buffers: int = Field(32, ge=2, le=4096, description="frame buffers queued to the driver")


def load_aravis(where: str) -> ModuleType:
    """The Aravis 0.8 GObject bindings, or an error saying what to install."""
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis
    except (ImportError, ValueError) as exc:
        raise MeniscopeError(
            where, f"Aravis is not available ({exc}): install the Debian package gir1.2-aravis-0.8 and PyGObject"
        ) from None
    return Aravis


class AravisSource(FrameSource):
    """A GenICam camera streaming continuously into a pool of ``buffers`` frame buffers."""

    kind = "aravis"

    def __init__(
        self, device_id: str | None = None, options: AravisOptions = AravisOptions(), uri: str | None = None
    ) -> None:
        super().__init__(uri or f"aravis://{device_id or ''}", options.timeout)
        self.device_id, self.options = device_id, options
        self._camera: Any = None
        self._stream: Any = None
        self._success: Any = None
        self._last_id: int | None = None
        self._index = 0
        self._t0_ns = 0

    @classmethod
    def from_uri(cls, uri: str, parts: SplitResult, options: Mapping[str, Any]) -> AravisSource:
        return cls(unquote(parts.netloc + parts.path) or None, parse_options(AravisOptions, uri, options), uri)

    def _open(self) -> StreamFormat:
        Aravis = load_aravis(self.uri)
        from gi.repository import GLib

        opts = self.options
        self._success = Aravis.BufferStatus.SUCCESS
        try:
            self._camera = cam = Aravis.Camera.new(self.device_id)
        except GLib.Error as exc:
            raise MeniscopeError(self.uri, f"cannot open the camera: {exc.message}") from None
        try:
            cam.set_acquisition_mode(Aravis.AcquisitionMode.CONTINUOUS)
            cam.set_pixel_format_from_string(opts.pixel_format)
            _, _, width, height = cam.get_region()
            cam.set_region(opts.x, opts.y, opts.width or width, opts.height or height)
            if opts.fps is not None:
                cam.set_frame_rate(opts.fps)
            if opts.exposure_us is not None:
                cam.set_exposure_time(opts.exposure_us)
            _, _, width, height = cam.get_region()
            fps = cam.get_frame_rate()
            self._stream = cam.create_stream(None, None)
            payload = cam.get_payload()
            for _ in range(opts.buffers):
                self._stream.push_buffer(Aravis.Buffer.new_allocate(payload))
            self._last_id, self._index = None, 0
            cam.start_acquisition()
        except GLib.Error as exc:
            self._release()
            raise MeniscopeError(
                self.uri, f"the camera refused the settings ({opts.pixel_format}): {exc.message}"
            ) from None
        dtype, bits = PIXEL_FORMATS[opts.pixel_format]
        return StreamFormat(width, height, dtype, bits, fps)

    def _read(self, max_frames: int) -> FrameBatch:
        frames: list[Frame] = []
        deadline = time.monotonic() + self.timeout
        while len(frames) < max_frames:
            left_us = int((deadline - time.monotonic()) * 1e6)
            buffer = self._stream.timeout_pop_buffer(left_us) if left_us > 0 else self._stream.try_pop_buffer()
            if buffer is None:
                break
            try:
                if buffer.get_status() == self._success:
                    frames.append(self._frame(buffer))
            finally:
                self._stream.push_buffer(buffer)  # back to the pool: the frame was copied out
        return FrameBatch.from_frames(frames, self.height, self.width, self.dtype)

    def _frame(self, buffer: Any) -> Frame:
        """The frame a filled buffer holds, with the next index after its block id and its time."""
        frame_id = buffer.get_frame_id()
        stamp = buffer.get_timestamp() or buffer.get_system_timestamp()
        if self._last_id is None:
            self._t0_ns = stamp
        else:
            step = frame_id - self._last_id
            if step <= 0 and self._last_id <= _BLOCK_ID_PERIOD:
                step += _BLOCK_ID_PERIOD
            self._index += max(step, 1)
        self._last_id = frame_id
        pixels = np.frombuffer(buffer.get_data(), self.dtype, self.width * self.height)
        return Frame(pixels.reshape(self.height, self.width), self._index, (stamp - self._t0_ns) * 1e-9)

    def _release(self) -> None:
        """Drop the stream (its receiving thread stops) and the camera connection."""
        self._stream = self._camera = None

    def _close(self) -> None:
        from gi.repository import GLib

        try:
            self._camera.stop_acquisition()
        except GLib.Error:
            pass  # the camera is gone already: nothing left to stop
        self._release()

    def _details(self) -> dict[str, Any]:
        if self._camera is None:
            return {"device_id": self.device_id}
        cam = self._camera
        return {
            "device_id": cam.get_device_id(),
            "vendor": cam.get_vendor_name(),
            "model": cam.get_model_name(),
            "pixel_format": self.options.pixel_format,
            "buffers": self.options.buffers,
        }
