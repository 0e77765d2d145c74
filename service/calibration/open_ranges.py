"""What a calibration left open, read back from its report: each parameter the video did not identify, with the
range its profiles leave it (``report.ridge_ranges``), so that models made for the calibrated scene can be trained
over those ranges instead of at the one value the calibration wrote (docs/calibration.md, "Training over what the
video leaves open").

Light on purpose: ``meniscope train`` reads it without loading the calibration's fit.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from service.calibration import parameters as P
from service.errors import MeniscopeError
from service.scene import Scene

#: The report's schema (``meniscope calibrate`` writes it).
SCHEMA = "meniscope.calibration/1"


def report_paths(scene_out: Path) -> tuple[Path, Path]:
    """The report JSON and PNG beside the calibrated scene: SCENE.calibration.json, SCENE.calibration.png."""
    stem = scene_out.with_suffix("")
    return stem.with_name(stem.name + ".calibration.json"), stem.with_name(stem.name + ".calibration.png")


def open_ranges(doc: dict) -> dict[str, tuple[float, float]]:
    """The report's parameters not identified whose range has a width: name (``section.key``) -> (low, high)."""
    ranges = {}
    for row in doc.get("parameters", []):
        span = row.get("range")
        if row.get("identified") is False and span is not None and span[1] > span[0]:
            ranges[row["name"]] = (float(span[0]), float(span[1]))
    return ranges


def beside(scene_path: Path, scene: Scene) -> dict[str, tuple[float, float]]:
    """The open ranges of the calibration report beside ``scene_path``, if there is one made for ``scene`` (its
    sha256); none otherwise: a scene written by hand, or edited after its calibration, has nothing to train over."""
    path = report_paths(scene_path)[0]
    if not path.exists():
        return {}
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise MeniscopeError(path, f"not a calibration report: {exc}") from None
    if not isinstance(doc, dict) or doc.get("schema") != SCHEMA:
        raise MeniscopeError(path, f"not a calibration report (schema {SCHEMA} expected)")
    if doc.get("scene_sha256") != scene.sha256:
        return {}
    return open_ranges(doc)


def drawn_over(scene: Scene, ranges: Mapping[str, tuple[float, float]], rng: np.random.Generator) -> Scene:
    """``scene`` with each parameter named in ``ranges`` that shapes the render (``section.key`` of the
    calibration's :data:`service.calibration.parameters.PARAMETERS`, a renderer's input) drawn uniformly over its
    range in the coordinate the calibration fits it in (log for the roughness and the light's angle): what its
    report leaves open. The sensor's values are left to the camera's own draws (noise presets, augmentations)."""
    params = tuple(p for p in P.PARAMETERS if p.name in ranges and p.rebuild)
    if not params:
        return scene
    lo, hi = (np.array([p.to_fit(ranges[p.name][k]) for p in params]) for k in (0, 1))
    data = scene.as_dict()
    for p, x in zip(params, rng.uniform(lo, hi)):
        data[p.path[0]][p.path[1]] = p.from_fit(float(x))
    return Scene.from_dict(data)
