"""JSON documents with a ``schema`` field (dataset and model manifests), read with one-line errors."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from service.errors import MeniscopeError


def read_schema_json(path: Path, schema: str, missing: str) -> dict[str, Any]:
    """The JSON object at ``path`` whose "schema" is ``schema``; ``missing`` says what an absent file means."""
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise MeniscopeError(path, f"missing: {missing}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise MeniscopeError(path, f"unreadable: {exc}") from None
    if not isinstance(data, dict) or data.get("schema") != schema:
        got = data.get("schema") if isinstance(data, dict) else type(data).__name__
        raise MeniscopeError(path, f"schema is {got!r}, expected {schema!r}")
    return data
