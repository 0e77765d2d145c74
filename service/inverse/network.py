"""The learned inverse methods at run time: an exported ONNX graph run by onnxruntime on the CPU.

``network`` is Price et al.'s (2022, Sec. 3.2 (b)) VAE encoder + regressor, ``direct`` the CNN
trained end to end on renders; both take the ROI as stored and return Eq. 1's coefficients and
D(0, t) in one call (normalisation is inside the graph, see ``training.export``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnxruntime as ort

from service.errors import MeniscopeError
from service.inverse import pooling
from service.inverse.base import InverseMethod, InverseOutput
from service.inverse.manifest import INPUT, LATENT, OUTPUTS, load_manifest
from service.pipeline.records import LATENT_SIZE
from service.scene import Scene

#: onnxruntime's graph optimisation levels by name (``meniscope bench inference`` compares them).
_LEVEL = ort.GraphOptimizationLevel
OPTIMISATION = {
    "none": _LEVEL.ORT_DISABLE_ALL,
    "basic": _LEVEL.ORT_ENABLE_BASIC,
    "extended": _LEVEL.ORT_ENABLE_EXTENDED,
    "all": _LEVEL.ORT_ENABLE_ALL,
}


def session_options(threads: int, optimisation: str = "all") -> ort.SessionOptions:
    """Options for a small graph on a shared CPU: ``threads`` intra-op threads that sleep when idle.

    Spinning threads would burn the cores the reader and the window fit need; one inter-op thread
    since the graphs are a single chain; by default every graph optimisation (constant folding,
    conv + ReLU fusion, and the blocked NCHWc convolutions that make the graphs 1.9-2.8x faster than
    ``basic`` here: ``meniscope bench inference``).
    """
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.graph_optimization_level = OPTIMISATION[optimisation]
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    options.add_session_config_entry("session.inter_op.allow_spinning", "0")
    return options


def onnx_outputs(path: Path, frames: np.ndarray, outputs: tuple[str, ...] = tuple(OUTPUTS)) -> list[np.ndarray]:
    """The named outputs of an exported graph (by default coefficients (N, 4) and centre (N,)), run by
    onnxruntime's CPU provider: what training and quantising compare their graphs by."""
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    return session.run(list(outputs), {INPUT: frames})


class NetworkMethod(InverseMethod):
    """An ONNX inverse method of a model folder made by ``meniscope train`` for this scene.

    ``method``: "network" (VAE encoder + regressor) or "direct" (the end-to-end CNN); frames are
    run ``batch`` at a time on ``threads`` CPU threads, with ``optimisation`` (:data:`OPTIMISATION`); the graph's
    input pooling is done outside onnxruntime where that reproduces it (:mod:`service.inverse.pooling`).
    """

    def __init__(
        self,
        model_dir: str | Path,
        scene: Scene,
        method: str = "network",
        threads: int = 1,
        batch: int = 64,
        optimisation: str = "all",
    ) -> None:
        if threads < 1 or batch < 1:
            raise MeniscopeError(model_dir, f"threads and batch must be at least 1, got {threads} and {batch}")
        manifest = load_manifest(model_dir, scene)
        if method not in manifest.methods:
            raise MeniscopeError(model_dir, f"has no {method!r} model; it has {sorted(manifest.methods)}")
        path = Path(model_dir) / manifest.methods[method].file
        options = session_options(threads, optimisation)
        try:
            self._session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own untyped errors for unloadable graphs
            raise MeniscopeError(path, f"onnxruntime cannot load it: {str(exc).splitlines()[0]}") from None
        self.name = method
        self.batch = batch
        self._outputs = list(OUTPUTS) + self._latent_output(path)
        self._dtype = np.dtype(manifest.input.dtype)
        self._shape = (manifest.input.height, manifest.input.width)
        self._input, self.pooling, self.standardised = INPUT, 0, False
        self._pool_outside(path, manifest.input.downsample, options)

    def _latent_output(self, path: Path) -> list[str]:
        """[:data:`LATENT`] where the graph outputs the encoder's mean (``training.export.expose_latent``), else []."""
        (latent,) = [o for o in self._session.get_outputs() if o.name == LATENT] or [None]
        if latent is None:
            return []
        if latent.shape[-1] != LATENT_SIZE:
            raise MeniscopeError(path, f"its {LATENT} output has shape {latent.shape}, not (N, {LATENT_SIZE})")
        return [LATENT]

    def _pool_outside(self, path: Path, factor: int, options: ort.SessionOptions) -> None:
        """Run the graph from its normalisation on, the pooling and standardisation done by :func:`pooling.block_means`
        and :func:`pooling.standardise`, or else from its pooling on, where the graph starts with them and the split
        reproduces the whole graph's outputs on test frames (:data:`pooling.PARITY_ABS`); the whole graph otherwise."""
        frames = np.random.default_rng(0).integers(0, 4096, (8, *self._shape), endpoint=True).astype(self._dtype)
        whole = self._session.run(self._outputs, {INPUT: frames})
        means = pooling.block_means(frames, factor)
        for standardised in (True, False):
            split = pooling.after_pooling(path, INPUT, factor, standardised)
            if split is None:
                continue
            inputs = pooling.standardise(means.copy()) if standardised else means  # standardised in place: a copy
            try:
                session = ort.InferenceSession(split[0], options, providers=["CPUExecutionProvider"])
                out = session.run(self._outputs, {split[1]: inputs})
            except Exception:  # onnxruntime's own untyped errors: a split it cannot run is not taken
                continue
            if all(np.abs(a - b).max() <= pooling.PARITY_ABS for a, b in zip(whole, out)):
                self._session, self._input, self.pooling, self.standardised = session, split[1], factor, standardised
                # the 8-bit kernel compiled now, not mid-stream
                pooling.block_means(frames[:1].astype(np.uint8), factor)
                return

    def check(self, frames: np.ndarray) -> None:
        if frames.ndim != 3 or frames.shape[1:] != self._shape:
            raise MeniscopeError(
                "frames", f"shape {frames.shape} is not (N, {self._shape[0]}, {self._shape[1]}), the scene's ROI"
            )
        if frames.dtype not in (np.uint8, np.uint16) or not np.can_cast(frames.dtype, self._dtype, "safe"):
            raise MeniscopeError("frames", f"pixel type {frames.dtype} cannot feed a {self._dtype} model")

    def prepare(self, frames: np.ndarray) -> np.ndarray:
        """The graph's input of ROI frames (N, H, W): their block means (N, 1, H/f, W/f) float32 where the graph is run
        from its pooling on (the sums of 8- or 16-bit pixels as they come, exact), the frames in the graph's dtype
        otherwise."""
        frames = np.asarray(frames)
        self.check(frames)
        if self.pooling:
            inputs = pooling.block_means(frames, self.pooling)
            return pooling.standardise(inputs) if self.standardised else inputs
        return np.ascontiguousarray(frames, dtype=self._dtype)

    def infer_prepared(self, inputs: np.ndarray) -> InverseOutput:
        coefficients = np.empty((len(inputs), 4), np.float64)
        centre = np.empty(len(inputs), np.float64)
        latent = np.empty((len(inputs), LATENT_SIZE), np.float32) if len(self._outputs) > len(OUTPUTS) else None
        for start in range(0, len(inputs), self.batch):
            part = slice(start, start + self.batch)
            outputs = self._session.run(self._outputs, {self._input: inputs[part]})
            coefficients[part], centre[part] = outputs[:2]
            if latent is not None:
                latent[part] = outputs[2]
        return InverseOutput(coefficients=coefficients, centre=centre, latent=latent)

    def infer(self, frames: np.ndarray) -> InverseOutput:
        return self.infer_prepared(self.prepare(frames))
