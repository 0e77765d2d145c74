"""``meniscope calibrate`` as a user runs it: its options checked before any frame is read."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.servicekit import meniscope


@pytest.mark.parametrize("windows", ["-1", "13"])
def test_a_window_count_outside_what_the_stage_reads_is_a_one_line_error(tmp_path: Path, windows: str) -> None:
    out = tmp_path / "scene.json"
    done = meniscope("calibrate", str(tmp_path / "lab.cine"), "--out", str(out), "--windows", windows)
    assert done.returncode == 2
    assert done.stderr.count("\n") == 1 and "--windows" in done.stderr and "between 0 and 12" in done.stderr
    assert not out.exists()


def test_the_help_says_how_to_skip_the_window_stage() -> None:
    done = meniscope("calibrate", "--help")
    assert done.returncode == 0 and "--windows" in done.stdout and "0 to skip" in done.stdout
