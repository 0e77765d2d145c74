"""Segmentation: ejections read from the printer's file or placed at its rate (detected: test_ejection_detector)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from service.analysis.segment import (
    ejections_at_rate,
    frame_brightness,
    read_ejections,
    windows_between,
)
from service.errors import MeniscopeError

FPS = 19000.0


def activity(
    ejections: np.ndarray, n: int, seed: int, strengths: np.ndarray | None = None, tail: int = 150
) -> np.ndarray:
    """Frame activity as a video gives it: noise, an ejection's out-and-back double burst, then for ``tail``
    frames a decaying oscillation's flicker about half as strong (single frames rival the weakest ejections)."""
    rng = np.random.default_rng(seed)
    a = np.abs(rng.normal(1.0, 0.2, n))
    strengths = rng.uniform(60, 100, ejections.size) if strengths is None else strengths  # bulges 0.06-0.1 mm
    for e, s in zip(ejections, strengths):
        burst = s * np.array([1.0, 0.2, 0.05, 0.3, 0.8, 0.5])
        a[e : e + 6] += burst[: max(0, min(6, n - e))]
        frames = np.arange(e + 6, min(e + tail, n))
        a[frames] += 0.5 * s * np.exp(-(frames - e) / 40) * np.abs(np.sin(0.4 * (frames - e)))
    return a


def test_windows_run_from_each_ejection_to_the_next():
    w = windows_between([10, 50], 100)
    assert [(x.start, x.end, x.starts_at_ejection, x.ends_at_ejection) for x in w] == [
        (0, 10, False, True),
        (10, 50, True, True),
        (50, 100, True, False),
    ]
    assert [(x.start, x.end) for x in windows_between([], 7)] == [(0, 7)]
    assert [(x.start, x.end) for x in windows_between([0], 7)] == [(0, 7)]
    with pytest.raises(ValueError):
        windows_between([7], 7)


def test_a_known_rate_takes_its_phase_from_the_bursts():
    true = 17 + np.round(190.0 * np.arange(10)).astype(int)
    assert np.array_equal(ejections_at_rate(activity(true, 1900, 1), FPS, 100.0), true)
    with pytest.raises(ValueError):
        ejections_at_rate(np.zeros(100), FPS, 15000.0)


def test_ejection_files_in_frames_and_in_seconds(tmp_path: Path):
    frames = tmp_path / "e.txt"
    frames.write_text("# printer log\n10\n200 # second\n\n390\n")
    assert read_ejections(frames, FPS, 1000).tolist() == [10, 200, 390]
    times = tmp_path / "t.csv"
    times.write_text("time_s,nozzle\n0.001,1\n0.011,1\n")
    assert read_ejections(times, FPS, 1000).tolist() == [19, 209]


@pytest.mark.parametrize(
    "text, message",
    [
        ("", "no ejections"),
        ("10\nabc\n", "line 2"),
        ("10\n10\n", "same frame"),
        ("5000\n", "beyond the series"),
        ("1.5\n", "whole frame"),
        ("-3\n", "non-negative"),
    ],
)
def test_bad_ejection_files_are_one_clear_error(tmp_path: Path, text: str, message: str):
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(MeniscopeError, match=message) as err:
        read_ejections(path, FPS, 1000)
    assert "bad.txt" in str(err.value)


@settings(max_examples=40, deadline=None)
@given(
    dtype=st.sampled_from([np.uint8, np.uint16]),
    side=st.sampled_from([1, 96, 256, 257]),
    fill=st.sampled_from(["max", "zero", "random"]),
    seed=st.integers(0, 2**16),
)
def test_frame_brightness_is_the_exact_mean_up_to_the_largest_sums(dtype, side, fill, seed) -> None:
    """The integer sum behind it switches from 32 to 64 bits where a frame of full-scale 16-bit pixels would
    overflow 32 (256 x 257 pixels): on both sides, and at full scale, it is the float64 mean to the last bit."""
    top = np.iinfo(dtype).max
    frames = {
        "max": np.full((3, side, side), top, dtype),
        "zero": np.zeros((3, side, side), dtype),
        "random": np.random.default_rng(seed).integers(0, top, (3, side, side), endpoint=True).astype(dtype),
    }[fill]
    assert np.array_equal(frame_brightness(frames), frames.reshape(3, -1).mean(axis=1, dtype=np.float64))
