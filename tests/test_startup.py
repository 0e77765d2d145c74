"""`meniscope --help` and `meniscope info REC` start fast (issue 14: under 0.3 s): they load no module that only
running a verb needs. Checked by what they import, not by timing (times belong in benchmarks)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

from service.recordings import open_writer

#: Modules that cost tenths of a second to import and that neither command needs.
HEAVY = ("cv2", "scipy", "onnxruntime", "numba", "pydantic", "service.analysis.fit", "service.camera_effects")


def loaded_by(argv: list[str]) -> set[str]:
    """The heavy modules imported by ``meniscope ARGV`` (run in a fresh interpreter, its output discarded)."""
    code = (
        "import sys, contextlib, io\nfrom service.cli import main\n"
        f"with contextlib.redirect_stdout(io.StringIO()):\n    try:\n        main({argv!r})\n"
        "    except SystemExit:\n        pass\n"
        f"print(' '.join(m for m in {HEAVY!r} if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60)
    return set(out.stdout.split())


def test_help_loads_no_heavy_module() -> None:
    assert loaded_by(["--help"]) == set()


def test_info_of_a_cine_loads_no_heavy_module(tmp_path: Path) -> None:
    path = tmp_path / "rec.cine"
    with open_writer(path, 8, 6, 19000.0, bit_depth=12) as writer:
        writer.write(np.zeros((3, 6, 8), np.uint16))
    assert loaded_by(["info", str(path)]) == set()
