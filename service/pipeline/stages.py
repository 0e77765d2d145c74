"""The per-frame stages every front door runs a batch of frames through: ROI -> measures (and the inverse's input) ->
inverse.

``meniscope serve`` calls them from its acquisition and inference threads, ``meniscope analyze`` one
after the other on a replay read at full speed, ``meniscope bench`` either way: a change to how a
frame is handled lands here once. Each batch becomes per-frame records
(:data:`service.pipeline.records.FRAME`), which the segmenter (:mod:`service.pipeline.segmenter`)
cuts into windows for the window-level work (:mod:`service.pipeline.windows`).
"""

from __future__ import annotations

import numpy as np

from service.inverse.base import InverseMethod
from service.pipeline.ejections import novelty_lags
from service.pipeline.measures import PixelMeasures
from service.pipeline.records import COEFFICIENTS, FRAME
from service.scene import Scene
from service.sources.base import FrameBatch, StreamFormat


class FrameStages:
    """The per-frame stages of a stream of frames in ``stream`` format (from ``uri``) through ``method``."""

    def __init__(self, scene: Scene, stream: StreamFormat, uri: str, method: InverseMethod) -> None:
        width, height = stream.width, stream.height
        scene.check_roi(width, height, uri)
        self._full_scale = float(2**stream.bit_depth - 1)
        (x, y), h, w = scene.camera.roi, scene.camera.height_px, scene.camera.width_px
        self._roi = (slice(None), slice(y, y + h), slice(x, x + w))
        self._roi_is_frame = (height, width) == (h, w)
        self.method = method
        self.pixels = PixelMeasures(*novelty_lags(stream.fps))

    def roi(self, batch: FrameBatch) -> FrameBatch:
        """The batch's region of interest, copied out so that whole sensor frames are freed at once; a batch whose
        frames are the ROI passes as it is."""
        if self._roi_is_frame:
            return batch
        return FrameBatch(batch.pixels[self._roi].copy(), batch.indices, batch.timestamps)

    def measure(self, batch: FrameBatch) -> tuple[np.ndarray, np.ndarray]:
        """Records (N,) of a batch of ROI frames with what the pixels alone say (change from the frame before, mean
        brightness, highlight, novelty; the inverse's fields NaN until :meth:`infer`), and the inverse method's
        input made of them (a graph's pooled frames: in the same pass over the pixels where it pools them), so
        that the thread that infers takes only that."""
        records = np.full(len(batch), np.nan, FRAME)
        n, h, w = batch.pixels.shape
        factor = self.method.pooling
        inputs = None
        if factor:
            self.method.check(batch.pixels)
            inputs = np.empty((n, 1, h // factor, w // factor), np.float32)
        change, brightness, peak, records["novelty"] = self.pixels.update(
            batch.pixels, batch.indices, inputs, self.method.standardised
        )
        records["change"] = change
        records["brightness"] = brightness
        records["highlight"] = (peak - brightness) / self._full_scale
        return records, self.method.prepare(batch.pixels) if inputs is None else inputs

    def infer(self, inputs: np.ndarray, records: np.ndarray) -> np.ndarray:
        """``records`` of the frames :meth:`measure` made ``inputs`` of, with the inverse method's coefficients and
        D(0, t) filled in (in place; returned for convenience)."""
        out = self.method.infer_prepared(inputs)
        for name, column in zip(COEFFICIENTS, out.coefficients.T):
            records[name] = column
        records["centre"] = out.centre
        if out.latent is not None:
            records["latent"] = out.latent
        return records
