"""The one results writer of every benchmark: JSON (plain numbers; NaN and infinities become null) and a Markdown
table beside it."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any


def write_results(out: Path, results: dict, table: str) -> tuple[Path, Path]:
    """``results`` to ``out`` (.json) and ``table`` to the .md beside it; the table is printed too."""
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(_finite(results), indent=1, allow_nan=False) + "\n")
    markdown = out.with_suffix(".md")
    markdown.write_text(table)
    print(table)
    return out, markdown


def _finite(value: Any) -> Any:
    """``value`` with every float that is not finite (a figure that could not be measured) replaced by None."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    return value
