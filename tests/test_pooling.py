"""The graphs' input pooling outside onnxruntime: the same block means, and the same outputs as the whole graph."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
from hypothesis import given, settings
from hypothesis import strategies as st
from onnx import TensorProto, helper

from service import DEFAULT_MODELS, DEFAULT_SCENE
from service.inverse import pooling
from service.inverse.manifest import INPUT, OUTPUTS, load_manifest
from service.inverse.network import NetworkMethod
from service.scene import Scene


@settings(max_examples=40, deadline=None)
@given(
    dtype=st.sampled_from([np.uint8, np.uint16]),
    factor=st.integers(1, 4),
    blocks=st.tuples(st.integers(1, 5), st.integers(1, 5)),
    full=st.booleans(),
    seed=st.integers(0, 2**16),
)
def test_block_means_are_the_float64_means_rounded_once(dtype, factor, blocks, full, seed) -> None:
    """Full-scale and random pixels of either stored type: each block's exact mean, rounded once to float32."""
    shape = (3, blocks[0] * factor, blocks[1] * factor)
    top = np.iinfo(dtype).max
    frames = np.full(shape, top, dtype) if full else np.random.default_rng(seed).integers(0, top, shape, dtype)
    want = frames.reshape(3, blocks[0], factor, blocks[1], factor).mean(axis=(2, 4), dtype=np.float64)
    assert np.array_equal(pooling.block_means(frames, factor)[:, 0], want.astype(np.float32))


@settings(max_examples=40, deadline=None)
@given(
    dtype=st.sampled_from([np.uint8, np.uint16]),
    fill=st.sampled_from(["max", "zero", "random", "one bright pixel"]),
    seed=st.integers(0, 2**16),
)
def test_standardised_means_are_the_exported_normalisation(dtype, fill, seed) -> None:
    """Block means then :func:`pooling.standardise` give what torch's ``Normalise`` (the layers every graph is
    exported with) gives the same frames, flat frames and a lone highlight included."""
    import torch

    from training.normalise import Normalise

    top = np.iinfo(dtype).max
    shape = (4, 96, 96)
    frames = np.random.default_rng(seed).integers(0, top, shape, dtype, endpoint=True)
    if fill != "random":
        frames = np.full(shape, top if fill == "max" else 0, dtype)
    if fill == "one bright pixel":
        frames[:, 40, 51] = top
    want = Normalise(3)(torch.from_numpy(frames.astype(np.int32))).numpy()
    np.testing.assert_allclose(pooling.standardise(pooling.block_means(frames, 3)), want, rtol=1e-5, atol=1e-4)


def test_the_shipped_graphs_run_from_their_normalisation_with_the_whole_graphs_outputs() -> None:
    """Both shipped methods start with the pooling and the normalisation, which the split graphs take as input, and
    their outputs on recorded-like frames, 12-bit and 8-bit (pooled as they come, not widened first), are the whole
    graph's."""
    manifest = load_manifest(DEFAULT_MODELS, Scene.load(DEFAULT_SCENE))
    rng = np.random.default_rng(1)
    twelve_bit = rng.integers(0, 4096, (100, 96, 96)).astype(np.uint16)
    eight_bit = rng.integers(0, 256, (100, 96, 96)).astype(np.uint8)
    for name, entry in manifest.methods.items():
        method = NetworkMethod(DEFAULT_MODELS, Scene.load(DEFAULT_SCENE), name, threads=1, batch=32)
        assert method.pooling == manifest.input.downsample and method.standardised  # the split was taken
        whole = ort.InferenceSession(str(DEFAULT_MODELS / entry.file), providers=["CPUExecutionProvider"])
        for frames in (twelve_bit, eight_bit):
            coefficients, centre = whole.run(list(OUTPUTS), {INPUT: frames.astype(np.uint16)})
            out = method.infer(frames)
            np.testing.assert_allclose(out.coefficients, coefficients, atol=pooling.PARITY_ABS)
            np.testing.assert_allclose(out.centre, centre, atol=pooling.PARITY_ABS)


def test_a_graph_that_does_not_start_with_the_pooling_is_left_whole(tmp_path: Path) -> None:
    """A graph without the exported input layers (here: max pooling) is not split."""
    x = helper.make_tensor_value_info(INPUT, TensorProto.UINT16, [None, 6, 6])
    y = helper.make_tensor_value_info("y", TensorProto.FLOAT, [None, 1, 2, 2])
    axis = helper.make_tensor("axis", TensorProto.INT64, [1], [1])
    nodes = [
        helper.make_node("Cast", [INPUT], ["a"], to=TensorProto.FLOAT),
        helper.make_node("Cast", ["a"], ["b"], to=TensorProto.FLOAT),
        helper.make_node("Unsqueeze", ["b", "axis"], ["c"]),
        helper.make_node("MaxPool", ["c"], ["y"], kernel_shape=[3, 3], strides=[3, 3]),
    ]
    graph = helper.make_graph(nodes, "g", [x], [y], initializer=[axis])
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]), tmp_path / "g.onnx")
    assert pooling.after_pooling(tmp_path / "g.onnx", INPUT, 3) is None


def test_a_graph_whose_normalisation_is_not_the_exported_one_runs_from_its_pooling(tmp_path: Path) -> None:
    """The shipped graph with its normalisation's nodes renamed (not the layers ``standardise`` reproduces): the split
    after the normalisation is refused, the one after the pooling still taken."""
    model = onnx.load(str(DEFAULT_MODELS / "network.onnx"))
    for node in model.graph.node:
        node.name = node.name.replace(pooling.NORMALISATION, "/other/")
    onnx.save(model, tmp_path / "renamed.onnx")
    assert pooling.after_pooling(tmp_path / "renamed.onnx", INPUT, 3, standardised=True) is None
    assert pooling.after_pooling(tmp_path / "renamed.onnx", INPUT, 3) is not None
