"""The training set: renders of random Eq. 1 shapes through a jittered scene and a randomised camera.

Each sample is a frame of the scene's ROI, rendered from coefficients (d, p, a, b) drawn uniformly
from :class:`service.physics.CoefficientRanges`, seen by a camera whose settings are drawn per frame
from :class:`service.camera_effects.EffectRanges`; each chunk of frames also moves the camera and the
light a little (:class:`Jitter`), standing for calibration error. The work is cut into fixed-size
chunks; chunk k is a pure function of (config, k), seeded by ``SeedSequence(seed, spawn_key=(k,))``,
so the files are the same for any number of workers.

On disk, a folder that ``numpy.load(..., mmap_mode="r")`` maps without reading it whole::

    frames.npy    (N, H, W) uint8 or uint16, stored pixel values
    coeffs.npy    (N, 4) float32, columns d (mm), p (-), a (mm), b (mm): exactly what was rendered
    centre.npy    (N,) float32, centre displacement D(0) = d + p R + a + b in mm
    manifest.json the config (scene included), counts, dtype, sha256 of each file; written last
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from concurrent.futures import Future
from dataclasses import dataclass
from datetime import UTC, datetime
from importlib.metadata import version
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from tqdm import tqdm

from service.calibration.open_ranges import drawn_over
from service.camera_effects import BitDepth, EffectRanges, apply_effects, pixel_dtype
from service.errors import MeniscopeError
from service.inverse.manifest import sha256_file
from service.inverse.nearest import DATASET_SCHEMA as SCHEMA
from service.jsonfile import read_schema_json
from service.physics import CoefficientRanges, centre_displacement
from service.render import Renderer
from service.scene import Scene
from training.engine import Engine, open_engine

#: Bumped whenever the same config would produce different files.
GENERATOR_VERSION = 1
FILES = ("frames.npy", "coeffs.npy", "centre.npy")

_Positive = Annotated[float, Field(ge=0, allow_inf_nan=False)]


class Jitter(BaseModel):
    """Per-chunk calibration error: uniform in +/- each half-width (angles in degrees), after drawing the parameters
    the scene's calibration left open over their ranges (``open_ranges``: :mod:`service.calibration.open_ranges`)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    camera_angle_deg: _Positive = 0.5  # camera azimuth and elevation, each
    distance_fraction: Annotated[float, Field(ge=0, lt=1, allow_inf_nan=False)] = 0.02  # camera distance
    light_angle_deg: _Positive = 2.0  # light azimuth and elevation, each
    open_ranges: dict[str, tuple[float, float]] = {}  # parameter name -> (low, high), file units

    def perturb(self, scene: Scene, rng: np.random.Generator) -> Scene:
        """A copy of ``scene`` with its open parameters drawn and camera and light moved by one draw (elevations
        kept inside their bounds).

        Built with :meth:`Scene.from_dict`, not ``model_copy``, which would keep the original's
        cached ``sha256`` and ``spheres``.
        """
        data = drawn_over(scene, self.open_ranges, rng).model_dump()
        cam, light = data["camera"], data["light"]
        da, de = rng.uniform(-self.camera_angle_deg, self.camera_angle_deg, size=2)
        la, le = rng.uniform(-self.light_angle_deg, self.light_angle_deg, size=2)
        scale = rng.uniform(1.0 - self.distance_fraction, 1.0 + self.distance_fraction)
        cam["azimuth_deg"] = float(cam["azimuth_deg"] + da)
        cam["elevation_deg"] = float(np.clip(cam["elevation_deg"] + de, -89.9, 89.9))
        cam["distance_mm"] = float(cam["distance_mm"] * scale)
        light["azimuth_deg"] = float(light["azimuth_deg"] + la)
        light["elevation_deg"] = float(np.clip(light["elevation_deg"] + le, -90.0, 90.0))
        return Scene.from_dict(data)


class DatasetConfig(BaseModel):
    """Everything that determines a dataset's files; stored in its manifest."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    scene: Scene
    samples: Annotated[int, Field(ge=1)]
    seed: Annotated[int, Field(ge=0)] = 0
    chunk_size: Annotated[int, Field(ge=1)] = 2048
    bit_depth: BitDepth = 8
    supersample: Annotated[int, Field(ge=1, le=8)] = 2
    ranges: CoefficientRanges = CoefficientRanges()
    jitter: Jitter = Jitter()
    augment: EffectRanges = EffectRanges()

    @property
    def chunks(self) -> int:
        return -(-self.samples // self.chunk_size)

    def chunk_slice(self, chunk_index: int) -> slice:
        """The samples chunk ``chunk_index`` holds."""
        start = chunk_index * self.chunk_size
        return slice(start, min(self.samples, start + self.chunk_size))

    @property
    def shape(self) -> tuple[int, int, int]:
        """Frames array shape (N, H, W)."""
        return self.samples, self.scene.camera.height_px, self.scene.camera.width_px


def generate_chunk(config: DatasetConfig, chunk_index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Samples of one chunk, a pure function of its arguments (safe to farm out to any worker).

    Returns
    -------
    frames : (n, H, W) uint8 or uint16, stored pixels
    coeffs : (n, 4) float32, d, p, a, b (the rendered values, float32-exact)
    centre : (n,) float32, D(0) in mm (Eq. 1 at r = 0)
    """
    part = config.chunk_slice(chunk_index)
    n = part.stop - part.start
    if n <= 0:
        raise ValueError(f"chunk {chunk_index} is outside the {config.chunks} chunks of the dataset")
    rng = np.random.default_rng(np.random.SeedSequence(config.seed, spawn_key=(chunk_index,)))
    scene = config.jitter.perturb(config.scene, rng)
    coeffs = config.ranges.sample(n, rng).astype(np.float32)
    linear = Renderer(scene, supersample=config.supersample, threads=1).render(coeffs.astype(np.float64))
    frames = apply_effects(linear, config.augment.sample(n, rng), config.bit_depth, rng)
    d, p, a, b = coeffs.astype(np.float64).T
    centre = centre_displacement(d, p, a, b, config.scene.nozzle.radius_mm).astype(np.float32)
    return frames, coeffs, centre


def _chunks(config: DatasetConfig, engine: Engine) -> Iterator[tuple[int, tuple[np.ndarray, np.ndarray, np.ndarray]]]:
    """(chunk index, chunk) pairs in order, computed by ``engine`` (at most 2 chunks per slot in flight)."""
    pending: dict[int, Future] = {}
    for k in range(config.chunks):
        pending[k] = engine.executor.submit(generate_chunk, config, k)
        if len(pending) >= 2 * engine.slots:
            first = min(pending)
            yield first, pending.pop(first).result()
    for k in sorted(pending):
        yield k, pending.pop(k).result()


def generate(config: DatasetConfig, out: str | Path, workers: int = 1, scheduler: str | None = None) -> dict[str, Any]:
    """Write the dataset folder ``out`` (new or empty) with ``workers`` local processes, or on the Dask
    cluster whose scheduler is at ``scheduler`` (``tcp://host:8786``); returns the manifest. The files are
    the same, byte for byte, whichever runs the chunks.

    On any failure the files written so far are removed, so a folder with a manifest is complete.
    """
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise MeniscopeError(out, "exists and is not an empty folder: choose a new one")
    with open_engine(workers, scheduler) as engine:
        return _write(config, out, engine)


def _write(config: DatasetConfig, out: Path, engine: Engine) -> dict[str, Any]:
    """The body of :func:`generate`, once ``out`` is checked and ``engine`` open."""
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise MeniscopeError(out, f"cannot create the folder: {exc.strerror or exc}") from None
    try:
        frames = np.lib.format.open_memmap(
            out / "frames.npy", mode="w+", dtype=pixel_dtype(config.bit_depth), shape=config.shape
        )
        coeffs = np.empty((config.samples, 4), np.float32)
        centre = np.empty(config.samples, np.float32)
        with tqdm(total=config.samples, unit="frame", desc=f"dataset {out.name}", disable=None) as bar:
            for k, (f, c, z) in _chunks(config, engine):
                part = config.chunk_slice(k)
                frames[part], coeffs[part], centre[part] = f, c, z
                bar.update(len(f))
        frames.flush()
        del frames
        np.save(out / "coeffs.npy", coeffs)
        np.save(out / "centre.npy", centre)
        manifest = {
            "schema": SCHEMA,
            "generator": {"module": __name__, "version": GENERATOR_VERSION, "meniscope": version("meniscope")},
            "created": datetime.now(UTC).isoformat(timespec="seconds"),
            "config": config.model_dump(mode="json"),
            "scene_sha256": config.scene.sha256,
            "samples": config.samples,
            "chunks": config.chunks,
            "frames": {"shape": list(config.shape), "dtype": pixel_dtype(config.bit_depth).name},
            "files": {name: sha256_file(out / name) for name in FILES},
        }
        (out / "manifest.json").write_text(json.dumps(manifest, indent=1, allow_nan=False) + "\n")
    except BaseException as exc:
        for name in (*FILES, "manifest.json"):
            (out / name).unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise MeniscopeError(out, f"cannot write the dataset: {exc.strerror or exc}") from None
        raise
    return manifest


@dataclass(frozen=True)
class Dataset:
    """A dataset opened read-only: memory maps of its arrays and its manifest."""

    path: Path
    frames: np.memmap  # (N, H, W) uint8 | uint16
    coeffs: np.memmap  # (N, 4) float32: d, p, a, b
    centre: np.memmap  # (N,) float32: D(0), mm
    manifest: dict[str, Any]
    config: DatasetConfig

    def __len__(self) -> int:
        return int(self.frames.shape[0])


def open_dataset(path: str | Path, scene: Scene | None = None, verify: bool = False) -> Dataset:
    """Map a dataset folder; every inconsistency is a one-line :class:`MeniscopeError`.

    ``scene``: refuse a dataset made for another scene. ``verify``: also check every file's sha256
    against the manifest (reads the files once).
    """
    path = Path(path)
    if not path.is_dir():
        raise MeniscopeError(path, "not a dataset folder (it does not exist or is a file)")
    manifest_path = path / "manifest.json"
    manifest = read_schema_json(manifest_path, SCHEMA, "not a dataset, or its generation did not finish")
    try:
        config = DatasetConfig.model_validate(manifest["config"])
    except (KeyError, ValidationError) as exc:
        raise MeniscopeError(manifest_path, f"config is missing or invalid: {str(exc).splitlines()[0]}") from None
    if scene is not None and scene.sha256 != config.scene.sha256:
        raise MeniscopeError(path, f"made for scene {config.scene.sha256[:12]}, not this one ({scene.sha256[:12]})")
    n, dtype = config.samples, pixel_dtype(config.bit_depth)
    expected = {
        "frames.npy": (config.shape, dtype),
        "coeffs.npy": ((n, 4), np.dtype(np.float32)),
        "centre.npy": ((n,), np.dtype(np.float32)),
    }
    arrays = {}
    for name, (shape, want) in expected.items():
        file = path / name
        try:
            array = np.load(file, mmap_mode="r")
        except FileNotFoundError:
            raise MeniscopeError(file, "missing") from None
        except (OSError, ValueError) as exc:
            raise MeniscopeError(file, f"corrupt or truncated: {exc}") from None
        if array.shape != tuple(shape) or array.dtype != want:
            raise MeniscopeError(file, f"holds {array.dtype} {array.shape}, the manifest says {want} {tuple(shape)}")
        if verify and sha256_file(file) != manifest.get("files", {}).get(name):
            raise MeniscopeError(file, "sha256 differs from the manifest: the file changed after it was written")
        arrays[name.removesuffix(".npy")] = array
    return Dataset(path=path, manifest=manifest, config=config, **arrays)
