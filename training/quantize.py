"""``meniscope quantize``: an int8 copy of a model folder's inverse graphs, with its accuracy cost measured.

onnxruntime's quantiser rewrites the convolutions after the first (and their ReLUs) to 8-bit integer
arithmetic: ``static`` (QDQ) with activation ranges calibrated on synthetic renders beforehand, so that the
CPU runs them as QLinearConv; ``dynamic`` with ranges measured per batch at run time (ConvInteger).
The first convolution stays float32: it reads the standardised frame, whose sparse highlights lie
far out in the tails, and the trunk's last linear layer and the regression heads are too small to
gain. Both graphs are then run on renders no model saw (seeded apart from training, the database
and calibration), and the largest difference from the float graph and each one's error against the
renders' truth go into the manifest; ``meniscope bench inference --models DIR`` and ``meniscope bench
tradeoff --more-models DIR`` measure the speed. On the development CPU (AVX2 without VNNI) neither mode
was faster than float beyond the noise (static 0.87-1.02x, dynamic 0.2x: docs/benchmarks.md): the choice is there for CPUs where int8 pays.
"""

from __future__ import annotations

import tempfile
from datetime import UTC, datetime
from importlib.metadata import version
from pathlib import Path

import numpy as np
import onnx
from onnxruntime.quantization import (
    CalibrationDataReader,
    QuantFormat,
    QuantType,
    quant_pre_process,
    quantize_dynamic,
    quantize_static,
)

from service.errors import MeniscopeError
from service.inverse.manifest import (
    INPUT,
    MANIFEST,
    Manifest,
    MethodEntry,
    Parity,
    Quantisation,
    load_manifest,
    prepare_model_folder,
    sha256_file,
    write_manifest,
)
from service.inverse.network import onnx_outputs
from service.scene import Scene
from service.validation.truth import TARGETS, score
from training.dataset import DatasetConfig, generate_chunk

MODES = ("static", "dynamic")
#: Seeds of the calibration and parity renders: apart from the training renders (0) and the database (1).
CALIBRATION_SEED, PARITY_SEED = 3, 4
#: Frames per calibration batch (the runtime's default batch).
BATCH = 64


def renders(scene: Scene, samples: int, seed: int, bit_depth: int) -> tuple[np.ndarray, np.ndarray]:
    """Stored frames (N, H, W) and their true targets (N, 5) in :data:`TARGETS` order, rendered as training's are."""
    config = DatasetConfig(scene=scene, samples=samples, seed=seed, chunk_size=samples, bit_depth=bit_depth)
    frames, coeffs, centre = generate_chunk(config, 0)
    return frames, np.column_stack([coeffs, centre]).astype(np.float64)


class _Batches(CalibrationDataReader):
    """The calibration frames, :data:`BATCH` at a time, as the graph's input."""

    def __init__(self, frames: np.ndarray) -> None:
        self._batches = iter([{INPUT: frames[i : i + BATCH]} for i in range(0, len(frames), BATCH)])

    def get_next(self) -> dict[str, np.ndarray] | None:
        return next(self._batches, None)


def quantised_nodes(path: Path) -> list[str]:
    """The convolutions of a graph after the first and the ReLUs that follow them, by node name.

    Quantising a ReLU with its convolution puts the activation's 8-bit range on [0, max] alone
    (the ReLU itself disappears): half the step of a range that also spans the negative values.
    """
    nodes = onnx.load(str(path)).graph.node
    convs = [n for n in nodes if n.op_type == "Conv"][1:]
    outputs = {o for n in convs for o in n.output}
    return [n.name for n in convs] + [n.name for n in nodes if n.op_type == "Relu" and n.input[0] in outputs]


def quantize_graph(source: Path, target: Path, mode: str, calibration: np.ndarray) -> list[str]:
    """Write the int8 copy of ``source`` to ``target``; returns the names of the nodes quantised.

    The quantiser's own pre-processing (shape inference, constant folding) runs first, as it asks.
    """
    with tempfile.TemporaryDirectory(prefix="meniscope-quantize-") as scratch:
        prepared = str(Path(scratch) / "prepared.onnx")
        quant_pre_process(str(source), prepared)
        nodes = quantised_nodes(Path(prepared))
        if mode == "static":
            quantize_static(
                prepared,
                str(target),
                _Batches(calibration),
                quant_format=QuantFormat.QDQ,
                activation_type=QuantType.QUInt8,
                weight_type=QuantType.QInt8,
                op_types_to_quantize=["Conv", "Relu"],
                nodes_to_quantize=nodes,
            )
        else:
            quantize_dynamic(
                prepared,
                str(target),
                weight_type=QuantType.QInt8,
                op_types_to_quantize=["Conv", "Relu"],
                nodes_to_quantize=nodes,
            )
    return nodes


def _targets(path: Path, frames: np.ndarray) -> np.ndarray:
    """A graph's outputs on ``frames`` as targets (N, 5)."""
    coefficients, centre = onnx_outputs(path, frames)
    return np.column_stack([coefficients, centre]).astype(np.float64)


def parity(source: Path, target: Path, frames: np.ndarray, truth: np.ndarray) -> Parity:
    """The int8 graph against its float source on the same renders: largest differences and both accuracies."""
    reference, got = _targets(source, frames), _targets(target, frames)
    return Parity(
        frames=len(frames),
        seed=PARITY_SEED,
        max_abs={k: float(v) for k, v in zip(TARGETS, np.abs(got - reference).max(axis=0))},
        float32=score(reference, truth),
        int8=score(got, truth),
    )


def quantize_models(
    models: Path, out: Path, scene: Scene, mode: str = "static", calibration_frames: int = 512, parity_frames: int = 512
) -> Manifest:
    """Everything ``meniscope quantize`` does: int8 copies of every inverse graph of ``models`` in ``out``,
    with a manifest that records how they were made and their parity against the float graphs."""
    if mode not in MODES:
        raise MeniscopeError("--mode", f"unknown mode {mode!r}; choose one of {', '.join(MODES)}")
    source = load_manifest(models, scene)
    if source.quantisation is not None:
        raise MeniscopeError(models, "is already int8 (`meniscope quantize` made it): quantise its float source")
    if Path(out).resolve() == Path(models).resolve():
        raise MeniscopeError(out, "must differ from --models: the float folder is kept")
    prepare_model_folder(out)
    input_dtype = np.dtype(source.input.dtype)
    bit_depth = source.training.dataset.get("bit_depth", 8)
    calibration = renders(scene, calibration_frames, CALIBRATION_SEED, bit_depth)[0].astype(input_dtype)
    frames, truth = renders(scene, parity_frames, PARITY_SEED, bit_depth)
    frames = frames.astype(input_dtype)
    methods, parities, nodes = {}, {}, []
    for name, entry in source.methods.items():
        target = Path(out) / entry.file
        nodes += [f"{name}: {node}" for node in quantize_graph(Path(models) / entry.file, target, mode, calibration)]
        parities[name] = parity(Path(models) / entry.file, target, frames, truth)
        methods[name] = MethodEntry(
            file=entry.file,
            description=f"{entry.description}; int8 ({mode})",
            parity_max_abs=max(parities[name].max_abs.values()),
        )
    activations = (
        f"uint8, ranges calibrated (min-max) on {calibration_frames} renders"
        if mode == "static"
        else "uint8, ranges measured per batch at run time"
    )
    quantisation = Quantisation(
        mode=mode,
        weights="int8, per tensor",
        activations=activations,
        nodes=nodes,
        source={"path": str(models), "manifest_sha256": sha256_file(Path(models) / MANIFEST)},
        calibration={"renders": calibration_frames, "seed": CALIBRATION_SEED} if mode == "static" else {},
        parity=parities,
    )
    manifest = source.model_copy(
        update={
            "created": datetime.now(UTC).isoformat(timespec="seconds"),
            "meniscope": version("meniscope"),
            "methods": methods,
            "autoencoder": None,
            "validation": {},
            "quantisation": quantisation,
            "files": {},
        }
    )
    write_manifest(out, manifest)
    return load_manifest(out, scene)
