"""The one results writer of every benchmark: JSON (plain numbers, no NaN) and a Markdown table beside it."""
from __future__ import annotations

import json
from pathlib import Path

from service.errors import MeniscopeError


def write_results(out: Path, results: dict, table: str) -> tuple[Path, Path]:
    """``results`` to ``out`` (.json) and ``table`` to the .md beside it; the table is printed too."""
    try:
        text = json.dumps(results, indent=1, allow_nan=False) + "\n"
    except ValueError as exc:
        raise MeniscopeError(out, f"a figure is not a finite number: {exc}") from None
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    markdown = out.with_suffix(".md")
    markdown.write_text(table)
    print(table)
    return out, markdown
