"""`meniscope bench pipeline` runs offline analysis and the live pipeline on one recording and reports, for each,
frames/s and the CPU it spent per frame (its fit processes included, and their share) and in each thread, as the user
runs it."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path


def test_bench_pipeline_reports_both_pipelines_with_their_cpu_per_frame(demo_cine: Path, tmp_path: Path) -> None:
    out = tmp_path / "pipeline.json"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "service.cli",
            "bench",
            "pipeline",
            str(demo_cine),
            "--repeat",
            "1",
            "--workers",
            "1",
            "--out",
            str(out),
        ],
        check=True,
        capture_output=True,
        timeout=300,
    )
    results = json.loads(out.read_text())
    for name in ("offline", "live"):
        (run,) = results[name]
        assert run["frames_per_s"] > 0 and run["windows"] > 0
        # the fit processes' CPU is counted: at least the time one frame's inference takes, far below a second
        assert 1 < run["cpu_us_per_frame"] < 1e6
        assert 0 < run["fit_cpu_us_per_frame"] < run["cpu_us_per_frame"]  # the fits ran in processes of their own
        threads = run["threads_us_per_frame"]
        assert min(threads.values()) >= 0
        # the threads are this process's and the fit processes are counted once: together no more than the whole
        # (the live fit workers' start left out), give or take a clock tick (10 ms) each
        tick_per_frame = 1e4 / (run["frames_per_s"] * run["seconds"])
        assert sum(threads.values()) <= run["cpu_us_per_frame"] + len(threads) * tick_per_frame
    assert {"MainThread", "meniscope-read-ahead", "meniscope-hash", "fit processes"} <= set(
        results["offline"][0]["threads_us_per_frame"]
    )
    assert {"MainThread", "meniscope-acquire", "fit workers (after their start)"} <= set(
        results["live"][0]["threads_us_per_frame"]
    )
    assert results["offline_over_live"] == results["offline_median_frames_per_s"] / results["live_median_frames_per_s"]
    text = out.with_suffix(".md").read_text()
    assert "CPU us/frame" in text and "of it fit processes" in text
    for table in (t for t in text.split("\n\n") if t.lstrip().startswith("|")):
        header, _, *rows = [line for line in table.splitlines() if line.startswith("|")]
        assert rows and all(row.count("|") == header.count("|") for row in rows)  # a cell for every column
    assert "| meniscope-acquire | live |" in text
