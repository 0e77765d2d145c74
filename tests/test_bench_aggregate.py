"""`bench analysis` and `bench tradeoff` report a set of recordings by the errors of its windows pooled: the median
and 90th percentile a user reads are those of every window of the set, not means of each recording's own."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from service.bench.analysis import aggregate
from service.validation.score import QUANTITIES

errors = st.lists(st.floats(0.0, 1e6, allow_nan=False), max_size=40)


def row(windows: dict[str, list[float]], **figures: float) -> dict:
    """A recording's summary row as :func:`service.validation.score.summary` gives it (the figures aggregate reads)."""
    return {"frames": 1900, "seconds": 1.0, **{f"{q}_errors": windows.get(q, []) for q in QUANTITIES}, **figures}


@settings(max_examples=200, deadline=None)
@given(st.lists(st.fixed_dictionaries({q: errors for q in QUANTITIES}), min_size=1, max_size=6))
def test_the_medians_and_p90s_are_those_of_the_windows_pooled(recordings: list[dict[str, list[float]]]) -> None:
    figures = aggregate([row(r) for r in recordings])
    for q in QUANTITIES:
        pooled = np.array([e for r in recordings for e in r[q]])
        if pooled.size:
            assert figures[f"{q}_median"] == np.median(pooled)
            assert figures[f"{q}_p90"] == np.percentile(pooled, 90)
        else:  # no window with this quantity in the whole set: not measured, not zero
            assert figures[f"{q}_median"] is None and figures[f"{q}_p90"] is None


def test_a_short_recordings_bad_tail_does_not_set_the_sets_p90() -> None:
    """Ten windows off by 1 % and one 4-window recording off by 40 % in one window: the set's p90 is 1 % (the
    mean of each recording's p90, the old rule, gave about 14 %)."""
    good = row({"decay": [0.01] * 10})
    short = row({"decay": [0.01, 0.01, 0.01, 0.40]})
    figures = aggregate([good, short])
    assert figures["decay_median"] == 0.01 and figures["decay_p90"] == 0.01


def test_the_other_figures_stay_means_over_recordings() -> None:
    figures = aggregate([row({}, precision=1.0, recall=0.5), row({}, precision=0.5, recall=1.0)])
    assert figures["precision"] == figures["recall"] == 0.75 and figures["recordings"] == 2
