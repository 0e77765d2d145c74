"""service.render.agreement: highlight centroids, correlation and gain between two renderers' frames."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from service.errors import MeniscopeError
from service.render.agreement import HIGHLIGHT_THRESHOLD, compare, highlights


def spot(shape: tuple[int, int], x: float, y: float, sigma: float = 1.5, peak: float = 1.0) -> np.ndarray:
    """A Gaussian highlight centred at column x, row y, on a dim background."""
    rows, cols = np.mgrid[: shape[0], : shape[1]]
    return 0.02 + (peak - 0.02) * np.exp(-((cols - x) ** 2 + (rows - y) ** 2) / (2 * sigma**2))


def test_centroid_of_a_single_bright_pixel_is_that_pixel_as_column_then_row():
    frame = np.zeros((5, 7))
    frame[1, 4] = 0.9
    h = highlights(frame)
    assert h.found.tolist() == [True]
    np.testing.assert_allclose(h.centroid[0], [4.0, 1.0])


def test_centroid_is_weighted_by_intensity_above_the_threshold_only():
    frame = np.full((3, 10), HIGHLIGHT_THRESHOLD * 0.99)  # everything just below the threshold
    frame[1, 2], frame[1, 8] = 1.0, 0.5
    np.testing.assert_allclose(highlights(frame).centroid[0], [(2 * 1.0 + 8 * 0.5) / 1.5, 1.0])


@given(dx=st.integers(-10, 10), dy=st.integers(-10, 10))
def test_shifting_the_highlight_by_whole_pixels_gives_that_centroid_distance(dx, dy):
    ours = spot((48, 64), 30, 22)[None]
    reference = spot((48, 64), 30 + dx, 22 + dy)[None]
    a = compare(ours, reference)
    assert a.both_found.tolist() == [True]
    assert a.distance_px[0] == pytest.approx(np.hypot(dx, dy), abs=1e-6)


@given(gain=st.floats(1e-3, 1e3), offset=st.floats(-1e3, 1e3))
def test_correlation_ignores_gain_and_offset_and_the_gain_is_recovered(gain, offset):
    ours = spot((16, 16), 7.3, 8.1)[None]
    a = compare(ours, gain * ours + offset, threshold=np.inf)
    assert a.correlation[0] == pytest.approx(1.0, abs=1e-9)
    if offset == 0:
        assert a.gain[0] == pytest.approx(gain, rel=1e-9)


def test_an_inverted_image_correlates_negatively():
    ours = spot((16, 16), 8, 8)[None]
    assert compare(ours, 1.0 - ours).correlation[0] == pytest.approx(-1.0)


def test_frames_without_a_highlight_are_counted_separately_and_never_compared():
    dark = np.full((1, 8, 8), 0.01)
    lit = spot((8, 8), 3, 4)[None]
    a = compare(np.concatenate([lit, lit, dark, dark]), np.concatenate([lit, dark, lit, dark]))
    s = a.summary()
    assert (s["highlight_both"], s["highlight_ours_only"], s["highlight_reference_only"], s["highlight_neither"]) == (
        1,
        1,
        1,
        1,
    )
    assert s["highlight_both_fraction"] == 0.25
    assert s["centroid_distance_median_px"] == 0.0


def test_constant_frames_have_no_correlation_and_the_summary_says_none():
    a = compare(np.zeros((3, 4, 4)), np.ones((3, 4, 4)))
    s = a.summary()
    assert s["correlated_frames"] == 0
    assert s["correlation_median"] is None and s["correlation_p10"] is None and s["gain_median"] is None
    assert s["centroid_distance_median_px"] is None
    json.dumps(s, allow_nan=False)


@settings(max_examples=100, deadline=None)
@given(
    pair=st.integers(1, 6).flatmap(
        lambda h: st.tuples(*(arrays(np.float32, (3, h, 5), elements=st.floats(0, 1, width=32)) for _ in range(2)))
    )
)
def test_any_frames_in_the_unit_range_give_a_finite_json_summary(pair):
    ours, reference = pair
    s = compare(ours, reference).summary()
    text = json.dumps(s, allow_nan=False)  # raises on NaN or Infinity
    assert json.loads(text)["frames"] == 3
    for key in ("correlation_median", "correlation_p10"):
        assert s[key] is None or -1.0 <= s[key] <= 1.0


def test_summary_percentiles_over_many_frames():
    rng = np.random.default_rng(0)
    n = 50
    shifts = np.arange(n)  # centroid distance k px in frame k
    ours = np.stack([spot((20, 80), 10, 10) for _ in range(n)])
    reference = np.stack([spot((20, 80), 10 + k, 10) for k in shifts])
    reference = reference + rng.normal(0, 1e-3, reference.shape)
    s = compare(ours, reference).summary()
    assert s["centroid_distance_median_px"] == pytest.approx(np.percentile(shifts, 50), abs=0.05)
    assert s["centroid_distance_p90_px"] == pytest.approx(np.percentile(shifts, 90), abs=0.05)
    assert s["correlation_p10"] <= s["correlation_median"]


@pytest.mark.parametrize(
    ("ours", "reference", "problem"),
    [
        (np.zeros((2, 4, 4)), np.zeros((3, 4, 4)), "do not match"),
        (np.zeros((2, 4, 4)), np.full((2, 4, 4), np.nan), "NaN"),
        (np.zeros((4,)), np.zeros((4,)), "shape (N, H, W)"),
    ],
)
def test_bad_input_is_a_one_line_error_naming_the_problem(ours, reference, problem):
    with pytest.raises(MeniscopeError, match=problem.replace("(", r"\(").replace(")", r"\)")):
        compare(ours, reference)
