"""The code is ruff-clean and ruff-formatted (rules and line length in pyproject.toml), so a change that is not
fails the test command like any other defect."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def ruff(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "ruff", *args], cwd=ROOT, capture_output=True, text=True, timeout=120)


def test_ruff_finds_nothing_to_report() -> None:
    done = ruff("check", ".")
    assert done.returncode == 0, done.stdout + done.stderr


def test_every_file_is_formatted() -> None:
    done = ruff("format", "--check", ".")
    assert done.returncode == 0, done.stdout + done.stderr


def test_no_text_file_holds_a_merge_conflict_marker() -> None:
    """A merge left unresolved in the docs or the code (it happened to docs/architecture.md once) fails here."""
    suffixes = {".py", ".md", ".toml", ".yml", ".yaml", ".json", ".sh", ".txt", ".cfg"}
    tracked = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    marked = [
        f"{path}:{n}"
        for path in (
            ROOT / name for name in tracked.splitlines() if Path(name).suffix in suffixes and (ROOT / name).is_file()
        )
        for n, line in enumerate(path.read_text(errors="replace").splitlines(), 1)
        if line.startswith(("<<<<<<< ", ">>>>>>> ")) or line == "======="
    ]
    assert not marked, marked
