"""``meniscope calibrate`` as a user runs it: its options checked before any frame is read, and a held parameter end to
end."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from service import DEFAULT_SCENE
from service.scene import Scene
from service.simulate import simulate
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


def test_a_held_parameter_keeps_the_guesss_value_end_to_end(tmp_path: Path) -> None:
    """``calibrate --hold`` as a user runs it, on a small camera (40 px: seconds): the written scene keeps the held
    values exactly, the report marks them held (neither identified nor not), the last line names them, and the report
    is JSON without NaN."""
    data = json.loads(Path(DEFAULT_SCENE).read_text())
    data["camera"].update(width_px=40, height_px=40, roi=[0, 0])
    data["artifacts"]["count"] = 0
    data["light"]["angle_deg"] = 3.3
    guess = tmp_path / "guess.json"
    guess.write_text(json.dumps(data))
    simulate(Scene.from_dict(data), tmp_path / "lab.cine", windows=2, seed=3, ejection_hz=1000.0)
    out = tmp_path / "scene.json"
    done = meniscope(
        "calibrate", str(tmp_path / "lab.cine"), "--scene", str(guess), "--out", str(out), "--hold", "light.angle_deg",
        "--windows", "0", "--ejection-hz", "1000", "--frames", "8", "--stack", "38",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "held at the guess's value: light.angle_deg" in done.stdout
    assert Scene.load(out).light.angle_deg == 3.3
    report = json.loads(out.with_suffix(".calibration.json").read_text(), parse_constant=lambda c: pytest.fail(c))
    rows = {row["name"]: row for row in report["parameters"]}
    assert rows["light.angle_deg"]["held"] and rows["light.angle_deg"]["identified"] is None
    assert not any(row["held"] for name, row in rows.items() if name != "light.angle_deg")
