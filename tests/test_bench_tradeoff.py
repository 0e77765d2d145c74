"""`meniscope bench tradeoff --mode quick`: every inverse method on the same held-out recordings, with the
renderer, the window fit and the replay pipeline beside them, in one run and one table; further model
folders (here an int8 copy of the shipped one) as rows of their own."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from service import DEFAULT_MODELS


def meniscope(*args: str | Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-P", "-m", "service.cli", *map(str, args)], capture_output=True,
                          text=True, timeout=900)


@pytest.fixture(scope="module")
def tradeoff(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("tradeoff")
    db = root / "db600"
    done = meniscope("database", "--samples", "600", "--chunk-size", "300", "--workers", "1", "--out", db)
    assert done.returncode == 0, done.stderr
    int8 = root / "int8"
    done = meniscope("quantize", "--models", DEFAULT_MODELS, "--out", int8, "--calibration", "64", "--parity", "16")
    assert done.returncode == 0, done.stderr
    out = root / "out"
    done = meniscope("bench", "tradeoff", "--mode", "quick", "--database", db, "--more-models", int8, "--out", out)
    assert done.returncode == 0, done.stderr
    return out


def test_every_method_is_measured_at_both_noise_levels_with_the_targets_it_misses(tradeoff: Path):
    results = json.loads((tradeoff / "tradeoff.json").read_text())
    labels = {(r["label"], r["noise"]) for r in results["methods"]}
    expected = {"network 32px", "direct 32px", "network 32px int8 static", "direct 32px int8 static", "nearest db600",
                "nearest-approx db600", "regularised db600"}
    assert labels == {(m, n) for m in expected for n in ("low", "high")}
    for row in results["methods"]:
        assert row["frames_per_s"] > 0 and row["ms_per_window"] > 0 and row["peak_memory_mb"] > 50
        assert row["precision"] == row["recall"] == 1.0  # the same ejections, whatever the method
        assert all(isinstance(m, str) for m in row["misses"])
    table = (tradeoff / "tradeoff.md").read_text()
    assert table.count("| regularised db600 |") == 2 and "Beside them" in table


def test_renderer_fit_and_pipeline_are_measured_in_the_same_run(tradeoff: Path):
    results = json.loads((tradeoff / "tradeoff.json").read_text())
    assert {lv["noise_mm"] for lv in results["fit"]["levels"]} == {2e-4, 1e-3}
    assert results["render"]["cycles"]["frames_per_s"] > 0 and results["render"]["ours"]
    assert 0 < results["realtime_factor"] <= 1.1
    assert (tradeoff / "tradeoff.png").stat().st_size > 10_000
