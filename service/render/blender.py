"""Reference renderer: the scene of shared/spec/scene.md through Blender Cycles, as Price et al. (2022) did.

Slow and noisy next to ``service.render.Renderer``; it exists to check that renderer
(``service.render.agreement``, ``meniscope bench render``). One ``blender -b`` process
renders a whole batch: the scene is built once and only the fluid mesh changes per frame.

Conventions (the contract's, mapped onto Cycles):

- camera: perspective, ``sensor_fit`` horizontal, angle = ``fov_deg``, no shift, placed
  at C = distance * direction(az, el) with image up = world +z projected;
- sun: Cycles sun lamp, ``angle`` = ``angle_deg`` (angular diameter), ``strength`` = the
  scene's strength (Cycles: irradiance in W/m^2 on a surface facing the sun, so a
  Lambert face of albedo rho at incidence i has radiance rho * strength * cos(i) / pi);
- world black; nozzle a watertight tube (bottom annulus, bore wall, outer wall, top),
  Diffuse BSDF with roughness 0 (Lambert) and colour = albedo;
- fluid: polar mesh of ``rings`` x ``segments`` over the bore at z = -D(r) (Eq. 1) with
  normals set from the analytic slope dD/dr; Glossy BSDF, GGX, colour = reflectance (no
  Fresnel term), Blender roughness = sqrt(alpha) because Cycles squares it; artifact
  spheres: UV spheres, 48 x 24, smooth, their own Glossy material (the fluid's when the scene gives none);
- film: ``samples`` per pixel, no adaptive sampling, no denoising, no clamping, no
  glossy filter, caustics on, Cycles default bounce limits (12 total, 4 diffuse,
  4 glossy), box pixel filter 1 px wide, fixed seed; linear radiance read from a
  32-bit OpenEXR, so the view transform never touches it.

Output as ours: float32 (N, H, W), pixel = clip(exposure * radiance, 0, 1).
"""

from __future__ import annotations

import collections
import json
import os
import shutil
import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike
from tqdm import tqdm

from service.errors import MeniscopeError
from service.physics import coefficient_array, displacement, slope
from service.render.camera import camera_frame
from service.scene import Scene, direction

#: The script Blender runs (standard library + bpy only; see its docstring).
SCRIPT = Path(__file__).with_name("blender_scene.py")

#: Box pixel filter width in pixels: each sample lands uniformly inside its pixel.
FILTER_WIDTH_PX = 1.0


@dataclass(frozen=True)
class BlenderTiming:
    """Wall-clock cost of one batch, measured from this side of the pipe.

    ``startup_s``: launching Blender and building the scene, up to the first render.
    ``frame_s``: shape (N,), seconds per frame (mesh update, render, read-back).
    """

    startup_s: float
    frame_s: np.ndarray


def fluid_profiles(coeffs: np.ndarray, radius: float, rings: int) -> np.ndarray:
    """Eq. 1 sampled on the mesh rings: shape (N, 2, rings + 1), float32.

    ``[:, 0]`` is the height z = -D(r_k) (mm), ``[:, 1]`` the slope dD/dr at
    r_k = radius * k / rings; ``coeffs`` is shape (N, 4): d, p, a, b.
    """
    r = radius * np.arange(rings + 1) / rings  # (K,)
    d, p, a, b = (coeffs[:, i, None] for i in range(4))  # (N, 1) each
    z = -displacement(r, d, p, a, b, radius)
    s = slope(r, p, a, b, radius)
    return np.stack([z, s], axis=1).astype(np.float32)


class BlenderRenderer:
    """Renders coefficient batches with Blender Cycles; same call and output as ``Renderer``.

    ``samples`` per pixel; ``blender`` the executable (name on PATH or path); the fluid
    mesh has ``rings`` x ``segments`` quads (the default keeps its chordal error below
    1e-4 mm, a hundredth of a pixel in the example scene). ``last_timing`` holds the
    :class:`BlenderTiming` of the latest :meth:`render`.
    """

    def __init__(
        self,
        scene: Scene,
        samples: int = 32,
        blender: str = "blender",
        rings: int = 64,
        segments: int = 256,
        seed: int = 0,
        progress: bool = True,
    ) -> None:
        if samples < 1 or rings < 1 or segments < 3:
            raise MeniscopeError(
                blender, f"need samples >= 1, rings >= 1, segments >= 3, got {samples}, {rings}, {segments}"
            )
        self.scene, self.samples, self.blender = scene, samples, blender
        self.rings, self.segments, self.seed, self.progress = rings, segments, seed, progress
        self.last_timing: BlenderTiming | None = None

    def job(self, frames: int, profiles: Path, output: Path) -> dict:
        """The JOB.json that ``blender_scene.py`` reads (its docstring lists the keys)."""
        s = self.scene
        location, forward, up = camera_frame(s)
        return {
            "width": s.camera.width_px,
            "height": s.camera.height_px,
            "samples": self.samples,
            "seed": self.seed,
            "filter_width_px": FILTER_WIDTH_PX,
            "camera": {
                "location": location.tolist(),
                "forward": forward.tolist(),
                "up": up.tolist(),
                "fov_rad": float(np.radians(s.camera.fov_deg)),
            },
            "sun": {
                "direction": direction(s.light.azimuth_deg, s.light.elevation_deg).tolist(),
                "angle_rad": float(np.radians(s.light.angle_deg)),
                "strength": s.light.strength,
            },
            "nozzle": {
                "radius": s.nozzle.radius_mm,
                "outer_radius": s.nozzle.outer_radius_mm,
                "bore_depth": s.nozzle.bore_depth_mm,
                "albedo": s.nozzle.albedo,
            },
            "fluid": {"roughness": float(np.sqrt(s.fluid.roughness)), "reflectance": s.fluid.reflectance},
            "spheres": s.spheres.tolist(),
            "sphere_material": {
                "roughness": float(np.sqrt(s.sphere_material.roughness)),
                "reflectance": s.sphere_material.reflectance,
            },
            "mesh": {"rings": self.rings, "segments": self.segments},
            "frames": frames,
            "profiles": str(profiles),
            "output": str(output),
        }

    def render(self, coeffs: ArrayLike) -> np.ndarray:
        """Frames for coefficients of shape (N, 4) (d, p, a, b): float32 (N, H, W) in [0, 1]."""
        coeffs = coefficient_array(coeffs)
        cam = self.scene.camera
        n, h, w = coeffs.shape[0], cam.height_px, cam.width_px
        if n == 0:
            self.last_timing = BlenderTiming(0.0, np.zeros(0))
            return np.zeros((0, h, w), np.float32)
        executable = shutil.which(self.blender)
        if executable is None:
            raise MeniscopeError(self.blender, "Blender not found (Debian: apt install blender), or pass its path")
        with tempfile.TemporaryDirectory(prefix="meniscope-blender-") as tmp:
            tmp = Path(tmp)
            fluid_profiles(coeffs, self.scene.nozzle.radius_mm, self.rings).tofile(tmp / "profiles.f32")
            job = self.job(n, tmp / "profiles.f32", tmp / "radiance.f32")
            (tmp / "job.json").write_text(json.dumps(job))
            self.last_timing = self._run(executable, tmp / "job.json", n)
            radiance = np.fromfile(tmp / "radiance.f32", dtype=np.float32)
        if radiance.size != n * h * w:
            raise MeniscopeError(executable, f"Blender wrote {radiance.size} pixels, expected {n * h * w}")
        frames = radiance.reshape(n, h, w)[:, ::-1, :]  # Blender's rows run bottom-up
        return np.clip(cam.exposure * frames, 0.0, 1.0).astype(np.float32)

    def _run(self, executable: str, job: Path, frames: int) -> BlenderTiming:
        """One Blender process for the batch; progress from its MENISCOPE lines, errors from its tail."""
        cmd = [
            executable,
            "-b",
            "--factory-startup",
            "-noaudio",
            "--python-exit-code",
            "3",
            "--python",
            str(SCRIPT),
            "--",
            str(job),
        ]
        env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
        tail: collections.deque[str] = collections.deque(maxlen=30)
        marks: list[float] = []
        start = time.perf_counter()
        with (
            tqdm(total=frames, desc="blender cycles", unit="frame", disable=not self.progress) as bar,
            subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env) as proc,
        ):
            assert proc.stdout is not None
            for line in proc.stdout:
                if line.startswith("MENISCOPE "):
                    marks.append(time.perf_counter())
                    bar.update(1 if line.split()[1] == "frame" else 0)
                elif line.strip():
                    tail.append(line.strip())
            rc = proc.wait()
        if rc != 0 or len(marks) != frames + 1:
            errors = [t for t in tail if "Error" in t or "error" in t] or list(tail)[-3:] or ["no output"]
            raise MeniscopeError(
                executable,
                f"Blender failed (exit {rc}) after {max(len(marks) - 1, 0)} of {frames} frames: {' | '.join(errors[-3:])}",
            )
        times = np.array([start] + marks)
        return BlenderTiming(startup_s=float(times[1] - times[0]), frame_s=np.diff(times[1:]))
