"""Eq. 1 and its time model: exact at the rim and centre, sound at the extremes, never NaN."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.special import j0

from service.physics import (
    L1,
    L2,
    CoefficientRanges,
    Coefficients,
    WindowMotion,
    centre_displacement,
    damped_mode,
    displacement,
    slope,
)

R = 0.25
amplitudes = st.floats(min_value=1e-9, max_value=1.0) | st.floats(min_value=-1.0, max_value=-1e-9) | st.just(0.0)
radii = st.floats(min_value=0.0, max_value=R)


def test_bessel_roots_are_roots() -> None:
    assert abs(j0(L1)) < 1e-15 and abs(j0(L2)) < 1e-15


@given(d=amplitudes, p=amplitudes, a=amplitudes, b=amplitudes)
def test_rim_and_centre_are_exact(d: float, p: float, a: float, b: float) -> None:
    # J0 vanishes at its roots to ~1e-16: the rim sits at d up to rounding of the mode terms
    assert displacement(R, d, p, a, b, R) == pytest.approx(d, rel=1e-12, abs=1e-15 * (abs(a) + abs(b)) + 1e-300)
    centre = float(centre_displacement(d, p, a, b, R))
    assert displacement(0.0, d, p, a, b, R) == pytest.approx(centre, rel=1e-12, abs=1e-300)
    assert slope(0.0, p, a, b, R) == 0.0


@given(r=radii, p=amplitudes, a=amplitudes, b=amplitudes)
def test_slope_is_the_derivative_of_eq1(r: float, p: float, a: float, b: float) -> None:
    h = 1e-6
    lo, hi = max(r - h, 0.0), min(r + h, R)
    numeric = (displacement(hi, 0, p, a, b, R) - displacement(lo, 0, p, a, b, R)) / (hi - lo)
    scale = abs(p) + abs(a) + abs(b)
    assert abs(slope(r, p, a, b, R) - numeric) <= 1e-4 * scale * (L2 / R) ** 2 + 1e-12


def test_broadcasts_over_radii_frames_and_parameter_sets() -> None:
    r = np.linspace(0, R, 7)[:, None, None]  # radii
    a = np.linspace(-0.01, 0.01, 5)[None, :, None]  # frames
    b = np.array([0.0, 0.002, -0.003])[None, None, :]  # parameter sets
    out = displacement(r, 0.01, 0.1, a, b, R)
    assert out.shape == (7, 5, 3)
    np.testing.assert_allclose(out[3, 2, 1], displacement(r[3, 0, 0], 0.01, 0.1, a[0, 2, 0], b[0, 0, 1], R))


def test_radii_outside_the_bore_are_clipped_to_it() -> None:
    assert displacement(2 * R, 0.01, 0.1, 0.02, 0.01, R) == displacement(R, 0.01, 0.1, 0.02, 0.01, R)


@given(
    t=st.floats(min_value=0.0, max_value=1e6),
    amplitude=amplitudes,
    decay=st.floats(min_value=0.0, max_value=1e7),
    frequency=st.floats(min_value=0.0, max_value=1e5),
    phase=st.floats(min_value=-10.0, max_value=10.0),
)
def test_damped_mode_is_bounded_by_its_envelope_and_never_nan(
    t: float, amplitude: float, decay: float, frequency: float, phase: float
) -> None:
    value = damped_mode(t, amplitude, decay, frequency, phase)
    assert np.isfinite(value)
    assert abs(value) <= abs(amplitude) * np.exp(-decay * t) * (1 + 1e-12) + 1e-300


def test_decay_underflows_to_exactly_zero() -> None:
    assert damped_mode(1e3, 1.0, 1e4, 500.0, 0.3) == 0.0
    assert damped_mode(0.0, 0.5, 0.0, 500.0, 0.0) == 0.5  # g = 0: undamped


def test_window_truth_produces_per_frame_coefficients() -> None:
    truth = WindowMotion(d=0.01, p=0.1, A1=0.02, g1=300, f1=1200, phi1=0.1, A2=0.005, g2=900, f2=2800, phi2=-0.4)
    t = np.arange(190) / 19000
    c = truth.coefficients(t)
    assert len(c) == 190 and c.to_array().shape == (190, 4)
    np.testing.assert_allclose(c.centre(R), 0.01 + 0.1 * R + c.a + c.b)
    np.testing.assert_array_equal(Coefficients.from_array(c.to_array()).to_array(), c.to_array())
    assert set(truth.as_dict()) == {"d", "p", "A1", "g1", "f1", "phi1", "A2", "g2", "f2", "phi2"}


def test_coefficient_ranges_sample_inside_their_bounds() -> None:
    ranges = CoefficientRanges()
    draws = ranges.sample(10_000, np.random.default_rng(0))
    lo, hi = ranges.bounds().T
    assert draws.shape == (10_000, 4) and np.all((draws >= lo) & (draws <= hi))
