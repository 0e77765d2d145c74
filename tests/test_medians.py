"""The frame path's medians are numpy's to the bit, at the extremes of float64 too."""

import math
import warnings

import numpy as np
from hypothesis import example, given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from service.medians import median, nanmedian

_any = st.floats(allow_nan=True, allow_infinity=True)
_series = arrays(np.float64, st.integers(0, 700), elements=_any)
_finite = arrays(np.float64, st.integers(1, 700), elements=st.floats(allow_nan=False, allow_infinity=False))


def _same(ours: float, numpy: float) -> bool:
    return (math.isnan(ours) and math.isnan(numpy)) or (
        ours == numpy and math.copysign(1, ours) == math.copysign(1, numpy)
    )


@example(np.array([-0.0]))
@example(np.array([-0.0, -0.0]))
@given(_series)
def test_median_is_numpys(values: np.ndarray) -> None:
    with np.errstate(all="ignore"):
        expected = float(np.median(values)) if values.size else math.nan
    assert _same(median(values), expected)


@example(np.array([-0.0, np.nan]))
@example(np.array([-0.0, -0.0, np.nan]))
@given(_series)
def test_nanmedian_is_numpys(values: np.ndarray) -> None:
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # numpy's all-NaN warning
        expected = float(np.nanmedian(values)) if values.size else math.nan
    assert _same(nanmedian(values), expected)


@given(_finite)
def test_finite_medians_agree(values: np.ndarray) -> None:
    """Without NaN both are the middle of the sorted values (an even count's two middle ones averaged)."""
    with np.errstate(over="ignore"):  # two middle values beyond half of float64's largest: inf, as numpy's
        assert _same(median(values), nanmedian(values))
        assert _same(median(values.tolist()), float(np.median(values)))


def test_integer_intervals() -> None:
    """The detector's intervals are integers: their median is numpy's float."""
    assert median([190, 191, 189, 190]) == float(np.median([190, 191, 189, 190])) == 190.0
    assert median([3, 4]) == 3.5
