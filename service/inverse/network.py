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
from service.inverse.manifest import INPUT, OUTPUTS, load_manifest
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
        threads: int = 2,
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
        self._dtype = np.dtype(manifest.input.dtype)
        self._shape = (manifest.input.height, manifest.input.width)
        self._input, self._pooling = INPUT, 0
        self._pool_outside(path, manifest.input.downsample, options)

    def _pool_outside(self, path: Path, factor: int, options: ort.SessionOptions) -> None:
        """Run the graph from its input pooling on, the pooling done by :func:`pooling.block_means`, where the
        graph starts with it and the split reproduces the whole graph's outputs on test frames
        (:data:`pooling.PARITY_ABS`); the whole graph otherwise."""
        split = pooling.after_pooling(path, INPUT, factor)
        if split is None:
            return
        session = ort.InferenceSession(split[0], options, providers=["CPUExecutionProvider"])
        frames = np.random.default_rng(0).integers(0, 4096, (8, *self._shape), endpoint=True).astype(self._dtype)
        whole = self._session.run(list(OUTPUTS), {INPUT: frames})
        pooled = session.run(list(OUTPUTS), {split[1]: pooling.block_means(frames, factor)})
        if all(np.abs(a - b).max() <= pooling.PARITY_ABS for a, b in zip(whole, pooled)):
            self._session, self._input, self._pooling = session, split[1], factor
            pooling.block_means(frames[:1].astype(np.uint8), factor)  # the 8-bit kernel compiled now, not mid-stream

    def infer(self, frames: np.ndarray) -> InverseOutput:
        frames = np.asarray(frames)
        if frames.ndim != 3 or frames.shape[1:] != self._shape:
            raise MeniscopeError(
                "frames", f"shape {frames.shape} is not (N, {self._shape[0]}, {self._shape[1]}), the scene's ROI"
            )
        if frames.dtype not in (np.uint8, np.uint16) or not np.can_cast(frames.dtype, self._dtype, "safe"):
            raise MeniscopeError("frames", f"pixel type {frames.dtype} cannot feed a {self._dtype} model")
        # (N, H, W): the block means sum 8- or 16-bit pixels as they come (exactly); a graph fed whole gets its dtype
        x = np.ascontiguousarray(frames) if self._pooling else np.ascontiguousarray(frames, dtype=self._dtype)
        coefficients = np.empty((len(x), 4), np.float64)
        centre = np.empty(len(x), np.float64)
        for start in range(0, len(x), self.batch):
            part = slice(start, start + self.batch)
            feed = pooling.block_means(x[part], self._pooling) if self._pooling else x[part]
            coefficients[part], centre[part] = self._session.run(list(OUTPUTS), {self._input: feed})
        return InverseOutput(coefficients=coefficients, centre=centre)
