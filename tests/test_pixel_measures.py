"""The per-frame pixel measures (change, mean, peak, novelty) in one compiled pass: exact, and blind to how frames
are batched."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from service.inverse import pooling as inverse_pooling
from service.inverse.pooling import STD_FLOOR_DN
from service.pipeline.measures import GRID, PixelMeasures


def novelty(frames: np.ndarray, indices: np.ndarray, near: int, far: int) -> np.ndarray:
    """Each frame's mean absolute distance, over its means in GRID bands of rows by GRID of columns (row y in band
    y * GRID // H), to the nearest frame ``near`` .. ``far`` frames before it with no frame lost in between; NaN
    where there is none."""
    n, h, w = frames.shape
    rows, cols = (np.split(np.arange(k), np.flatnonzero(np.diff(np.arange(k) * min(GRID, k) // k)) + 1) for k in (h, w))
    x = frames.astype(np.float64)
    cells = np.stack([x[:, r][:, :, c].mean(axis=(1, 2)) for r in rows for c in cols], axis=1)
    out = np.full(n, np.nan)
    for i in range(n):
        past = [j for j in range(i - far, i - near + 1) if j >= 0 and indices[i] - indices[j] == i - j]
        if past:
            out[i] = min(np.abs(cells[i] - cells[j]).mean() for j in past)
    return out


def reference(
    frames: np.ndarray, indices: np.ndarray, near: int, far: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The measures as numpy states them: float64 means of |frame - frame before|, of the frame, its maximum, and
    its novelty."""
    x = frames.reshape(len(frames), -1).astype(np.float64)
    change = np.r_[np.nan, np.abs(np.diff(x, axis=0)).mean(axis=1)]
    change[1:][np.diff(indices) != 1] = np.nan
    return change, x.mean(axis=1), x.max(axis=1), novelty(frames, indices, near, far)


@settings(max_examples=60, deadline=None)
@given(
    dtype=st.sampled_from([np.uint8, np.uint16, np.int16, np.float32]),
    fill=st.sampled_from(["max", "zero", "random"]),
    frames=st.integers(1, 12),
    side=st.sampled_from([1, 7, 96]),
    batch=st.integers(1, 12),
    gap=st.integers(0, 11),
    seed=st.integers(0, 2**16),
    near=st.integers(1, 4),
    span=st.integers(0, 6),
)
def test_measures_match_numpy_whatever_the_pixels_and_the_batching(
    dtype, fill, frames, side, batch, gap, seed, near, span
):
    """At full scale (sums past 32 bits are kept in 64), all zero and random, in any type a source hands out, with
    a lost frame (``gap``) in the stream: the same as numpy's float64 means to the last bit (exact integer sums);
    novelty (cell means: sums in another order) equal to rounding, never compared across the lost frame."""
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
    measures = PixelMeasures(near, near + span)
    got = [
        np.concatenate(part)
        for part in zip(
            *(measures.update(pixels[i : i + batch], indices[i : i + batch]) for i in range(0, frames, batch))
        )
    ]
    want = reference(pixels, indices, near, near + span)
    np.testing.assert_allclose(got.pop(), want[-1], rtol=1e-9, atol=1e-9 * float(top), equal_nan=True)
    for g, w in zip(got, want):
        if dtype == np.float32:  # float sums in another order: equal to rounding
            np.testing.assert_allclose(g, w, rtol=1e-12, equal_nan=True)
        else:
            np.testing.assert_array_equal(g, w)


def novelty_one_lag_at_a_time(frames: np.ndarray, indices: np.ndarray, near: int, far: int) -> np.ndarray:
    """:func:`novelty` with each distance summed cell by cell in the cells' order, one earlier frame at a time (the
    nearest taken first to last), as the measures defined it before they summed every lag together."""
    n, h, w = frames.shape
    rows, cols = (np.split(np.arange(k), np.flatnonzero(np.diff(np.arange(k) * min(GRID, k) // k)) + 1) for k in (h, w))
    x = frames.astype(np.float64)
    cells = np.stack([x[:, r][:, :, c].sum(axis=(1, 2)) / (r.size * c.size) for r in rows for c in cols], axis=1)
    out = np.full(n, np.nan)
    for i in range(n):
        best = np.inf
        for j in range(i - near, i - far - 1, -1):
            if j < 0 or indices[i] - indices[j] != i - j:
                break
            d = 0.0
            for a, b in zip(cells[i].tolist(), cells[j].tolist()):
                d += abs(a - b)
            best = min(best, d)
        out[i] = best / cells.shape[1] if best < np.inf else np.nan
    return out


@settings(max_examples=60, deadline=None)
@given(
    dtype=st.sampled_from([np.uint8, np.uint16]),
    fill=st.sampled_from(["max", "zero", "random", "steps"]),
    frames=st.integers(1, 40),
    side=st.sampled_from([1, 5, 8, 17, 96]),
    batch=st.integers(1, 40),
    gap=st.integers(0, 41),
    seed=st.integers(0, 2**16),
    near=st.integers(1, 6),
    span=st.integers(0, 12),
)
def test_novelty_is_the_nearest_earlier_frame_summed_cell_by_cell_to_the_last_bit(
    dtype, fill, frames, side, batch, gap, seed, near, span
):
    """Novelty, all earlier frames' distances summed together, equals each distance summed in the cells' order one
    frame at a time, to the last bit: at full scale, zero, random and few-level pixels (many equal distances), any
    batching, a lost frame, comparisons as far back as the stream holds or farther."""
    rng = np.random.default_rng(seed)
    top = np.iinfo(dtype).max
    shape = (frames, side, side)
    pixels = {
        "max": np.full(shape, top, dtype),
        "zero": np.zeros(shape, dtype),
        "random": rng.integers(0, top, shape, dtype, endpoint=True),
        "steps": (rng.integers(0, 3, shape) * (top // 2)).astype(dtype),
    }[fill]
    indices = np.arange(frames) + (np.arange(frames) >= gap)
    measures = PixelMeasures(near, near + span)
    got = np.concatenate(
        [measures.update(pixels[i : i + batch], indices[i : i + batch])[3] for i in range(0, frames, batch)]
    )
    np.testing.assert_array_equal(got, novelty_one_lag_at_a_time(pixels, indices, near, near + span))


@settings(max_examples=60, deadline=None)
@given(
    dtype=st.sampled_from([np.uint8, np.uint16]),
    fill=st.sampled_from(["max", "zero", "random"]),
    factor=st.integers(1, 4),
    blocks=st.tuples(st.integers(1, 33), st.integers(1, 33)),
    frames=st.integers(1, 9),
    batch=st.integers(1, 9),
    seed=st.integers(0, 2**16),
    standardise=st.booleans(),
)
def test_block_means_made_in_the_same_pass_are_the_exact_means_rounded_once_and_change_nothing_else(
    dtype, fill, factor, blocks, frames, batch, seed, standardise
):
    """A graph's input pooled in the measures' pass, at full scale, zero and random, any block size and batching:
    each block's float64 mean rounded once to float32 (what :func:`service.inverse.pooling.block_means` and the
    graphs' AveragePool make), with ``standardise`` those means standardised frame by frame as the graphs'
    normalisation does (a flat frame all zeros, a frame of one block NaN as torch's unbiased std makes it) and to the
    bit as :func:`service.inverse.pooling.standardise` makes them, and the measures the same as without it."""
    shape = (frames, blocks[0] * factor, blocks[1] * factor)
    top = np.iinfo(dtype).max
    pixels = {
        "max": np.full(shape, top, dtype),
        "zero": np.zeros(shape, dtype),
        "random": np.random.default_rng(seed).integers(0, top, shape, dtype, endpoint=True),
    }[fill]
    indices = np.arange(frames)
    pooling, plain = PixelMeasures(1, 3), PixelMeasures(1, 3)
    for lo in range(0, frames, batch):
        part = slice(lo, lo + batch)
        pooled = np.empty((len(pixels[part]), 1, *blocks), np.float32)
        with_pooling = pooling.update(pixels[part], indices[part], pooled, standardise)
        for got, want in zip(with_pooling, plain.update(pixels[part], indices[part])):
            np.testing.assert_array_equal(got, want)
        means = pixels[part].reshape(-1, blocks[0], factor, blocks[1], factor).mean(axis=(2, 4), dtype=np.float64)
        means = means.astype(np.float32)
        if not standardise:
            np.testing.assert_array_equal(pooled[:, 0], means)
            continue
        x = means.reshape(len(means), -1).astype(np.float64)
        deviation = x - x.mean(axis=1, keepdims=True)
        with np.errstate(invalid="ignore", divide="ignore"):  # one block: torch's unbiased std is NaN
            want = deviation / (np.sqrt((deviation**2).sum(axis=1, keepdims=True) / (x.shape[1] - 1)) + STD_FLOOR_DN)
        np.testing.assert_allclose(pooled.reshape(len(pooled), -1), want, rtol=1e-6, atol=1e-5)
        np.testing.assert_array_equal(pooled, inverse_pooling.standardise(means[:, None].copy()))  # to the bit
        if fill != "random" and blocks != (1, 1):
            assert not pooled.any()


def stored_bottom_up(frames: np.ndarray, gap: int) -> np.ndarray:
    """``frames`` (N, H, W) as a read-only view of one buffer where each frame's rows are stored bottom row first
    after ``gap`` bytes of something else, as a .cine holds its images: frames at a stride, rows at a negative one."""
    n, h, w = frames.shape
    item, row = frames.itemsize, w * frames.itemsize
    step = gap + h * row
    buffer = np.zeros(n * step, np.uint8)
    for i, frame in enumerate(frames):
        buffer[i * step + gap : (i + 1) * step] = np.frombuffer(frame[::-1].tobytes(), np.uint8)
    buffer.setflags(write=False)
    offset = gap + (h - 1) * row
    return np.ndarray(frames.shape, frames.dtype, buffer=buffer, offset=offset, strides=(step, -row, item))


@settings(max_examples=60, deadline=None)
@given(
    dtype=st.sampled_from([np.uint8, np.uint16]),
    factor=st.integers(1, 3),
    blocks=st.tuples(st.integers(1, 12), st.integers(1, 12)),
    frames=st.integers(1, 9),
    gap=st.sampled_from([0, 2, 8, 12]),
    viewed=st.lists(st.booleans(), min_size=9, max_size=9),
    batch=st.integers(1, 9),
    seed=st.integers(0, 2**16),
    standardise=st.booleans(),
)
def test_frames_viewed_where_stored_bottom_up_measure_as_their_copies(
    dtype, factor, blocks, frames, gap, viewed, batch, seed, standardise
):
    """Frames read in place where a file stores them (bottom row first, at a stride: no copy) give the measures and
    pooled means of the same frames copied top row first, to the last bit, whichever batches come viewed and which
    copied (the frame before a batch carried across); the means standardised, to float32's rounding (their squares
    are summed in the other order)."""
    shape = (frames, blocks[0] * factor, blocks[1] * factor)
    pixels = np.random.default_rng(seed).integers(0, np.iinfo(dtype).max, shape, dtype, endpoint=True)
    stored = stored_bottom_up(pixels, gap)
    indices = np.arange(frames)
    copied, mixed = PixelMeasures(1, 3), PixelMeasures(1, 3)
    for k, lo in enumerate(range(0, frames, batch)):
        part = slice(lo, lo + batch)
        want_pooled, got_pooled = (np.empty((len(pixels[part]), 1, *blocks), np.float32) for _ in range(2))
        want = copied.update(pixels[part], indices[part], want_pooled, standardise)
        got = mixed.update(stored[part] if viewed[k] else pixels[part], indices[part], got_pooled, standardise)
        for g, w in zip(got, want):
            np.testing.assert_array_equal(g, w)
        np.testing.assert_allclose(got_pooled, want_pooled, rtol=1e-6, atol=1e-6 if standardise else 0)


def test_a_pooled_output_that_does_not_fit_the_frames_is_refused() -> None:
    frames = np.zeros((2, 6, 6), np.uint16)
    for pooled in (
        np.empty((2, 1, 4, 4), np.float32),
        np.empty((2, 1, 0, 0), np.float32),
        np.empty((2, 2, 2), np.float32),
    ):
        with pytest.raises(ValueError, match="whole blocks"):
            PixelMeasures(1, 3).update(frames, np.arange(2), pooled)
    with pytest.raises(ValueError, match="float32"):
        PixelMeasures(1, 3).update(frames, np.arange(2), np.empty((2, 1, 2, 2)))


@settings(max_examples=12, deadline=None)
@given(
    dtype=st.sampled_from([np.uint8, np.uint16, np.uint32]),
    beyond=st.integers(-1, 1),
    frames=st.integers(1, 3),
    seed=st.integers(0, 2**16),
)
def test_sums_at_full_scale_either_side_of_32_bits_are_exact(dtype, beyond, frames, seed) -> None:
    """Frames of as many pixels as keep a full-scale frame's sum just within 32 bits, one pixel row more (the sums
    then kept in 64 bits) or fewer: every pixel at full scale, the means, change and peak the exact ones; with a
    random frame between, its change from a full-scale frame exact too."""
    top = int(np.iinfo(dtype).max)
    width = 64
    rows = max(1, (2**32 - 1) // top // width + beyond)  # rows * width * top crosses 2**32 at beyond = 1
    rows = min(rows, 2**20 // width)  # 8-bit frames that large would take a gigabyte: a mebipixel is plenty
    pixels = np.full((frames, rows, width), top, dtype)
    pixels[frames // 2] = np.random.default_rng(seed).integers(0, top, (rows, width), dtype, endpoint=True)
    change, mean, peak, _ = PixelMeasures(1, 2).update(pixels, np.arange(frames))
    want = reference(pixels, np.arange(frames), 1, 2)
    for got, expected in zip((change, mean, peak), want):
        np.testing.assert_array_equal(got, expected)
