"""The learned graphs' input layers done outside onnxruntime: compiled block means and their standardisation, and
the graph from after them.

Every exported graph starts as ``training.normalise.Normalise`` made it: the frames cast to float32, given a
channel axis, average-pooled by the manifest's ``downsample``, then standardised frame by frame. onnxruntime spent
half of a 96 x 96 frame's inference on the pooling and a sixth of the rest on the standardisation's dozen small
nodes (docs/benchmarks.md); the measures' pass makes both as it reads the pixels, and the rest of the graph is run
from the normalisation's output on (or from the pooling's, where a graph's normalisation is not this one). A graph
that does not start so, or whose split does not reproduce it, runs whole.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numba import njit

#: The input layers as exported, from the graph's input on (Constant nodes aside).
PREFIX = ("Cast", "Cast", "Unsqueeze", "AveragePool")
#: Largest difference in any output allowed between the split graph and the whole one (float32 rounding).
PARITY_ABS = 1e-5
#: Added to each frame's standard deviation (in stored DN) by the graphs' normalisation, so that a flat frame maps to
#: zeros, not NaN; far below the 1 DN quantisation step, so it never changes a real frame's scale.
STD_FLOOR_DN = 1e-6
#: The node the exported normalisation's names start with (``training.normalise.Normalise`` as ``normalise``).
NORMALISATION = "/normalise/"


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


@njit(cache=True, nogil=True, error_model="numpy")
def standardise_frame(frame, total, squares):  # type: ignore[no-untyped-def]
    """``frame`` (M,) float32 in place as ``(x - mean) / (std + STD_FLOOR_DN)``, std the unbiased standard deviation
    (torch's), from the float64 sum and sum of squares of its values."""
    size = frame.size
    mean = total / size
    scale = 1.0 / (np.sqrt(max(squares - total * mean, 0.0) / (size - 1)) + STD_FLOOR_DN)
    for k in range(size):
        frame[k] = (frame[k] - mean) * scale


@njit(cache=True, nogil=True)
def _standardise(pooled):  # type: ignore[no-untyped-def]
    """Each frame of ``pooled`` (N, rows, columns) float32 standardised in place (:func:`standardise_frame`), its
    values summed and squared column by column, row after row, then the columns' sums added: as the measures' pass
    sums them (the same result to the bit), and without one long chain of dependent additions."""
    count, rows, columns = pooled.shape
    sums, squares = np.zeros(columns), np.zeros(columns)
    for i in range(count):
        sums[:] = 0.0
        squares[:] = 0.0
        for r in range(rows):
            for c in range(columns):
                v = np.float64(pooled[i, r, c])
                sums[c] += v
                squares[c] += v * v
        standardise_frame(pooled[i].reshape(-1), sums.sum(), squares.sum())


def standardise(pooled: np.ndarray) -> np.ndarray:
    """Block means (N, 1, H/f, W/f) float32 standardised frame by frame, in place, as the graphs' normalisation does
    after their pooling (``training.normalise.Normalise``); returned for convenience."""
    _standardise(pooled.reshape(len(pooled), pooled.shape[-2], pooled.shape[-1]))
    return pooled


def after_pooling(path: Path, input_name: str, factor: int, standardised: bool = False) -> tuple[bytes, str] | None:
    """The graph at ``path`` from its input pooling on (serialised) and the name of its new input, or None where it
    does not start with :data:`PREFIX` pooling ``factor`` x ``factor`` blocks without padding; with ``standardised``,
    from its normalisation on (the :data:`NORMALISATION` nodes' one output the rest of the graph reads), or None
    where it has none."""
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
    if standardised:
        inside = [n for n in model.graph.node if n.name.startswith(NORMALISATION)]
        names = {n.name for n in inside}
        read = {
            t for t in (o for n in inside for o in n.output) if any(c.name not in names for c in consumers.get(t, []))
        }
        if len(read) != 1:
            return None
        (tensor,) = read
    outputs = [o.name for o in model.graph.output]
    split = Extractor(onnx.shape_inference.infer_shapes(model)).extract_model([tensor], outputs)
    return split.SerializeToString(), tensor
