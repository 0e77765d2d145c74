"""``meniscope validate``: the paper's validation figures for a model folder and render databases, as PNGs
and one JSON document of every number measured (``figures.json``, schema ``meniscope.validation/1``).

Runs in the service half (onnxruntime, no torch) so it checks the very artifacts the service loads; the
VAE reconstructions come from the model folder's ``autoencoder.onnx`` (exported by ``meniscope train``),
and a folder made before that graph existed gets every figure but that one.
"""

from __future__ import annotations

import json
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort
from tqdm import tqdm

from service.errors import MeniscopeError
from service.inverse.manifest import AUTOENCODER_OUTPUTS, INPUT, Manifest, load_manifest, write_manifest
from service.inverse.methods import open_database
from service.inverse.network import NetworkMethod, session_options
from service.recordings.roi import read_roi_frames
from service.render import Renderer
from service.scene import Scene
from service.validation.evaluate import Evaluation, RecordingResult
from service.validation.figures import plot_centre_series, plot_rows

SCHEMA = "meniscope.validation/1"
#: Lab frames shown in the reconstruction and render figures (Figs. 13 and 15).
SHOWN_FRAMES = 8


def lab_frames(path: Path, scene: Scene, count: int = SHOWN_FRAMES) -> np.ndarray:
    """``count`` ROI frames (count, H, W) as stored, evenly spaced over a recording."""
    return read_roi_frames(path, scene, count, run=1)[0]


def reconstructions(model_dir: Path, manifest: Manifest, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The VAE's input and reconstruction (N, h, w) of stored frames, through ``autoencoder.onnx``."""
    session = ort.InferenceSession(
        str(model_dir / manifest.autoencoder.file), session_options(1), providers=["CPUExecutionProvider"]
    )
    x, recon = session.run(list(AUTOENCODER_OUTPUTS), {INPUT: frames.astype(manifest.input.dtype)})
    return x[:, 0], recon[:, 0]


def record_scores(model_dir: Path, scene: Scene, results: list[RecordingResult]) -> None:
    """Add the networks' scores on each recording to the model manifest's ``validation`` (keyed by file name);
    only the manifest changes, so its file hashes stay those of training."""
    manifest = load_manifest(model_dir, scene)
    validation = {name: dict(by_data) for name, by_data in manifest.validation.items()}
    for result in results:
        for name in manifest.methods:
            validation.setdefault(name, {})[result.path.name] = result.methods[name].scores
    write_manifest(model_dir, manifest.model_copy(update={"validation": validation}))
    load_manifest(model_dir, scene)  # the service must still accept it


def validate(
    scene: Scene,
    model_dir: Path,
    databases: list[Path],
    recordings: list[Path],
    out: Path,
    lab_video: Path | None = None,
    record: bool = False,
) -> dict[str, Any]:
    """Measure every method on every recording, draw the figures into ``out`` and write ``figures.json``."""
    if not recordings:
        raise MeniscopeError("--recording", "name at least one simulated recording to score against")
    for option, names in (("--database", [d.name for d in databases]), ("--recording", [r.name for r in recordings])):
        if len(set(names)) != len(names):
            raise MeniscopeError(option, f"file and folder names must differ (they label the results): {names}")
    labels = [d.name for d in databases]
    if out.exists() and not out.is_dir():
        raise MeniscopeError(out, "exists and is a file, not a folder")
    manifest = load_manifest(model_dir, scene)
    networks = {name: NetworkMethod(model_dir, scene, name) for name in manifest.methods}
    loaded, index_seconds = {}, {}
    for folder in tqdm(databases, desc="index databases", unit="database", disable=None):
        started = time.perf_counter()
        loaded[folder.name] = open_database(folder, scene)
        index_seconds[folder.name] = time.perf_counter() - started
    out.mkdir(parents=True, exist_ok=True)
    evaluation = Evaluation(scene, networks, loaded)
    results = []
    with tqdm(total=len(recordings) * evaluation.steps() + 2, unit="step", desc="validate", disable=None) as bar:
        for path in recordings:
            results.append(evaluation.recording(path, bar))
        figures = {
            f"centre {r.path.name}": plot_centre_series(r, out / f"centre_{r.path.stem}.png").name for r in results
        }
        bar.set_description("validate: lab frames")
        lab = lab_video or recordings[0]
        frames = lab_frames(lab, scene)
        if manifest.autoencoder is not None:
            shown, recon = reconstructions(model_dir, manifest, frames)
            figures["reconstructions"] = plot_rows(
                {"lab frame": shown, "VAE": recon},
                out / "reconstructions.png",
                f"{lab.name}: frames as the VAE sees them, and its reconstructions",
            ).name
        bar.update()
        renderer = Renderer(scene)
        rows = {"lab frame": frames.astype(np.float64)}
        rows.update(
            {
                f"render of\n{name}": renderer.render(method.infer(frames).coefficients)
                for name, method in networks.items()
            }
        )
        figures["inferred renders"] = plot_rows(
            rows,
            out / "inferred_renders.png",
            f"{lab.name}: frames beside renders of the coefficients inferred from them",
        ).name
        bar.update()
    document = {
        "schema": SCHEMA,
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "scene_sha256": scene.sha256,
        "models": {
            "path": str(model_dir),
            "created": manifest.created,
            "autoencoder": manifest.autoencoder is not None,
        },
        "databases": {
            label: {"path": str(folder), "renders": len(loaded[label]), "index_seconds": index_seconds[label]}
            for label, folder in zip(labels, databases)
        },
        "lab_video": str(lab),
        "recordings": {r.path.name: r.as_json() for r in results},
        "figures": figures,
    }
    (out / "figures.json").write_text(json.dumps(document, indent=1, allow_nan=False) + "\n")
    if record:
        record_scores(model_dir, scene, results)
    return document
