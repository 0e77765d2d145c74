"""The training verbs after a runtime-only install (no torch, no onnx): one line saying how to add the extra."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: Run first in the child: importing the extras' modules fails as it does where they are not installed.
WITHOUT = """
import sys
class Absent:
    def find_spec(self, name, path=None, target=None):
        if name.partition(".")[0] in ("torch", "onnx"):
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
sys.meta_path.insert(0, Absent())
"""


@pytest.mark.parametrize(
    ("argv", "extra"),
    [
        (["train", "--lab-video", "lab.cine", "--out", "models-x", "--quick"], "train"),
        (["quantize", "--models", "models/default", "--out", "int8-x"], "train"),
    ],
)
def test_a_missing_extra_is_one_line_naming_it(tmp_path: Path, argv: list[str], extra: str) -> None:
    code = WITHOUT + "from service.cli import main; sys.exit(main(sys.argv[1:]))"
    done = subprocess.run(
        [sys.executable, "-c", code, *argv],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
        env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"},
    )
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in done.stderr
    assert f"'.[{extra}]'" in lines[0] and "bash deploy/install.sh --dev" in lines[0]
