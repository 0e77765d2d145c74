"""The camera model: an ideal camera only quantises, optics move and spread light as stated,
noise has the variance its physics says, and no setting wraps, overflows or makes NaN."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from service.camera_effects import (
    NOISE_PRESETS,
    CameraEffects,
    EffectRanges,
    apply_effects,
    noise_preset,
    optics,
    pixel_dtype,
)

BIT_DEPTHS = (8, 10, 12, 16)
unit_frames = arrays(
    np.float32,
    st.tuples(st.integers(1, 3), st.integers(1, 12), st.integers(1, 12)),
    elements=st.floats(0.0, 1.0, width=32),
)


def rng(seed: int = 0) -> np.random.Generator:
    return np.random.default_rng(seed)


def moments(image: np.ndarray) -> tuple[float, float, float]:
    """Total, centroid column and variance along columns of a 2-D image."""
    cols = np.arange(image.shape[1])
    total = image.sum()
    cx = (image.sum(axis=0) * cols).sum() / total
    return float(total), float(cx), float((image.sum(axis=0) * (cols - cx) ** 2).sum() / total)


@pytest.mark.parametrize("bit_depth", BIT_DEPTHS)
@given(frames=unit_frames)
def test_an_ideal_camera_only_quantises(bit_depth: int, frames: np.ndarray) -> None:
    out = CameraEffects(bit_depth=bit_depth).apply(frames, rng())
    top = 2**bit_depth - 1
    assert out.dtype == pixel_dtype(bit_depth) and out.shape == frames.shape
    assert np.array_equal(out, np.rint(frames * np.float32(top)).astype(out.dtype))
    assert np.abs(out / top - frames).max() <= 0.5 / top + 1e-7


@pytest.mark.parametrize("bit_depth", BIT_DEPTHS)
def test_black_and_full_scale_map_to_the_ends_of_the_range(bit_depth: int) -> None:
    frames = np.stack([np.zeros((4, 4)), np.ones((4, 4))]).astype(np.float32)
    out = CameraEffects(bit_depth=bit_depth).apply(frames, rng())
    assert out.dtype == (np.uint8 if bit_depth == 8 else np.uint16)
    assert (out[0] == 0).all() and (out[1] == 2**bit_depth - 1).all()


@given(
    level=st.sampled_from([0.0, 1.0]),
    gain=st.sampled_from([0.0, 1e-6, 1.0, 1e6]),
    offset=st.sampled_from([-1.0, 0.0, 1.0]),
    full_well=st.sampled_from([0.0, 1.0, 1e9]),
    read=st.sampled_from([0.0, 1e5]),
    sigma=st.sampled_from([0.0, 10.0]),
    shift=st.sampled_from([-8.0, 0.0, 0.5, 8.0]),
    bit_depth=st.sampled_from(BIT_DEPTHS),
)
@settings(max_examples=60, deadline=None)
def test_extreme_settings_stay_in_range(level, gain, offset, full_well, read, sigma, shift, bit_depth) -> None:
    effects = CameraEffects(
        gain=gain,
        offset=offset,
        full_well_e=full_well,
        read_noise_dn=read,
        blur_sigma_px=sigma,
        shift_px=(shift, -shift),
        bit_depth=bit_depth,
    )
    out = effects.apply(np.full((2, 9, 7), level, np.float32), rng())
    assert out.dtype == pixel_dtype(bit_depth) and out.shape == (2, 9, 7)
    assert int(out.max()) <= 2**bit_depth - 1


@pytest.mark.parametrize("bit_depth", BIT_DEPTHS)
def test_huge_gain_saturates_instead_of_wrapping(bit_depth: int) -> None:
    frames = np.linspace(0.01, 1.0, 2 * 8 * 8, dtype=np.float32).reshape(2, 8, 8)
    out = CameraEffects(gain=1e6, bit_depth=bit_depth).apply(frames, rng())
    assert (out == 2**bit_depth - 1).all()


def test_non_finite_input_is_refused() -> None:
    frames = np.zeros((1, 4, 4), np.float32)
    frames[0, 1, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        CameraEffects().apply(frames, rng())


def test_the_same_seed_gives_the_same_pixels_and_another_seed_others() -> None:
    frames = rng(1).random((5, 16, 16), dtype=np.float32)
    effects = noise_preset("high", 12)
    assert np.array_equal(effects.apply(frames, rng(7)), effects.apply(frames, rng(7)))
    assert not np.array_equal(effects.apply(frames, rng(7)), effects.apply(frames, rng(8)))
    ranges = EffectRanges()
    a = apply_effects(frames, ranges.sample(5, rng(3)), 8, rng(4))
    assert np.array_equal(a, apply_effects(frames, ranges.sample(5, rng(3)), 8, rng(4)))


@pytest.mark.parametrize("level, full_well", [(0.5, 10_000.0), (0.9, 4_000.0), (0.05, 40_000.0)])
def test_shot_noise_variance_is_signal_over_full_well(level: float, full_well: float) -> None:
    top = 2**16 - 1
    out = CameraEffects(full_well_e=full_well, bit_depth=16).apply(np.full((20, 64, 64), level, np.float32), rng())
    expected = top**2 * level / full_well + 1 / 12  # Poisson variance in DN^2, plus rounding
    assert out.mean() == pytest.approx(top * level, rel=1e-3)
    assert out.astype(np.float64).var() == pytest.approx(expected, rel=0.03)


@pytest.mark.parametrize("read", [0.7, 3.0, 40.0])
def test_read_noise_is_gaussian_in_dn(read: float) -> None:
    out = CameraEffects(read_noise_dn=read, bit_depth=12).apply(np.full((20, 64, 64), 0.5, np.float32), rng())
    assert out.astype(np.float64).var() == pytest.approx(read**2 + 1 / 12, rel=0.05)


def test_few_electrons_are_counted_exactly() -> None:
    # one DN per electron: the stored values are the photo-electron counts, Poisson(3)
    out = CameraEffects(full_well_e=2**16 - 1, bit_depth=16).apply(
        np.full((10, 64, 64), 3 / (2**16 - 1), np.float32), rng()
    )
    counts = out.astype(np.float64)
    assert counts.mean() == pytest.approx(3.0, rel=0.02) and counts.var() == pytest.approx(3.0, rel=0.05)
    assert (out == 0).mean() == pytest.approx(np.exp(-3.0), rel=0.08)


def test_the_noise_grows_with_the_preset() -> None:
    frames = np.full((8, 32, 32), 0.4, np.float32)
    spread = [
        noise_preset(name, 12).apply(frames, rng()).astype(float).std() for name in ("none", "low", "lab", "high")
    ]
    assert spread == sorted(spread) and spread[0] == 0.0


def test_presets_keep_read_noise_in_electrons_across_bit_depths() -> None:
    for name, (full_well, read_e, _, _) in NOISE_PRESETS.items():
        for bit_depth in BIT_DEPTHS:
            effects = noise_preset(name, bit_depth)
            electrons = effects.read_noise_dn / (2**bit_depth - 1) * full_well
            assert electrons == pytest.approx(read_e) and effects.bit_depth == bit_depth


@given(dx=st.floats(-3.0, 3.0), dy=st.floats(-3.0, 3.0))
@settings(max_examples=40, deadline=None)
def test_a_shift_moves_the_centroid_by_exactly_that_much(dx: float, dy: float) -> None:
    frames = np.zeros((1, 24, 24), np.float32)
    frames[0, 10:13, 11:13] = 0.5
    out = optics(frames, CameraEffects(shift_px=(dx, dy)).per_frame(1))
    total, cx, _ = moments(out[0])
    _, cy, _ = moments(out[0].T)
    assert total == pytest.approx(3.0, rel=1e-5)
    assert cx == pytest.approx(11.5 + dx, abs=1e-4) and cy == pytest.approx(11.0 + dy, abs=1e-4)


@pytest.mark.parametrize("sigma", [1.0, 1.5, 2.5])
def test_the_psf_spreads_a_point_by_its_sigma(sigma: float) -> None:
    frames = np.zeros((1, 41, 41), np.float32)
    frames[0, 20, 20] = 1.0
    total, cx, var = moments(optics(frames, CameraEffects(blur_sigma_px=sigma).per_frame(1))[0])
    assert total == pytest.approx(1.0, rel=1e-5) and cx == pytest.approx(20.0, abs=1e-5)
    assert var == pytest.approx(sigma**2, rel=0.01)


def test_augmentation_draws_stay_inside_their_ranges() -> None:
    ranges = EffectRanges()
    drawn = ranges.sample(2000, rng())
    for name in ("gain", "offset", "blur_sigma_px", "full_well_e", "read_noise_dn"):
        lo, hi = getattr(ranges, name)
        values = getattr(drawn, name)
        assert values.shape == (2000,) and lo <= values.min() and values.max() <= hi
    assert drawn.shift_px.shape == (2000, 2) and np.abs(drawn.shift_px).max() <= ranges.shift_px
    half = drawn[:1000]
    assert len(half) == 1000 and np.array_equal(half.gain, drawn.gain[:1000])


def test_settings_are_validated() -> None:
    with pytest.raises(ValueError):
        CameraEffects(gain=-1.0)
    with pytest.raises(ValueError):
        CameraEffects(bit_depth=9)
    with pytest.raises(ValueError):
        CameraEffects(read_noise_dn=float("nan"))
