"""Warm starts: the torch modules of a model folder, read back from its ONNX graphs, to fine-tune for another scene.

A model folder holds ONNX graphs only (no torch checkpoints), but the exporter keeps every weight as a named
initializer (``vae.encoder.trunk.convs.0.weight``, ``head.mlp.0.bias``, ...), so the VAE (from
``autoencoder.onnx``), the regressor head (from ``network.onnx``) and the direct CNN (from ``direct.onnx``) load
back exactly. ``meniscope train --init MODELS`` starts from them: a calibrated scene differs from the one MODELS
were made for in its materials and light, not in what a frame can show, so a few epochs on the new scene's frames
move the weights where a full run would take them (docs/calibration.md, "New camera").
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx
import torch
from onnx import numpy_helper
from pydantic import ValidationError

from service.errors import MeniscopeError
from service.inverse.manifest import MANIFEST, Manifest, sha256_file
from training.direct import DirectCNN
from training.normalise import Normalise
from training.regressor import Head
from training.vae import VAE, NetConfig


@dataclass(frozen=True)
class WarmStart:
    """The modules of a model folder, ready to train further: the VAE, the regressor head, the direct CNN."""

    folder: Path
    vae: VAE
    head: Head
    direct: DirectCNN


def read_init_manifest(folder: Path) -> Manifest:
    """A model folder's manifest, its files checked against their sha256, for any scene (the point of a warm start
    is a scene other than the one it was trained for)."""
    path = folder / MANIFEST
    if not path.is_file():
        raise MeniscopeError(folder, "not a model folder: no manifest.json (`meniscope train` makes one)")
    try:
        manifest = Manifest.model_validate_json(path.read_text())
    except ValidationError as exc:
        err = exc.errors()[0]
        raise MeniscopeError(path, f"invalid manifest: {'.'.join(map(str, err['loc']))}: {err['msg']}") from None
    if manifest.autoencoder is None or "direct" not in manifest.methods or "network" not in manifest.methods:
        raise MeniscopeError(folder, "a warm start needs the network, direct and autoencoder graphs; one is missing")
    for name, expected in manifest.files.items():
        if not (folder / name).is_file() or sha256_file(folder / name) != expected:
            raise MeniscopeError(folder / name, f"missing or changed since {MANIFEST} was written")
    return manifest


def initializers(path: Path, prefix: str = "") -> dict[str, torch.Tensor]:
    """The named weights of an ONNX graph whose names start with ``prefix``, that prefix cut off."""
    graph = onnx.load(str(path)).graph
    return {
        init.name[len(prefix) :]: torch.from_numpy(np.array(numpy_helper.to_array(init)))
        for init in graph.initializer
        if init.name.startswith(prefix)
    }


def net_of(folder: Path) -> NetConfig:
    """The network sizes a model folder's graphs were trained with: a fine-tuning of them keeps them."""
    return _net_config(read_init_manifest(folder))


def _net_config(manifest: Manifest) -> NetConfig:
    """The :class:`NetConfig` stored in a manifest's training record."""
    config = manifest.training.config.get("net", {})
    return NetConfig(**{**config, "channels": tuple(config.get("channels", ()))})


def load_warm_start(folder: Path, net: NetConfig, normalise: Normalise, height: int, width: int) -> WarmStart:
    """The torch modules of ``folder``'s graphs, for frames of ``height`` x ``width`` through ``normalise``.

    Refused in one line when the folder's networks have another shape (sizes, model input) than ``net``.
    """
    manifest = read_init_manifest(folder)
    made = _net_config(manifest)
    shape = (manifest.input.height, manifest.input.width, manifest.input.downsample)
    if made != net or shape != (height, width, normalise.factor):
        raise MeniscopeError(
            folder,
            f"its networks ({made}, {shape[0]}x{shape[1]} px pooled {shape[2]}x) differ from this run's "
            f"({net}, {height}x{width} px pooled {normalise.factor}x): warm starts need the same shapes",
        )
    h, w = height // normalise.factor, width // normalise.factor
    vae = VAE(net, h, w)
    head = Head(net.latent, net.hidden, np.zeros(5), np.ones(5))
    direct = DirectCNN(net, normalise, h, w, np.zeros(5), np.ones(5))
    for module, graph, prefix in (
        (vae, manifest.autoencoder.file, "vae."),
        (head, manifest.methods["network"].file, "head."),
        (direct, manifest.methods["direct"].file, ""),
    ):
        try:
            module.load_state_dict(initializers(folder / graph, prefix), strict=True)
        except RuntimeError as exc:
            raise MeniscopeError(folder / graph, f"weights do not fit this run's network: {exc}") from None
    return WarmStart(folder, vae, head, direct)
