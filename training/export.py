"""ONNX export of the inverse networks: stored pixels in, Eq. 1 coefficients and D(0, t) out, one file each.

The graph's input is the scene's ROI as stored, uint8 or uint16 of shape (N, H, W) with a dynamic
batch; normalisation is inside the graph, so ``service.inverse.network`` only hands frames over.
Outputs: ``coefficients`` (N, 4) float32, columns d (mm), p (-), a (mm), b (mm), and ``centre``
(N,) float32, D(0, t) in mm. The VAE's reconstruction graph (``autoencoder.onnx``, for the validation
figures) takes the same input and outputs ``normalised`` and ``reconstruction`` instead.

Exporter: the TorchScript one (``dynamo=False``). torch 2.13's default dynamo exporter needs the
onnxscript package and takes ~14 s per graph against < 1 s; the TorchScript exporter cannot take a
uint16 input ("ScalarType UInt16 is an unexpected tensor scalar type"), so the graph is exported
with a float32 input and a Cast from the stored dtype is put in front of it here. Weights stay
inside the .onnx file (no .onnx.data beside it).
"""

from __future__ import annotations

import io
import warnings
from pathlib import Path

import numpy as np
import onnx
import torch
from onnx import TensorProto, helper
from torch import nn

from service.inverse.manifest import INPUT, LATENT, OUTPUTS
from service.inverse.network import onnx_outputs

OPSET = 17
#: Stored pixel types a graph can take, as numpy names.
INPUT_DTYPES = {"uint8": TensorProto.UINT8, "uint16": TensorProto.UINT16}
_FLOAT_INPUT = "frames_float32"


def export_onnx(
    model: nn.Module,
    path: Path,
    height: int,
    width: int,
    dtype: str = "uint16",
    outputs: tuple[str, ...] = tuple(OUTPUTS),
) -> Path:
    """Write ``model`` (frames (N, H, W) -> ``outputs``, by default coefficients and centre) as a single
    self-contained .onnx file.

    ``dtype`` is the stored pixel type the graph takes; uint16 also serves uint8 recordings, whose
    frames the runtime widens losslessly.
    """
    if dtype not in INPUT_DTYPES:
        raise ValueError(f"input dtype {dtype!r} is not one of {sorted(INPUT_DTYPES)}")
    model = model.eval()
    buffer = io.BytesIO()
    dynamic = {name: {0: "batch"} for name in (_FLOAT_INPUT, *outputs)}
    with warnings.catch_warnings():  # the TorchScript exporter announces its deprecation (module docstring)
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.onnx.export(
            model,
            (torch.zeros(2, height, width),),
            buffer,
            dynamo=False,
            input_names=[_FLOAT_INPUT],
            output_names=list(outputs),
            dynamic_axes=dynamic,
            opset_version=OPSET,
        )
    proto = onnx.load_from_string(buffer.getvalue())
    _cast_input(proto, INPUT_DTYPES[dtype])
    onnx.checker.check_model(proto, full_check=True)
    path = Path(path)
    onnx.save_model(proto, str(path), save_as_external_data=False)
    return path


def _cast_input(proto: onnx.ModelProto, elem_type: int) -> None:
    """Make the graph take stored pixels: a new input ``frames`` of ``elem_type``, cast to the float32 one."""
    graph = proto.graph
    (inp,) = graph.input
    inp.name = INPUT
    inp.type.tensor_type.elem_type = elem_type
    graph.node.insert(0, helper.make_node("Cast", [INPUT], [_FLOAT_INPUT], to=TensorProto.FLOAT, name="cast_frames"))


def expose_latent(path: Path, head_weight: str = "head.mlp.0.weight") -> Path:
    """Add the latent regressor's encoder mean (the input of its head's first layer, named by that layer's
    ``head_weight``) to the graph at ``path`` as the output :data:`LATENT` (N, latent), in place: the window model
    reads it, and the per-frame pass has already computed it. The other outputs and weights stay as they were."""
    proto = onnx.load(str(path))
    graph = proto.graph
    if any(o.name == LATENT for o in graph.output):
        return Path(path)
    heads = [n for n in graph.node if n.op_type == "Gemm" and n.input[1] == head_weight]
    if len(heads) != 1:
        raise ValueError(f"{path}: no single Gemm reads {head_weight!r}: not a latent regressor's graph")
    (weight,) = (w for w in graph.initializer if w.name == head_weight)
    transposed = {a.name: a.i for a in heads[0].attribute}.get("transB", 0)
    size = weight.dims[1] if transposed else weight.dims[0]
    graph.node.append(helper.make_node("Identity", [heads[0].input[0]], [LATENT], name="latent_output"))
    graph.output.append(helper.make_tensor_value_info(LATENT, TensorProto.FLOAT, ["batch", size]))
    onnx.checker.check_model(proto, full_check=True)
    onnx.save_model(proto, str(path), save_as_external_data=False)
    return Path(path)


def parity(model: nn.Module, path: Path, frames: np.ndarray, outputs: tuple[str, ...] = tuple(OUTPUTS)) -> float:
    """Largest absolute difference between torch and onnxruntime over all outputs (in their units)."""
    with torch.no_grad():
        expected = [t.numpy() for t in model.eval()(torch.from_numpy(frames))]
    got = onnx_outputs(path, frames, outputs)
    return float(max(np.abs(e - g).max(initial=0.0) for e, g in zip(expected, got)))
