"""Every file a help text or the README names is in the repository, and the ZeroMQ frame document
describes the header the encoder writes."""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import numpy as np
import pytest

from service.cli import build_parser
from service.sources.base import FrameBatch, StreamFormat
from service.sources.zmq_format import encode

ROOT = Path(__file__).resolve().parents[1]
#: A repository path in plain text: a top-level folder of the checkout (or shared/, which is not one), then more;
#: not what a command is told to create (``--out models/nozzle2``).
FOLDERS = "|".join(re.escape(p.name) for p in sorted(ROOT.iterdir()) if p.is_dir() and not p.name.startswith("."))
PATH_IN_TEXT = re.compile(rf"(?<!--out )(?<![\w/.:-])((?:{FOLDERS}|\.ci|shared)/[\w./*-]*[\w*/])")
#: In Markdown: inline code that is one path, and link targets (neither absolute nor a URL).
CODE_SPAN = re.compile(r"`([^`\s]+/[^`\s]*)`")
LINK = re.compile(r"\]\(([^)\s#]+)")


def help_texts(parser: argparse.ArgumentParser, name: str = "meniscope") -> dict[str, str]:
    """Each command's and sub-command's --help text, by command line."""
    texts = {name: parser.format_help()}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for verb, sub in action.choices.items():
                texts |= help_texts(sub, f"{name} {verb}")
    return texts


def missing(names: set[str], base: Path = ROOT) -> list[str]:
    """The names (relative paths, globs allowed) with no file or folder behind them under ``base``."""
    return sorted(n for n in names if not any(base.glob(n.rstrip("/"))))


def test_paths_in_help_texts_exist(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("COLUMNS", "10000")  # no line wrapping (argparse breaks lines at hyphens)
    texts = help_texts(build_parser())
    assert len(texts) > 15  # every verb and the bench sub-commands
    named = {
        (command, path) for command, text in texts.items() for path in PATH_IN_TEXT.findall(" ".join(text.split()))
    }
    assert ("meniscope publish-frames", "docs/zmq-frames.md") in named
    assert [(c, p) for c, p in sorted(named) if missing({p})] == []


def test_paths_in_the_readme_exist() -> None:
    text = (ROOT / "README.md").read_text()
    named = {
        p
        for p in CODE_SPAN.findall(text) + LINK.findall(text)
        if not p.startswith(("/", "~", "-", "http")) and "://" not in p and "=" not in p
    }
    named |= set(PATH_IN_TEXT.findall(text))
    assert {"docs/service.md", "deploy/install.sh"} <= named
    assert missing(named) == []


def test_the_frame_format_document_names_every_header_field() -> None:
    batch = FrameBatch(np.zeros((2, 4, 6), np.uint16), np.arange(5, 7), np.array([0.0, 0.001]))
    header = encode(batch, StreamFormat(6, 4, np.dtype(np.uint16), 12, 1000.0), 0)[0]
    irregular = encode(
        FrameBatch(batch.pixels, batch.indices, np.array([0.0, 0.5])),
        StreamFormat(6, 4, np.dtype(np.uint16), 12, 1000.0),
        1,
    )[0]
    fields = set(json.loads(bytes(header))) | set(json.loads(bytes(irregular)))
    document = (ROOT / "docs" / "zmq-frames.md").read_text()
    assert fields <= set(re.findall(r"^\| `(\w+)` \|", document, re.MULTILINE)) and '"end": true' in document
