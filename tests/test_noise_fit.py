"""The sensor's noise from a lab video's still pixels (`service.calibration.noise.fit_noise`): shot and read noise
recovered on a dim camera whose still pixels span little signal, with a few pixels that are not still among them."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from service.calibration.noise import fit_noise

FULL_SCALE = 4095.0  # a 12-bit camera


def _dim_stack(seed: int, full_well: float, read_e: float, moving: int, swing: float) -> tuple[np.ndarray, float]:
    """120 frames of 6,000 still pixels (fractions of full scale, quantised to 12 bits) of a camera at x0.4 exposure:
    a black background and a dim nozzle face (0.0066 above a black level of 0.04), shot and read noise; ``moving``
    of the face's pixels also swing by ``swing`` of full scale over the frames (a shadow reaching them now and
    then), so they are not still."""
    rng = np.random.default_rng(seed)
    black = 0.04
    signal = np.where(rng.random(6000) < 0.4, 0.0, rng.normal(0.0066, 0.0004, 6000).clip(0.0))
    electrons = rng.poisson(np.broadcast_to(signal * full_well, (120, 6000)))
    frames = electrons / full_well + black + rng.normal(0.0, read_e / full_well, (120, 6000))
    frames[:, 3000 : 3000 + moving] += swing * np.sin(np.linspace(0, 3, 120))[:, None]
    return np.round(frames * FULL_SCALE) / FULL_SCALE, black


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31), st.sampled_from([8000.0, 16000.0, 30000.0]), st.integers(0, 120), st.floats(0.002, 0.05))
def test_a_dim_cameras_shot_and_read_noise_are_recovered_past_pixels_that_are_not_still(
    seed: int, full_well: float, moving: int, swing: float
) -> None:
    """Up to 2 % of the pixels taken for still ones move, by 50 to 30,000 times a still pixel's variance: the line
    of variance over signal is refitted without them until the pixels kept settle: the read noise (in full scale)
    comes back within 5 % and the full well, which rests on the 0.0066 of signal the still pixels span, within 15 %
    (with three refits, 120 such pixels swinging by 5 % of full scale left a full well 96 % low; the Blender lab
    video at x0.4 exposure gave 8,400 e for 16,000)."""
    stack, black = _dim_stack(seed, full_well, 20.0, moving, swing)
    fit = fit_noise(stack.reshape(120, 60, 100), np.ones((60, 100), bool), black, FULL_SCALE)
    assert abs(fit.read_noise_fraction * full_well / 20.0 - 1) <= 0.05
    assert abs(fit.full_well_e / full_well - 1) <= 0.15


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 2**31), st.sampled_from([8, 12]), st.one_of(st.floats(0.1, 0.4), st.floats(0.6, 3.0)))
def test_the_noise_counts_as_measured_only_where_it_spans_half_a_quantisation_step(
    seed: int, bits: int, steps: float
) -> None:
    """Under half a step of read noise the rounding's variance is no longer the uniform step^2 / 12 the fit takes
    off: an 8- or 12-bit camera with a 16,000 e well and read noise well clear of half a step either way (0.1-0.4 or
    0.6-3 steps) is measured only from half a step up."""
    full_scale = 2.0**bits - 1
    read_e = steps / full_scale * 16000
    rng = np.random.default_rng(seed)
    signal = np.where(rng.random(6000) < 0.4, 0.0, 0.02)
    frames = rng.poisson(np.broadcast_to(signal * 16000, (120, 6000))) / 16000 + 0.01
    frames = np.round((frames + rng.normal(0.0, read_e / 16000, frames.shape)) * full_scale) / full_scale
    fit = fit_noise(frames.reshape(120, 60, 100), np.ones((60, 100), bool), 0.01, full_scale)
    assert fit.measured(full_scale) == (steps >= 0.5)
