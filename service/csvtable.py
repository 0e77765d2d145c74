"""Numeric CSV tables with a header row (COEFFS.csv, SERIES.csv of shared/spec/cli.md), read with one-line errors."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from service.errors import MeniscopeError


def read_columns(path: str | Path, names: tuple[str, ...], allow_empty: bool = False) -> np.ndarray:
    """Columns ``names`` of the CSV at ``path`` as float64 (rows, len(names)).

    Other columns are ignored. Empty cells are NaN when ``allow_empty`` (missing samples; in a
    one-column file they are blank lines, so blank lines count too, except at the end), skipped
    blank lines and an error otherwise; so is any cell that is not a finite number, naming file, line and column.
    """
    path = Path(path)
    try:
        with path.open(newline="") as fh:
            reader = csv.reader(fh)
            header = [h.strip() for h in next(reader, [])]
            missing = [n for n in names if n not in header]
            if missing:
                raise MeniscopeError(
                    path,
                    f"needs a header row with columns {', '.join(names)}; "
                    f"missing {', '.join(missing)} (header: {','.join(header) or 'none'})",
                )
            index = [header.index(n) for n in names]
            rows, blank = [], 0
            for line, row in enumerate(reader, start=2):
                if not any(cell.strip() for cell in row):
                    blank += 1  # a missing sample when empty cells are allowed, unless only blanks follow
                    continue
                rows.extend([[math.nan] * len(names)] * (blank if allow_empty else 0))
                blank = 0
                rows.append(
                    [
                        _cell(path, line, name, row[i] if i < len(row) else "", allow_empty)
                        for name, i in zip(names, index)
                    ]
                )
    except FileNotFoundError:
        raise MeniscopeError(path, "no such file") from None
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise MeniscopeError(path, f"cannot read as CSV: {exc}") from None
    return np.array(rows, dtype=np.float64).reshape(len(rows), len(names))


def _cell(path: Path, line: int, name: str, text: str, allow_empty: bool) -> float:
    text = text.strip()
    if not text:
        if allow_empty:
            return math.nan
        raise MeniscopeError(path, f"line {line}: empty cell in column {name}")
    try:
        value = float(text)
    except ValueError:
        raise MeniscopeError(path, f"line {line}: column {name} is not a number: {text!r}") from None
    if not math.isfinite(value):
        raise MeniscopeError(path, f"line {line}: column {name} is not finite: {text!r}")
    return value


def write_columns(path: str | Path, names: tuple[str, ...], columns: list[np.ndarray], what: str) -> Path:
    """A CSV with header ``names`` and one row per element of the equal-length ``columns``.

    Integer columns are written as integers, floats with 9 significant digits, NaN/Inf as empty
    cells (read back as missing by :func:`read_columns` with ``allow_empty``). Cells are formatted from the
    columns' Python values, not numpy's string arrays, which cost ``meniscope analyze`` more than twice the time
    for the same bytes (docs/benchmarks.md).
    """
    path = Path(path)
    cells = [_cells(np.asarray(col)) for col in columns]
    try:
        with path.open("w", newline="") as fh:
            writer = csv.writer(fh)
            writer.writerow(names)
            writer.writerows(zip(*cells))
    except OSError as exc:
        raise MeniscopeError(path, f"cannot write the {what}: {exc.strerror or exc}") from None
    return path


def _cells(column: np.ndarray) -> list[str]:
    """One column's cells: integers as such, floats as ``%.9g``, a non-finite float as an empty cell."""
    if column.dtype.kind in "iu":
        return list(map(str, column.tolist()))
    finite = math.isfinite
    return [f"{value:.9g}" if finite(value) else "" for value in column.astype(np.float64).tolist()]
