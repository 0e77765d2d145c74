"""`meniscope bench pipeline` runs offline analysis and the live pipeline on one recording and reports, for each,
frames/s and the CPU it spent per frame (its fit processes included), as the user runs it."""

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
    assert results["offline_over_live"] == results["offline_median_frames_per_s"] / results["live_median_frames_per_s"]
    assert "CPU us/frame" in out.with_suffix(".md").read_text()
