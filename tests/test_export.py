"""The per-frame network's latent as a graph output (``training.export.expose_latent``): the encoder mean its head
reads, added without touching what the graph computed before, so that the window model can take it per frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from service.inverse.manifest import LATENT, OUTPUTS
from service.inverse.network import onnx_outputs
from service.pipeline.records import LATENT_SIZE

torch = pytest.importorskip("torch", reason="exporting needs the train extra (torch)")

from training.export import export_onnx, expose_latent  # noqa: E402
from training.normalise import Normalise  # noqa: E402
from training.regressor import Head, LatentRegressor  # noqa: E402
from training.vae import Encoder, NetConfig  # noqa: E402


@pytest.fixture(scope="module")
def graphs(tmp_path_factory: pytest.TempPathFactory) -> tuple[LatentRegressor, Path, Path]:
    """An untrained latent regressor, its graph as exported and the same graph with the latent exposed."""
    torch.manual_seed(3)
    config = NetConfig()
    model = LatentRegressor(
        Normalise(3), Encoder(config, 32, 32), Head(config.latent, config.hidden, np.zeros(5), np.ones(5))
    ).eval()
    folder = tmp_path_factory.mktemp("export")
    plain = export_onnx(model, folder / "plain.onnx", 96, 96)
    exposed = export_onnx(model, folder / "network.onnx", 96, 96)
    assert expose_latent(exposed) == expose_latent(exposed)  # a second call finds it there and changes nothing
    return model, plain, exposed


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), peak=st.sampled_from([0, 1, 255, 4095, 65535]), frames=st.integers(1, 4))
def test_exposing_the_latent_keeps_every_output_bit_identical_and_adds_the_encoder_mean(
    graphs: tuple, seed: int, peak: int, frames: int
) -> None:
    """Any frames, flat black to full-scale 16-bit noise: coefficients and centre as before to the bit, the latent
    the torch encoder's posterior mean (float32 rounding only)."""
    model, plain, exposed = graphs
    x = np.random.default_rng(seed).integers(0, peak + 1, (frames, 96, 96)).astype(np.uint16)
    before = onnx_outputs(plain, x)
    after = onnx_outputs(exposed, x, (*OUTPUTS, LATENT))
    for old, new in zip(before, after):
        np.testing.assert_array_equal(old, new)
    with torch.no_grad():
        mu, _ = model.encoder(model.normalise(torch.from_numpy(x.astype(np.float32))))
    assert after[2].shape == (frames, LATENT_SIZE)
    np.testing.assert_allclose(after[2], mu.numpy(), rtol=1e-4, atol=1e-4)


def test_a_graph_without_a_regressor_head_is_refused_in_one_line(graphs: tuple, tmp_path: Path) -> None:
    _, plain, _ = graphs
    with pytest.raises(ValueError, match="no single Gemm reads 'head.nothing'"):
        expose_latent(plain, head_weight="head.nothing")
