"""meniscope runtime: physics prior, renderer, recordings, inverse models and the service.

Never imports torch or ``training``; ``training`` builds on this package.
"""
from importlib.resources import files
from pathlib import Path

__all__ = ["DEFAULT_MODELS", "DEFAULT_SCENE"]

#: The embedded default scene (a copy of shared/spec/scene.example.json).
DEFAULT_SCENE: Path = Path(str(files("service") / "scenes" / "default.json"))
#: The shipped inverse models for the embedded scene (``models/default`` of the checkout; editable installs).
DEFAULT_MODELS: Path = Path(__file__).resolve().parents[1] / "models" / "default"
