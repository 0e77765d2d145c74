"""Calibration against a known answer: a synthetic recording's truth sidecar (``simulate``) scores what was recovered."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from service.calibration.artifacts import glint_positions
from service.scene import Scene, direction
from service.simulate import truth_path


def load_truth(recording: Path) -> dict[str, Any] | None:
    """The recording's truth sidecar, or None (a lab recording has none)."""
    path = truth_path(recording)
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def score(found: Scene, truth: dict[str, Any]) -> dict[str, Any]:
    """Errors of a calibrated scene against a recording's truth (the scene and camera effects it was made with)."""
    true = Scene.from_dict(truth["scene"])
    fx = truth["camera_effects"]
    sensor = found.sensor
    between = float(
        np.degrees(
            np.arccos(
                np.clip(
                    direction(found.light.azimuth_deg, found.light.elevation_deg)
                    @ direction(true.light.azimuth_deg, true.light.elevation_deg),
                    -1.0,
                    1.0,
                )
            )
        )
    )
    out: dict[str, Any] = {
        "fluid.roughness": {
            "true": true.fluid.roughness,
            "found": found.fluid.roughness,
            "relative_error": found.fluid.roughness / true.fluid.roughness - 1,
        },
        "fluid.reflectance": {"true": true.fluid.reflectance, "found": found.fluid.reflectance},
        "light.direction_error_deg": between,
        "light.angle_deg": {
            "true": true.light.angle_deg,
            "found": found.light.angle_deg,
            "relative_error": found.light.angle_deg / max(true.light.angle_deg, 1e-9) - 1,
        },
        "camera.exposure": {
            "true": true.camera.exposure * true.light.strength,
            "found": found.camera.exposure * found.light.strength,
        },
        "camera.elevation_error_deg": found.camera.elevation_deg - true.camera.elevation_deg,
        "roi": {
            "true": list(true.camera.roi),
            "found": list(found.camera.roi),
            "error_px": float(math.dist(true.camera.roi, found.camera.roi)),
        },
        "sensor": {
            "true": {k: fx[k] for k in ("offset", "blur_sigma_px", "full_well_e")},
            "found": None if sensor is None else sensor.model_dump(),
        },
    }
    out["defects"] = _defects(found, true)
    return out


def _defects(found: Scene, true: Scene) -> dict[str, Any]:
    """Each true defect's glint (frame px) against the nearest recovered one, and their material."""
    t = glint_positions(true, true.spheres) + np.array(true.camera.roi)
    f = glint_positions(found, found.spheres) + np.array(found.camera.roi) if len(found.spheres) else np.zeros((0, 2))
    material = {"true": true.sphere_material.model_dump(), "found": found.sphere_material.model_dump()}
    if not len(f) or not len(t):
        return {"true": len(t), "found": len(f), "within_1px": 0, "nearest_px": [], "material": material}
    dist = np.linalg.norm(t[:, None, :] - f[None, :, :], axis=-1)
    nearest = dist.min(axis=1)
    return {
        "material": material,
        "true": len(t),
        "found": len(f),
        "within_1px": int((nearest <= 1.0).sum()),
        "nearest_px": [round(float(v), 2) for v in np.sort(nearest)],
        "found_nearest_true_px": [round(float(v), 2) for v in np.sort(dist.min(axis=0))],
    }
