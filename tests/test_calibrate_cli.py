"""``meniscope calibrate`` as a user runs it: its options checked before any frame is read."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.servicekit import meniscope


@pytest.mark.parametrize(
    ("option", "value", "allowed"),
    [
        ("--windows", "-1", "between 0 and 12"),
        ("--windows", "13", "between 0 and 12"),
        ("--edge-rays", "-1", "between 0 and 16"),
        ("--edge-rays", "17", "between 0 and 16"),
        ("--hold", "light.angle", "not a calibrated parameter"),
    ],
)
def test_an_option_outside_its_range_is_a_one_line_error(tmp_path: Path, option: str, value: str, allowed: str) -> None:
    """A window count beyond what the window stage reads, edge rays beyond what the renderer is meant for, or a
    parameter to hold that the calibration does not have."""
    out = tmp_path / "scene.json"
    done = meniscope("calibrate", str(tmp_path / "lab.cine"), "--out", str(out), option, value)
    assert done.returncode == 2
    assert done.stderr.count("\n") == 1 and option in done.stderr and allowed in done.stderr
    assert not out.exists()


def test_the_help_says_how_to_skip_the_window_stage() -> None:
    done = meniscope("calibrate", "--help")
    assert done.returncode == 0 and "--windows" in done.stdout and "0 to skip" in done.stdout
