"""The manifest of a model folder: what was trained, for which scene, on what, how well, and every file's hash.

``meniscope train`` writes ``MODEL_DIR/manifest.json`` last; the runtime reads it through
:func:`load_manifest`, which refuses a folder made for another scene or whose files changed since.
Older manifests load as long as their keys are a subset: missing optional keys take the defaults.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from service.errors import MeniscopeError
from service.jsonfile import read_schema_json
from service.scene import Scene

SCHEMA = "meniscope.models/1"
MANIFEST = "manifest.json"
#: The input every exported graph takes (stored pixels, N x H x W) and its outputs in order, with units.
INPUT = "frames"
OUTPUTS = {
    "coefficients": "float32 (N, 4): d (mm), p (-), a (mm), b (mm) of Eq. 1",
    "centre": "float32 (N,): centre displacement D(0, t) (mm)",
}

#: The network's third output (``training.export.expose_latent``): the VAE encoder's posterior mean its head reads,
#: which the window model may take per frame too: float32 (N, 10) (the direct CNN's graph has none).
LATENT = "latent"

#: Outputs of the VAE's reconstruction graph (``autoencoder.onnx``), which takes the same input.
AUTOENCODER_OUTPUTS = {
    "normalised": "float32 (N, 1, h, w): the frames as the networks see them (pooled, standardised)",
    "reconstruction": "float32 (N, 1, h, w): the VAE decoder's output from the encoder's posterior mean",
}

Finite = Annotated[float, Field(allow_inf_nan=False)]


class _Record(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class InputSpec(_Record):
    """The frames a graph takes, and the image it reduces them to inside the graph."""

    height: int  # the scene's ROI, px
    width: int
    dtype: Literal["uint8", "uint16"]  # stored pixel type; uint16 graphs also take widened uint8 frames
    downsample: int  # average-pooling factor inside the graph
    model_height: int  # height // downsample
    model_width: int


class MethodEntry(_Record):
    """One inverse method of the folder: its file and how it was made."""

    file: str  # relative to the model folder
    description: str
    parity_max_abs: Finite | None = None  # largest |reference - this graph| over the outputs: torch at export,
    # the float graph for an int8 one (``meniscope quantize``)


class Scores(_Record):
    """Accuracy of one method on one set of frames with known coefficients.

    ``rmse`` has keys d (mm), p (-), a (mm), b (mm), centre (mm); ``centre_correlation`` is
    Pearson's r between predicted and true D(0, t) (None when either is constant).
    """

    frames: int
    rmse: dict[str, Finite]
    centre_correlation: Finite | None


class Parity(_Record):
    """An int8 graph against the float one it was made from, on the same renders (coefficients known)."""

    frames: int
    seed: int  # of the renders (``training.dataset``)
    max_abs: dict[str, Finite]  # largest |float - int8| per target: d (mm), p (-), a (mm), b (mm), centre (mm)
    float32: Scores  # each graph's accuracy against the renders' truth
    int8: Scores


class Quantisation(_Record):
    """How an int8 folder was made from a float one (``meniscope quantize``) and what it costs."""

    mode: Literal["static", "dynamic"]  # activation ranges calibrated beforehand, or measured per batch at run time
    weights: str
    activations: str
    nodes: list[str]  # the quantised nodes of each graph; the rest stays float32
    source: dict[str, Any]  # the float folder: path and its manifest's sha256
    calibration: dict[str, int]  # renders and seed the static ranges came from (empty for dynamic)
    parity: dict[str, Parity]  # method -> against its float graph


class TrainingSummary(_Record):
    """Where the training data came from and the full training configuration."""

    dataset: dict[str, Any]  # excerpt of the dataset manifest: path, samples, seed, bit depth, hashes
    lab_video: dict[str, Any]  # path, frames used, fps, size, bit depth
    config: dict[str, Any]  # the complete config dataclass, as a dict
    seconds: Finite  # wall time of the whole run
    losses: dict[str, Finite] = {}  # final training losses per model


class Manifest(_Record):
    """``MODEL_DIR/manifest.json``."""

    schema_: Literal["meniscope.models/1"] = Field(SCHEMA, alias="schema")
    created: str  # ISO 8601, UTC
    meniscope: str  # package version that trained
    scene: dict[str, Any]
    scene_sha256: str
    input: InputSpec
    outputs: dict[str, str] = OUTPUTS
    methods: dict[str, MethodEntry]
    autoencoder: MethodEntry | None = None  # the VAE's reconstruction graph, for figures: not an inverse method
    training: TrainingSummary
    validation: dict[str, dict[str, Scores]] = {}  # method -> data set ("synthetic", "recording", ...) -> scores
    quantisation: Quantisation | None = None  # an int8 copy of a float folder: how, and its parity
    files: dict[str, str]  # every other file of the folder (relative path) -> sha256

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)

    def to_json(self) -> str:
        return json.dumps(self.model_dump(mode="json", by_alias=True), indent=1, allow_nan=False) + "\n"

    def label(self, method: str) -> str:
        """How benchmarks name one of its methods: the name, the model input size and any quantisation."""
        q = self.quantisation
        return f"{method} {self.input.model_height}px" + (f" int8 {q.mode}" if q else "")


def sha256_file(path: Path) -> str:
    """Hex sha256 of a file, read in 4 MiB blocks."""
    digest = hashlib.sha256()
    with Path(path).open("rb") as f:
        for block in iter(lambda: f.read(1 << 22), b""):
            digest.update(block)
    return digest.hexdigest()


def hash_folder(model_dir: Path) -> dict[str, str]:
    """sha256 of every file under ``model_dir`` except the manifest, by relative POSIX path."""
    model_dir = Path(model_dir)
    return {
        p.relative_to(model_dir).as_posix(): sha256_file(p)
        for p in sorted(model_dir.rglob("*"))
        if p.is_file() and p.relative_to(model_dir).as_posix() != MANIFEST
    }


def write_manifest(model_dir: Path, manifest: Manifest) -> Path:
    """Write ``manifest`` (its ``files`` hashes taken now, from the folder) as ``MODEL_DIR/manifest.json``."""
    path = Path(model_dir) / MANIFEST
    path.write_text(manifest.model_copy(update={"files": hash_folder(model_dir)}).to_json())
    return path


def prepare_model_folder(out: Path) -> None:
    """Make ``out`` ready to receive models (``meniscope train``, ``meniscope quantize``): new, empty, or a model
    folder whose listed files are replaced; anything else is refused, so no other folder is overwritten."""
    old = out / MANIFEST
    if out.exists() and not out.is_dir():
        raise MeniscopeError(out, "exists and is a file, not a model folder")
    if out.is_dir() and any(out.iterdir()):
        if not old.is_file():
            raise MeniscopeError(out, "exists and is neither empty nor a model folder: choose a new one")
        for name in json.loads(old.read_text()).get("files", {}):
            (out / name).unlink(missing_ok=True)
        old.unlink()
    out.mkdir(parents=True, exist_ok=True)


def load_manifest(model_dir: str | Path, scene: Scene) -> Manifest:
    """Read and check a model folder's manifest; every problem is one :class:`MeniscopeError` line.

    Refuses a folder trained for another scene (by the scene's sha256), and one where a file the
    manifest lists is missing or differs from its recorded sha256.
    """
    model_dir = Path(model_dir)
    if not model_dir.is_dir():
        raise MeniscopeError(model_dir, "not a model folder (it does not exist or is a file)")
    path = model_dir / MANIFEST
    data = read_schema_json(path, SCHEMA, "not a model folder, or `meniscope train` did not finish")
    try:
        manifest = Manifest.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        loc = ".".join(str(p) for p in err["loc"])
        raise MeniscopeError(path, f"invalid manifest: {loc}: {err['msg']}") from None
    if manifest.scene_sha256 != scene.sha256:
        raise MeniscopeError(
            model_dir,
            f"trained for scene {manifest.scene_sha256[:12]}, not this one ({scene.sha256[:12]}): "
            "train models for this scene with `meniscope train`",
        )
    for name, expected in manifest.files.items():
        file = model_dir / name
        if not file.is_file():
            raise MeniscopeError(file, f"missing: {MANIFEST} lists it")
        if sha256_file(file) != expected:
            raise MeniscopeError(file, f"sha256 differs from {MANIFEST}: the file changed after training")
    graphs = {**manifest.methods, **({"autoencoder": manifest.autoencoder} if manifest.autoencoder else {})}
    for method, entry in graphs.items():
        if entry.file not in manifest.files:
            raise MeniscopeError(path, f"method {method!r} names {entry.file!r}, which the manifest does not hash")
    return manifest
