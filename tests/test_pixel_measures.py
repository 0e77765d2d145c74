"""The per-frame pixel measures (change, mean, peak) in one compiled pass: exact, and blind to how frames are batched."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from service.pipeline.measures import PixelMeasures


def reference(frames: np.ndarray, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The measures as numpy states them: float64 means of |frame - frame before|, of the frame, and its maximum."""
    x = frames.reshape(len(frames), -1).astype(np.float64)
    change = np.r_[np.nan, np.abs(np.diff(x, axis=0)).mean(axis=1)]
    change[1:][np.diff(indices) != 1] = np.nan
    return change, x.mean(axis=1), x.max(axis=1)


@settings(max_examples=60, deadline=None)
@given(
    dtype=st.sampled_from([np.uint8, np.uint16, np.int16, np.float32]),
    fill=st.sampled_from(["max", "zero", "random"]),
    frames=st.integers(1, 12),
    side=st.sampled_from([1, 7, 96]),
    batch=st.integers(1, 12),
    gap=st.integers(0, 11),
    seed=st.integers(0, 2**16),
)
def test_measures_match_numpy_whatever_the_pixels_and_the_batching(dtype, fill, frames, side, batch, gap, seed):
    """At full scale (sums past 32 bits are kept in 64), all zero and random, in any type a source hands out, with
    a lost frame (``gap``) in the stream: the same as numpy's float64 means to the last bit (exact integer sums)."""
    rng = np.random.default_rng(seed)
    top = np.iinfo(dtype).max if np.issubdtype(dtype, np.integer) else 1.0
    low = np.iinfo(dtype).min if np.issubdtype(dtype, np.signedinteger) else 0
    shape = (frames, side, side)
    pixels = {
        "max": np.full(shape, top, dtype),
        "zero": np.zeros(shape, dtype),
        "random": (rng.integers(low, top, shape, endpoint=True) if top != 1.0 else rng.random(shape)).astype(dtype),
    }[fill]
    indices = np.arange(frames) + (np.arange(frames) >= gap)  # frame ``gap`` (if any) lost before it arrived
    measures = PixelMeasures()
    got = [
        np.concatenate(part)
        for part in zip(
            *(measures.update(pixels[i : i + batch], indices[i : i + batch]) for i in range(0, frames, batch))
        )
    ]
    want = reference(pixels, indices)
    for g, w in zip(got, want):
        if dtype == np.float32:  # float sums in another order: equal to rounding
            np.testing.assert_allclose(g, w, rtol=1e-12, equal_nan=True)
        else:
            np.testing.assert_array_equal(g, w)
