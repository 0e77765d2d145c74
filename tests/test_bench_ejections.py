"""meniscope bench ejections: each recording's ejections scored live and offline, a table per kind."""

from __future__ import annotations

import json
from pathlib import Path

from tests.servicekit import meniscope


def test_bench_ejections_scores_a_recording_with_its_truth_live_and_offline(demo_cine: Path, tmp_path: Path) -> None:
    out = tmp_path / "EJECTIONS.json"
    done = meniscope("bench", "ejections", "--recordings", demo_cine, "--out", out)
    assert done.returncode == 0, done.stderr
    rows = json.loads(out.read_text())["kinds"][demo_cine.name]
    truth = json.loads(demo_cine.with_suffix(".truth.json").read_text())
    scored = len(truth["ejections"]) - 1  # the first, frame 0, has no frames before it
    assert rows == [{"recording": demo_cine.name, "live": [scored] * 3, "offline": [scored] * 3}]
    table = out.with_suffix(".md").read_text()
    assert f"| {demo_cine.name} | {scored} | 1.000 | 1.000 | 1.000 | 1.000 |" in table
