"""The one exception type a user sees: a single line naming the file and the problem."""

from __future__ import annotations

from pathlib import Path


class MeniscopeError(Exception):
    """Bad input or an unusable resource, reported as ``<where>: <problem>`` on one line.

    The CLI prints it without a traceback and exits non-zero; services turn it into a
    readiness reason. ``where`` is usually a file path.
    """

    def __init__(self, where: str | Path | None, problem: str) -> None:
        self.where = str(where) if where is not None else None
        self.problem = " ".join(str(problem).split())  # always one line
        super().__init__(f"{self.where}: {self.problem}" if self.where else self.problem)


def require_folder_of(path: Path) -> None:
    """Refuse an output path whose folder does not exist, before any work is done for it."""
    if not Path(path).parent.is_dir():
        raise MeniscopeError(path, f"folder {Path(path).parent} does not exist")
