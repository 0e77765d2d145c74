"""CLI verbs: one module per family, each exposing ``register(subparsers)``; and the options several verbs share,
so that each is spelled and defaulted once."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_scene_option(parser: argparse.ArgumentParser) -> None:
    """``--scene SCENE.json``, defaulting to the embedded scene: every verb that renders, trains or analyses takes one."""
    from service import DEFAULT_SCENE

    parser.add_argument("--scene", type=Path, default=DEFAULT_SCENE, help="scene file (default: the embedded one)")
