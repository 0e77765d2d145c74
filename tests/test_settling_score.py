"""Whether the meniscus settled, scored against the truth: the verdict `bench analysis` reports beside the errors."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from service.analysis.results import FitSettings, Report, Source, WindowResult
from service.validation.score import settling_statistics, window_settled

FPS = 19000.0


def true_window(start: int, g1: float) -> dict:
    """A 190-frame true window whose oscillation starts 5 frames in: 20 um at 1,500 Hz decaying at ``g1``, 5 um of
    mode 2 decaying twice as fast."""
    truth = {"A1": 0.02, "g1": g1, "f1": 1500.0, "A2": 0.005, "g2": 2 * g1, "f2": 3450.0}
    return {"start_frame": start, "end_frame": start + 190, "oscillation_start_frame": start + 5, "truth": truth}


def report(said: list[bool | None]) -> Report:
    """Windows 190 frames apart saying settled or not (None: no window there), one frame off the truth's starts."""
    windows = [
        WindowResult(
            index=i,
            start_frame=190 * i + 1,
            end_frame=190 * i + 190,
            status="ok",
            settled=bool(s),
            settling_time_s=0.004 if s else None,
        )
        for i, s in enumerate(said)
        if s is not None
    ]
    return Report(source=Source(path="x.cine", frames=190 * len(said), fps=FPS), method="t", windows=windows)


def test_each_window_is_judged_by_what_is_left_of_its_modes_at_its_end():
    """After 185 frames (9.7 ms) a mode decaying at 150 /s keeps 24 % of itself (unsettled, over 5 % of the 25 um),
    one at 1,000 /s under 0.01 % (settled); the report's verdicts match where it says so, an unmatched window is
    wrong, and the unsettled window called settled is the error counted apart."""
    truth = {"windows": [true_window(0, 150.0), true_window(190, 1000.0), true_window(380, 150.0)]}
    true, said = window_settled(report([True, True, None]), truth)
    assert true.tolist() == [0, 1, 0] and said.tolist() == [1, 1, -1]
    assert settling_statistics(true, said) == {"settled_right": 1 / 3, "settled_falsely": 0.5}


def test_the_tolerance_is_the_report_s_own():
    """The same window is settled under a looser tolerance (half its start, or a floor of 10 um) and not under the
    default (5 % of its start, 0.5 um)."""
    truth = {"windows": [true_window(0, 150.0)]}
    for fit, settled in (
        (FitSettings(), 0),
        (FitSettings(settle_fraction=0.5), 1),
        (FitSettings(settle_floor_mm=0.01), 1),
    ):
        loose = report([False]).model_copy(update={"fit": fit})
        assert window_settled(loose, truth)[0].tolist() == [settled]


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 1), st.integers(-1, 1)), max_size=30))
def test_the_shares_are_fractions_or_none_never_nan(pairs):
    """Any verdicts (missing windows among them): shares within [0, 1], None where there is nothing to count."""
    true = np.array([t for t, _ in pairs], np.int64)
    said = np.array([s for _, s in pairs], np.int64)
    stats = settling_statistics(true, said)
    assert (stats["settled_right"] is None) == (true.size == 0)
    assert (stats["settled_falsely"] is None) == (not (true == 0).any())
    assert all(v is None or 0.0 <= v <= 1.0 for v in stats.values())
