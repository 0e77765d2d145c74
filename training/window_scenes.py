"""Scenes randomised around a scene, for window-model training windows that a calibrated scene's errors resemble.

A recording of the real set-up (or Blender's) is analysed with the scene's network and pipeline, but it was made by
a world that differs from the scene within its calibration's uncertainty (docs/calibration.md): the fluid's GGX
alpha and reflectance, the light's direction and angle, the exposure, the camera's blur, black level and noise, the
nozzle's defects. Windows rendered from such perturbed scenes and replayed through the unperturbed scene's network
(:func:`training.window.cached_examples` with the scene itself) show the window model those errors.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from service.calibration.open_ranges import drawn_over
from service.camera_effects import CameraEffects
from service.scene import Scene
from training.window import Vary, render_mix


@dataclass(frozen=True)
class Spread:
    """How far a randomised scene strays from its scene: multiplicative ``*_factor`` (drawn log-uniformly in
    [1/f, f]) and additive ``*_deg``, ``*_px``, ``reflectance`` and ``black_level`` (uniform in [-x, x]).

    The defaults span what docs/calibration.md's fits on Blender Cycles recordings of known scenes left uncertain
    (fluid, light, blur, reflectance), the camera's own exposure and black level, and full wells between the noise
    presets'; the light's direction is kept narrower than that, since a wider one made the windows' errors larger
    than Blender's and the model trained on them worse (docs/window_model.md, "Windows from scenes randomised around
    the scene", with the figures)."""

    roughness_factor: float = 1.5
    reflectance: float = 0.1
    light_deg: float = 0.75
    angle_factor: float = 1.35
    exposure_factor: float = 1.25
    blur_px: float = 0.3
    black_level: float = 0.01
    full_well_factor: float = 2.0


SPREAD = Spread()


def _factor(rng: np.random.Generator, f: float) -> float:
    """A factor log-uniform in [1/f, f]."""
    return math.exp(rng.uniform(-math.log(f), math.log(f)))


def randomised(scene: Scene, rng: np.random.Generator, spread: Spread = SPREAD) -> Scene:
    """``scene`` with its fluid, light, exposure and defects drawn around its own (clipped to valid values); the
    geometry and the camera's pose stay, as a calibrated scene pins them down."""
    fluid, light, camera = scene.fluid, scene.light, scene.camera
    return scene.model_copy(
        update={
            "fluid": fluid.model_copy(
                update={
                    "roughness": float(np.clip(fluid.roughness * _factor(rng, spread.roughness_factor), 1e-4, 1.0)),
                    "reflectance": float(np.clip(fluid.reflectance + rng.uniform(-1, 1) * spread.reflectance, 0, 1)),
                }
            ),
            "light": light.model_copy(
                update={
                    "azimuth_deg": light.azimuth_deg + rng.uniform(-1, 1) * spread.light_deg,
                    "elevation_deg": float(
                        np.clip(light.elevation_deg + rng.uniform(-1, 1) * spread.light_deg, -90, 90)
                    ),
                    "angle_deg": float(np.clip(light.angle_deg * _factor(rng, spread.angle_factor), 0, 179)),
                }
            ),
            "camera": camera.model_copy(update={"exposure": camera.exposure * _factor(rng, spread.exposure_factor)}),
            "artifacts": scene.artifacts.model_copy(update={"seed": int(rng.integers(2**31))}),
        }
    )


def randomised_effects(effects: CameraEffects, rng: np.random.Generator, spread: Spread = SPREAD) -> CameraEffects:
    """``effects`` (a noise preset's camera) with its blur, black level and full well drawn around its own."""
    return effects.model_copy(
        update={
            "blur_sigma_px": float(np.clip(effects.blur_sigma_px + rng.uniform(-1, 1) * spread.blur_px, 0, 10)),
            "offset": float(np.clip(effects.offset + rng.uniform(-1, 1) * spread.black_level, -1, 1)),
            "full_well_e": effects.full_well_e * _factor(rng, spread.full_well_factor),
        }
    )


def vary(scene: Scene, effects: CameraEffects, rng: np.random.Generator) -> tuple[Scene, CameraEffects]:
    """One recording's world: :func:`randomised` scene and :func:`randomised_effects` camera."""
    return randomised(scene, rng), randomised_effects(effects, rng)


def over_ranges(ranges: Mapping[str, tuple[float, float]]) -> Vary:
    """A recording's world: the scene with ``ranges`` drawn (:func:`drawn_over`), the camera its preset's."""

    def vary_over(scene: Scene, effects: CameraEffects, rng: np.random.Generator) -> tuple[Scene, CameraEffects]:
        return drawn_over(scene, ranges, rng), effects

    return vary_over


def around(ranges: Mapping[str, tuple[float, float]]) -> Vary:
    """A recording's world randomised (:func:`vary`) around the scene with ``ranges`` drawn first (none: :func:`vary`)."""
    if not ranges:
        return vary

    def vary_around(scene: Scene, effects: CameraEffects, rng: np.random.Generator) -> tuple[Scene, CameraEffects]:
        return vary(drawn_over(scene, ranges, rng), effects, rng)

    return vary_around


#: Seeds of successive chunks of :func:`render_randomised` lie this far apart (room for :func:`render_mix`'s offsets).
CHUNK_SEEDS = 1000


def render_randomised(
    data: Path, scene: Scene, windows: int, seed: int, chunk: int = 40, world: Vary = vary
) -> list[Path]:
    """``windows`` training windows per noise preset as :func:`training.window.render_mix` draws them, in chunks of
    ``chunk`` per preset whose every recording has a scene and camera of its own (``world``: by default
    :func:`vary`; it is written beside the recording). Each recording sets up its own renderer (~3 s of CPU), so
    chunks of a few dozen windows keep that below the rendering's own cost."""
    paths: list[Path] = []
    for c, first in enumerate(range(0, windows, chunk)):
        paths += render_mix(data, scene, min(chunk, windows - first), seed + c * CHUNK_SEEDS, world)
    return paths
