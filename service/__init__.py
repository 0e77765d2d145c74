"""meniscope runtime: physics prior, renderer, recordings, inverse models and the service.

Never imports torch or ``training``; ``training`` builds on this package.
"""

import os
from importlib.resources import files
from pathlib import Path

__all__ = ["DEFAULT_SCENE", "DEFAULT_MODELS"]

#: The embedded default scene (a copy of shared/spec/scene.example.json).
DEFAULT_SCENE: Path = Path(str(files("service") / "scenes" / "default.json"))
#: The shipped models for that scene: models/default of the checkout, or $MENISCOPE_MODELS (an installed image).
DEFAULT_MODELS: Path = Path(
    os.environ.get("MENISCOPE_MODELS") or Path(__file__).resolve().parents[1] / "models" / "default"
)
