"""Fixtures shared by every test module: the example scene, the demo recording, the ../shared folder and an int8
copy of the shipped models."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import settings

from service import DEFAULT_MODELS, DEFAULT_SCENE
from service.pipeline.demo import demo_recording
from service.scene import Scene
from tests.servicekit import meniscope

# The same examples on every run (CI must not fail by chance); `--hypothesis-profile explore` draws new ones.
settings.register_profile("ci", derandomize=True, print_blob=True)
settings.register_profile("explore", print_blob=True)
settings.load_profile("ci")

#: ../shared beside the checkout (specs and real Phantom recordings); may be absent.
SHARED = Path(__file__).resolve().parents[1].parent / "shared"


@pytest.fixture(scope="session")
def scene() -> Scene:
    """The embedded default scene (shared/spec/scene.example.json)."""
    return Scene.load(DEFAULT_SCENE)


@pytest.fixture(scope="module")
def demo_cine(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The demo recording as an 8-bit .cine (its ground truth beside it), made afresh for each module."""
    return demo_recording(tmp_path_factory.mktemp("data"))


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    """The shared folder, or a skip saying where it was looked for."""
    if not SHARED.is_dir():
        pytest.skip(
            f"../shared not found at {SHARED}: the shared specs and recordings are not checked out beside the repo"
        )
    return SHARED


@pytest.fixture(scope="session")
def int8(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The shipped models, quantised (static, `meniscope quantize`) from 128 calibration renders and compared on 128
    others: made once, for the quantisation's own tests and the tradeoff's int8 rows."""
    out = tmp_path_factory.mktemp("quantize") / "int8"
    done = meniscope("quantize", "--models", DEFAULT_MODELS, "--out", out, "--calibration", "128", "--parity", "128")
    assert done.returncode == 0, done.stderr
    assert "network int8 (static)" in done.stdout and "direct int8 (static)" in done.stdout
    return out
