"""The learned graphs' input pooling done outside onnxruntime: a compiled block mean, and the graph from after it.

Every exported graph starts as ``training.normalise.Normalise`` made it: the frames cast to float32, given a
channel axis and average-pooled by the manifest's ``downsample``. onnxruntime spends half of a 96 x 96 frame's
inference there (10 of 22 us of CPU); the block means below take 4, and the rest of the graph is run from the
pooling's output on. A graph that does not start so, or whose split does not reproduce it, runs whole.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numba import njit

#: The input layers as exported, from the graph's input on (Constant nodes aside).
PREFIX = ("Cast", "Cast", "Unsqueeze", "AveragePool")
#: Largest difference in any output allowed between the split graph and the whole one (float32 rounding).
PARITY_ABS = 1e-5


@njit(cache=True, nogil=True)
def _block_means(frames, factor, out):  # type: ignore[no-untyped-def]
    """Means of ``factor`` x ``factor`` blocks of ``frames`` (N, H, W) into ``out`` (N, 1, H/f, W/f) float32: each
    block row's columns summed first (a loop the compiler vectorises), in float64 (exact for integer pixels)."""
    n, h, w = frames.shape
    rows = np.empty(w, np.float64)
    for i in range(n):
        for r in range(h // factor):
            for c in range(w):
                rows[c] = frames[i, r * factor, c]
            for rr in range(r * factor + 1, r * factor + factor):
                for c in range(w):
                    rows[c] += frames[i, rr, c]
            for c in range(w // factor):
                s = rows[c * factor]
                for cc in range(1, factor):
                    s += rows[c * factor + cc]
                out[i, 0, r, c] = s / (factor * factor)


def block_means(frames: np.ndarray, factor: int) -> np.ndarray:
    """(N, H, W) frames -> (N, 1, H/f, W/f) float32 means of their ``factor`` x ``factor`` blocks, as the graphs'
    AveragePool makes them."""
    n, h, w = frames.shape
    out = np.empty((n, 1, h // factor, w // factor), np.float32)
    _block_means(np.ascontiguousarray(frames), factor, out)
    return out


def after_pooling(path: Path, input_name: str, factor: int) -> tuple[bytes, str] | None:
    """The graph at ``path`` from its input pooling on (serialised) and the name of its new input, or None where it
    does not start with :data:`PREFIX` pooling ``factor`` x ``factor`` blocks without padding."""
    import onnx
    from onnx.utils import Extractor

    model = onnx.load(str(path))
    consumers: dict[str, list] = {}
    for node in model.graph.node:
        for name in node.input:
            consumers.setdefault(name, []).append(node)
    tensor, node = input_name, None
    for op in PREFIX:
        following = consumers.get(tensor, [])
        if len(following) != 1 or following[0].op_type != op:
            return None
        node = following[0]
        tensor = node.output[0]
    attributes = {a.name: onnx.helper.get_attribute_value(a) for a in node.attribute}
    if (
        list(attributes.get("kernel_shape", [])) != [factor, factor]
        or list(attributes.get("strides", [])) != [factor, factor]
        or any(attributes.get("pads", []))
        or attributes.get("ceil_mode", 0)
    ):
        return None
    outputs = [o.name for o in model.graph.output]
    split = Extractor(onnx.shape_inference.infer_shapes(model)).extract_model([tensor], outputs)
    return split.SerializeToString(), tensor
