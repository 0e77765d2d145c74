"""The scene file (shared/spec/scene.md) as a validated pydantic model.

One calibrated camera set-up: nozzle geometry, fluid material, artifact spheres,
pinhole camera and sun light. Everything that renders, trains or analyses takes one.
Units: millimetres, seconds, degrees in the file (radians inside code).
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Mapping
from functools import cached_property
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from service.errors import MeniscopeError

PositiveMm = Annotated[float, Field(gt=0, allow_inf_nan=False)]
Fraction = Annotated[float, Field(ge=0, le=1, allow_inf_nan=False)]
Degrees = Annotated[float, Field(allow_inf_nan=False)]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Nozzle(_Strict):
    """Flat bottom face at z = 0 pierced by a bore of radius ``radius_mm`` up to ``bore_depth_mm``."""

    radius_mm: PositiveMm
    outer_radius_mm: PositiveMm
    bore_depth_mm: PositiveMm
    albedo: Fraction

    @model_validator(mode="after")
    def _outer_beyond_bore(self) -> Nozzle:
        if self.outer_radius_mm <= self.radius_mm:
            raise ValueError(f"outer_radius_mm ({self.outer_radius_mm}) must exceed radius_mm ({self.radius_mm})")
        return self


class Fluid(_Strict):
    """Specular metal, GGX microfacet; ``roughness`` is the GGX width alpha."""

    roughness: Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)]
    reflectance: Fraction


class Sphere(_Strict):
    x: float = Field(allow_inf_nan=False)
    y: float = Field(allow_inf_nan=False)
    z: float = Field(allow_inf_nan=False)
    radius: PositiveMm


class SphereMaterial(_Strict):
    """The artifact spheres' own GGX metal (machining defects are rougher than the fluid): alpha and reflectance."""

    roughness: Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)]
    reflectance: Fraction


class Artifacts(_Strict):
    """Small specular spheres on the nozzle face: drawn from ``seed`` or listed in ``spheres``.

    ``material``: their own GGX metal; absent (older files), they share the fluid's.
    """

    count: Annotated[int, Field(ge=0, le=1000)] = 0
    radius_mm: tuple[PositiveMm, PositiveMm] = (0.006, 0.018)
    ring_mm: tuple[PositiveMm, PositiveMm] = (0.26, 0.33)
    seed: int = 0
    spheres: list[Sphere] | None = None
    material: SphereMaterial | None = None

    @field_validator("radius_mm", "ring_mm")
    @classmethod
    def _ordered(cls, v: tuple[float, float]) -> tuple[float, float]:
        if v[0] > v[1]:
            raise ValueError(f"range must be [low, high], got {list(v)}")
        return v


class Camera(_Strict):
    """Pinhole camera looking at the origin; ``fov_deg`` spans ``width_px``; ROI inside the recording."""

    azimuth_deg: Degrees
    # open interval: looking straight along the axis leaves "image up" undefined
    elevation_deg: Annotated[float, Field(gt=-90, lt=90, allow_inf_nan=False)]
    distance_mm: PositiveMm
    fov_deg: Annotated[float, Field(gt=0, lt=90, allow_inf_nan=False)]
    width_px: Annotated[int, Field(ge=1, le=8192)]
    height_px: Annotated[int, Field(ge=1, le=8192)]
    roi: tuple[Annotated[int, Field(ge=0)], Annotated[int, Field(ge=0)]] = (0, 0)
    fps: Annotated[float, Field(gt=0, allow_inf_nan=False)]
    exposure: Annotated[float, Field(gt=0, allow_inf_nan=False)] = 1.0


class Sensor(_Strict):
    """The camera's response as calibrated (service.camera_effects): black level (fraction of full scale),
    Gaussian PSF sigma (px), full well (electrons at full scale, 0: no shot noise) and read noise (electrons)."""

    offset: Annotated[float, Field(ge=-1, le=1, allow_inf_nan=False)] = 0.0
    blur_sigma_px: Annotated[float, Field(ge=0, le=10, allow_inf_nan=False)] = 0.0
    full_well_e: Annotated[float, Field(ge=0, le=1e9, allow_inf_nan=False)] = 0.0
    read_noise_e: Annotated[float, Field(ge=0, le=1e6, allow_inf_nan=False)] = 0.0


class Light(_Strict):
    """Directional sun: direction towards the light, angular diameter, radiance scale."""

    azimuth_deg: Degrees
    elevation_deg: Annotated[float, Field(ge=-90, le=90, allow_inf_nan=False)]
    angle_deg: Annotated[float, Field(ge=0, lt=180, allow_inf_nan=False)]
    strength: Annotated[float, Field(ge=0, allow_inf_nan=False)]


def direction(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """Unit vector for (azimuth, elevation) in the scene convention (scene.md, "Camera")."""
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    return np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])


class Scene(_Strict):
    """A validated scene file; build with :meth:`load` or :meth:`from_dict`."""

    nozzle: Nozzle
    fluid: Fluid
    artifacts: Artifacts = Artifacts()
    camera: Camera
    light: Light
    sensor: Sensor | None = None

    @model_validator(mode="after")
    def _artifacts_on_face(self) -> Scene:
        lo, hi = self.artifacts.ring_mm
        if (
            self.artifacts.spheres is None
            and self.artifacts.count
            and (lo < self.nozzle.radius_mm or hi > self.nozzle.outer_radius_mm)
        ):
            raise ValueError(
                f"artifacts.ring_mm {[lo, hi]} must lie on the nozzle face "
                f"[{self.nozzle.radius_mm}, {self.nozzle.outer_radius_mm}]"
            )
        return self

    # ---- construction -------------------------------------------------------------
    def model_copy(self, *, update: Mapping[str, Any] | None = None, deep: bool = False) -> Scene:
        """A copy with ``update`` applied and validated afresh.

        pydantic's own copy would carry over the cached :attr:`sha256` and :attr:`spheres` of the
        original, so a changed scene would still claim the old scene's hash (and models)."""
        data = {name: getattr(self, name) for name in type(self).model_fields} | dict(update or {})
        return type(self).model_validate(data)

    @classmethod
    def from_dict(cls, data: object, where: str | Path = "scene") -> Scene:
        """Validate a parsed scene; errors become one :class:`MeniscopeError` line."""
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            problems = []
            for err in exc.errors():
                loc = ".".join(str(p) for p in err["loc"]) or "scene"
                msg = err["msg"].removeprefix("Value error, ")
                got = err.get("input")
                shown = "" if isinstance(got, (dict, list)) or got is None else f", got {got!r}"
                problems.append(f"{loc}: {msg}{shown}")
            raise MeniscopeError(where, "invalid scene: " + "; ".join(problems)) from None

    @classmethod
    def load(cls, path: str | Path) -> Scene:
        """Read and validate a scene JSON file."""
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except FileNotFoundError:
            raise MeniscopeError(path, "scene file not found") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise MeniscopeError(path, f"cannot read scene file: {exc}") from None
        except json.JSONDecodeError as exc:
            raise MeniscopeError(path, f"not valid JSON: {exc}") from None
        return cls.from_dict(data, where=path)

    # ---- derived quantities -----------------------------------------------------------
    def to_json(self) -> str:
        """Canonical JSON (sorted keys, no whitespace): what :attr:`sha256` hashes.

        Optional blocks added after the first format (``artifacts.material``, ``sensor``) are left out
        when absent, so an older file keeps its hash and the models tied to it."""
        return json.dumps(self.as_dict(), sort_keys=True, separators=(",", ":"))

    def as_dict(self) -> dict:
        """The scene as JSON-ready data, without the absent optional blocks (see :meth:`to_json`)."""
        data = self.model_dump(mode="json")
        if data["artifacts"]["material"] is None:
            del data["artifacts"]["material"]
        if data["sensor"] is None:
            del data["sensor"]
        return data

    @property
    def sphere_material(self) -> SphereMaterial:
        """The artifact spheres' GGX material: their own, or the fluid's in older files."""
        fluid = self.fluid
        return self.artifacts.material or SphereMaterial(roughness=fluid.roughness, reflectance=fluid.reflectance)

    @cached_property
    def sha256(self) -> str:
        """Content hash that models and recordings carry to prove which scene they belong to."""
        return hashlib.sha256(self.to_json().encode()).hexdigest()

    @cached_property
    def spheres(self) -> np.ndarray:
        """Artifact spheres as an array of shape (K, 4): x, y, z, radius (mm)."""
        art = self.artifacts
        if art.spheres is not None:
            return np.array([[s.x, s.y, s.z, s.radius] for s in art.spheres], dtype=np.float64).reshape(-1, 4)
        rng = np.random.default_rng(art.seed)
        radius = rng.uniform(*art.radius_mm, size=art.count)
        ring = rng.uniform(*art.ring_mm, size=art.count)
        azimuth = rng.uniform(0.0, 2 * np.pi, size=art.count)
        return np.stack([ring * np.cos(azimuth), ring * np.sin(azimuth), np.zeros(art.count), radius], axis=1)

    def check_roi(self, width: int, height: int, where: str | Path) -> None:
        """Raise unless the scene's ROI fits inside a ``width`` x ``height`` recording."""
        x, y = self.camera.roi
        if x + self.camera.width_px > width or y + self.camera.height_px > height:
            raise MeniscopeError(
                where,
                f"scene ROI {self.camera.width_px}x{self.camera.height_px} at ({x}, {y}) "
                f"lies outside the {width}x{height} frame",
            )
