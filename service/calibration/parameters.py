"""The scene parameters a calibration fits: where each lives in the scene file, its bounds, its scale.

A parameter is fitted in a coordinate where a step means about the same everywhere (log10 for the
roughness, the light's angle and the exposure). Parameters the video cannot tell apart from others
are not fitted but named with the reason (:data:`UNIDENTIFIABLE`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from service.scene import Scene


@dataclass(frozen=True)
class Parameter:
    """One fitted scene value: ``path`` into the scene's JSON, bounds in the file's units, fitted as its log10, its
    square or itself; ``span``: the half-width around the guess searched for unbounded angles (degrees), else None."""

    path: tuple[str, str]
    low: float
    high: float
    log: bool = False
    #: fitted as its square: a blur's width enters the image as its variance, whose slope at 0 is not 0 (the
    #: width's is, so a fit that reached 0 blur stayed there: the PSF collapsed on every Blender recording)
    squared: bool = False
    span: float | None = None
    #: needs a new renderer when it changes (the sensor's values do not)
    rebuild: bool = True

    @property
    def name(self) -> str:
        return ".".join(self.path)

    def bounds(self, guess: float) -> tuple[float, float]:
        """Bounds in the fitted coordinate for a scene whose value is ``guess``."""
        lo, hi = self.low, self.high
        if self.span is not None:
            lo, hi = max(lo, guess - self.span), min(hi, guess + self.span)
        return (self.to_fit(lo), self.to_fit(hi))

    def to_fit(self, value: float) -> float:
        return math.log10(value) if self.log else value * value if self.squared else value

    def from_fit(self, x: float) -> float:
        return 10.0**x if self.log else math.sqrt(max(x, 0.0)) if self.squared else x


PARAMETERS: tuple[Parameter, ...] = (
    Parameter(("fluid", "roughness"), 0.0007, 0.5, log=True),
    Parameter(("fluid", "reflectance"), 0.05, 1.0),
    Parameter(("light", "azimuth_deg"), -720.0, 720.0, span=30.0),
    Parameter(("light", "elevation_deg"), -89.0, 89.0, span=30.0),
    Parameter(("light", "angle_deg"), 0.2, 40.0, log=True),
    Parameter(("camera", "exposure"), 1e-3, 1e3, log=True),
    Parameter(("camera", "elevation_deg"), -89.0, 89.0, span=5.0),
    Parameter(("sensor", "blur_sigma_px"), 0.0, 3.0, squared=True, rebuild=False),
    Parameter(("sensor", "offset"), -0.2, 0.5, rebuild=False),
)

#: What the video cannot tell apart, and why: these keep the guess's value and the report says so.
UNIDENTIFIABLE: dict[str, str] = {
    "light.strength": "only exposure x strength reaches the pixels (fitted as camera.exposure, strength kept)",
    "nozzle.albedo": "only albedo x strength x exposure reaches the pixels; the fluid's reflectance is fitted "
    "relative to it",
    "camera.azimuth_deg": "rotating camera, light and defects together about the nozzle axis changes nothing "
    "(the gauge: kept, the light's azimuth is fitted relative to it)",
    "camera.distance_mm": "with fov_deg only their ratio (the scale in px/mm) is seen; kept",
    "artifacts.material.roughness": "a defect's glint, the sun's image in a sphere of a pixel or less, is a point "
    "source whose flux (F E r^2 / 4) its roughness does not change (service.render.glints): kept",
    "artifacts.material.reflectance": "a glint's flux grows as reflectance x radius^2: the radii take it up; kept",
}


def free(held: tuple[str, ...] = ()) -> tuple[Parameter, ...]:
    """The parameters a calibration fits: :data:`PARAMETERS` without those ``held`` at the guess's value (ones the user
    measured, such as a sun's angle the video cannot tell from the fluid's curvature). ValueError naming the choices for
    a name that is not a parameter."""
    names = [p.name for p in PARAMETERS]
    unknown = [name for name in held if name not in names]
    if unknown:
        raise ValueError(f"{', '.join(unknown)} is not a calibrated parameter (choose from {', '.join(names)})")
    return tuple(p for p in PARAMETERS if p.name not in held)


def index(name: str) -> int:
    """Where parameter ``name`` sits in :data:`PARAMETERS` (and in a scene's fitted coordinates, :func:`read`)."""
    return [p.name for p in PARAMETERS].index(name)


def read(scene: Scene, params: tuple[Parameter, ...] = PARAMETERS) -> np.ndarray:
    """The fitted coordinates of ``params`` in ``scene`` (a scene without a sensor block reads an ideal one)."""
    data = _with_sensor(scene.as_dict())
    return np.array([p.to_fit(float(data[p.path[0]][p.path[1]])) for p in params])


def write(scene: Scene, x: np.ndarray, params: tuple[Parameter, ...] = PARAMETERS) -> Scene:
    """``scene`` with ``params`` set from fitted coordinates ``x``; one whose coordinate is the scene's own keeps its
    value to the last bit (a log or squared coordinate's round trip would not: a held parameter stays as the user
    wrote it)."""
    data = _with_sensor(scene.as_dict())
    for p, value in zip(params, x):
        section, key = p.path
        if float(value) != p.to_fit(float(data[section][key])):
            data[section][key] = p.from_fit(float(value))
    data["sensor"]["offset"] = float(np.clip(data["sensor"]["offset"], -1.0, 1.0))
    data["light"]["azimuth_deg"] = float(data["light"]["azimuth_deg"])
    return Scene.from_dict(data)


def bounds(scene: Scene, params: tuple[Parameter, ...] = PARAMETERS) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper bounds (fitted coordinates) around ``scene``'s values."""
    data = _with_sensor(scene.as_dict())
    lohi = np.array([p.bounds(float(data[p.path[0]][p.path[1]])) for p in params]).reshape(-1, 2)
    return lohi[:, 0], lohi[:, 1]


def _with_sensor(data: dict) -> dict:
    data.setdefault("sensor", {"offset": 0.0, "blur_sigma_px": 0.0, "full_well_e": 0.0, "read_noise_e": 0.0})
    return data
