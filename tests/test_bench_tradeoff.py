"""`meniscope bench tradeoff --mode quick`: every inverse method on the same held-out recordings, with the
renderer, the window fit and the replay pipeline beside them, in one run and one table; further model
folders (here an int8 copy of the shipped one) as rows of their own."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from service.bench import fitsuite
from service.bench.tradeoff import misses
from tests.servicekit import meniscope

#: A learned method's row exactly at every target: issue 4's accuracy targets and the camera's 19,000 frames/s.
AT_TARGETS = {
    "method": "network",
    "frames_per_s": 19000.0,
    "ms_per_window": 40.0,
    "frequency_median": 0.005,
    "decay_median": 0.05,
    "amplitude_median": 0.10,
    "offset_mm_median": 0.002,
}


def test_a_row_exactly_at_every_target_misses_none() -> None:
    assert misses(AT_TARGETS) == []


@pytest.mark.parametrize(
    "figure, value, missed",
    [
        ("frequency_median", 0.0051, "frequency 0.0051 > 0.005"),
        ("decay_median", 0.0501, "decay 0.0501 > 0.05"),
        ("amplitude_median", 0.25, "amplitude 0.25 > 0.1"),
        ("offset_mm_median", 0.0114, "offset 0.0114 > 0.002"),
        ("decay_median", None, "decay not measured (no window with a mode)"),
    ],
)
def test_an_accuracy_figure_above_its_target_or_not_measured_misses_it(
    figure: str, value: float | None, missed: str
) -> None:
    assert misses({**AT_TARGETS, figure: value}) == [missed]


@pytest.mark.parametrize("method", ["network", "direct"])
def test_the_learned_methods_miss_the_camera_rate_below_it(method: str) -> None:
    assert misses({**AT_TARGETS, "method": method}) == []
    assert misses({**AT_TARGETS, "method": method, "frames_per_s": 5170.4}) == ["5,170.4 frames/s < camera 19,000"]
    assert misses({**AT_TARGETS, "method": method, "frames_per_s": 18999.6}) == ["18,999.6 frames/s < camera 19,000"]


def test_the_regularised_method_misses_one_second_per_window_above_it() -> None:
    row = {**AT_TARGETS, "method": "regularised", "frames_per_s": 50.0}
    assert misses({**row, "ms_per_window": 1000.0}) == []
    assert misses({**row, "ms_per_window": 1500.0}) == ["1.50 s/window > 1 s"]


def test_a_refinement_misses_a_windows_ten_milliseconds_above_them_and_not_the_camera_rate() -> None:
    row = {**AT_TARGETS, "refine": True, "frames_per_s": 9.0}
    assert misses({**row, "ms_per_window": 10.0}) == []
    assert misses({**row, "ms_per_window": 21_500.0}) == ["21,500 ms/window > a window's 10 ms"]


@pytest.mark.parametrize("method", ["nearest", "nearest-approx"])
def test_the_nearest_methods_have_no_speed_target(method: str) -> None:
    assert misses({**AT_TARGETS, "method": method, "frames_per_s": 1.0, "ms_per_window": 1e6}) == []


def test_every_target_missed_is_listed_accuracy_first() -> None:
    row = {**AT_TARGETS, "method": "direct", "frames_per_s": 5613.0, "decay_median": 0.533, "frequency_median": 0.208}
    assert misses(row) == ["frequency 0.208 > 0.005", "decay 0.533 > 0.05", "5,613.0 frames/s < camera 19,000"]


@pytest.fixture(scope="module")
def tradeoff(tmp_path_factory: pytest.TempPathFactory, int8: Path) -> Path:
    root = tmp_path_factory.mktemp("tradeoff")
    db = root / "db600"
    done = meniscope("database", "--samples", "600", "--chunk-size", "300", "--workers", "1", "--out", db)
    assert done.returncode == 0, done.stderr
    out = root / "out"
    done = meniscope("bench", "tradeoff", "--mode", "quick", "--database", db, "--more-models", int8, "--out", out)
    assert done.returncode == 0, done.stderr
    return out


def test_every_method_is_measured_at_both_noise_levels_with_the_targets_it_misses(tradeoff: Path):
    results = json.loads((tradeoff / "tradeoff.json").read_text())
    labels = {(r["label"], r["noise"]) for r in results["methods"]}
    expected = {
        "network 32px + window model",  # what analyze runs by default
        "network 32px",
        "network 32px + synthesis",  # analyze --refine
        "direct 32px",
        "network 32px int8 static",
        "direct 32px int8 static",
        "nearest db600",
        "nearest-approx db600",
        "regularised db600",
    }
    assert labels == {(m, n) for m in expected for n in ("low", "high")}
    for row in results["methods"]:
        assert row["frames_per_s"] > 0 and row["ms_per_window"] > 0 and row["peak_memory_mb"] > 50
        assert row["precision"] == row["recall"] == 1.0  # the same ejections, whatever the method
        assert row["misses"] == misses(row)  # exactly the targets its own figures miss
    refined = [r for r in results["methods"] if r["refine"]]
    assert [len(r["recording_files"]) for r in refined] == [1, 1] and all(r["series"] == "window" for r in refined)
    table = (tradeoff / "tradeoff.md").read_text()
    assert table.count("| regularised db600 |") == 2 and "Beside them" in table
    for row in results["methods"]:  # the table's last column says the same, or "none"
        line = next(t for t in table.splitlines() if t.startswith(f"| {row['label']} | {row['noise']} |"))
        assert line.endswith(f"| {'; '.join(row['misses']) or 'none'} |")


def test_renderer_fit_and_pipeline_are_measured_in_the_same_run(tradeoff: Path):
    results = json.loads((tradeoff / "tradeoff.json").read_text())
    assert [c["name"] for c in results["fit"]["categories"]] == [c.name for c in fitsuite.CATEGORIES]
    assert results["render"]["cycles"]["frames_per_s"] > 0 and results["render"]["ours"]
    assert 0 < results["realtime_factor"] <= 1.1
    assert (tradeoff / "tradeoff.png").stat().st_size > 10_000


def test_a_set_of_recordings_is_given_as_label_and_folder(tmp_path: Path) -> None:
    for spec, problem in [
        ("blender", "give LABEL=FOLDER"),
        ("low=" + str(tmp_path), "the label 'low' is taken"),
        ("blender=" + str(tmp_path), "no recordings with a .truth.json"),
    ]:
        done = meniscope("bench", "tradeoff", "--recordings", spec, "--out", tmp_path / "out")
        assert done.returncode != 0 and problem in done.stderr and "Traceback" not in done.stderr
        assert not (tmp_path / "out").exists()  # refused before anything is simulated
