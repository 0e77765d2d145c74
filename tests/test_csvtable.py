"""The numeric CSV tables beside a report: what is written reads back, at the extremes of float64."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from service.csvtable import read_columns, write_columns
from service.errors import MeniscopeError

#: Any float64 (subnormals included) whose nine digits parse back as a finite number, and the non-finite ones.
floats = arrays(
    np.float64,
    st.integers(1, 40),
    elements=st.floats(-1e308, 1e308) | st.sampled_from([np.nan, np.inf, -np.inf]),
)


@settings(max_examples=60, deadline=None)
@given(values=floats)
def test_floats_read_back_to_nine_digits_and_non_finite_ones_as_missing(tmp_path_factory, values: np.ndarray):
    path = tmp_path_factory.mktemp("csv") / "t.csv"
    index = np.arange(values.size, dtype=np.int64) * 7_000_000_000  # beyond 32 bits
    write_columns(path, ("i", "x"), [index, values], "table")
    back = read_columns(path, ("i", "x"), allow_empty=True)
    finite = np.isfinite(values)
    assert back.shape == (values.size, 2)
    assert np.array_equal(back[:, 0], index.astype(np.float64))
    assert np.array_equal(np.isnan(back[:, 1]), ~finite)
    np.testing.assert_allclose(back[finite, 1], values[finite], rtol=5e-9, atol=0)


def test_each_float_has_nine_significant_digits_and_integers_stay_whole(tmp_path: Path):
    path = write_columns(
        tmp_path / "t.csv",
        ("frame", "value", "small"),
        [np.array([0, 18_446_744_073_709_551_615], np.uint64), np.array([np.pi, -0.0]), np.float32([0.1, 5e-45])],
        "table",
    )
    assert path.read_text().splitlines() == [
        "frame,value,small",
        "0,3.14159265,0.100000001",
        "18446744073709551615,-0,5.60519386e-45",
    ]


def test_an_unwritable_place_is_one_line_naming_the_file(tmp_path: Path):
    target = tmp_path / "missing" / "t.csv"
    with pytest.raises(MeniscopeError) as failed:
        write_columns(target, ("x",), [np.zeros(3)], "per-frame table")
    message = str(failed.value)
    assert str(target) in message and "cannot write the per-frame table" in message and "\n" not in message
