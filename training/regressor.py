"""The regressor of Price et al. (2022), Sec. 3.2 (b): VAE latent -> Eq. 1 coefficients and D(0, t).

Trained on synthetic renders through the frozen encoder of ``training.vae``; the whole chain,
from stored pixels to millimetres, is one module (:class:`LatentRegressor`) that
``training.export`` writes as one ONNX graph.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from service.validation.truth import TARGETS
from training.normalise import Normalise
from training.vae import Encoder


def targets(coefficients: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """(N, 5) float32 of coefficients (N, 4) and centre displacement (N,), columns :data:`TARGETS`."""
    return np.concatenate([coefficients, centre[:, None]], axis=1).astype(np.float32)


class Head(nn.Module):
    """(N, features) -> (N, 5) in physical units: a two-layer MLP on standardised targets.

    The targets' training-set mean and standard deviation are buffers, so the exported graph
    outputs millimetres directly; D(0, t) is predicted in its own right (not summed from d, p, a, b)
    because it is what the window analysis follows and the best-constrained quantity in a frame.
    """

    def __init__(self, features: int, hidden: int, target_mean: np.ndarray, target_std: np.ndarray) -> None:
        super().__init__()
        self.mlp = nn.Sequential(
            nn.Linear(features, hidden),
            nn.ReLU(),
            nn.Linear(hidden, hidden),
            nn.ReLU(),
            nn.Linear(hidden, len(TARGETS)),
        )
        self.register_buffer("mean", torch.as_tensor(target_mean, dtype=torch.float32).reshape(len(TARGETS)))
        self.register_buffer("std", torch.as_tensor(target_std, dtype=torch.float32).reshape(len(TARGETS)))

    def standardise(self, y: torch.Tensor) -> torch.Tensor:
        """Targets (N, 5) in physical units -> the unit-variance scale the loss is taken on."""
        return (y - self.mean) / self.std

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return self.mlp(features) * self.std + self.mean  # (N, 5)


def split_outputs(y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, 5) -> coefficients (N, 4) and centre (N,): the two outputs of every exported graph."""
    return y[:, :4], y[:, 4]


class LatentRegressor(nn.Module):
    """Stored frames (N, H, W) -> coefficients (N, 4), centre (N,): normalise, encoder mean, head."""

    def __init__(self, normalise: Normalise, encoder: Encoder, head: Head) -> None:
        super().__init__()
        self.normalise = normalise
        self.encoder = encoder
        self.head = head

    def forward(self, frames: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mu, _ = self.encoder(self.normalise(frames))  # (N, latent): the posterior mean, no sampling
        return split_outputs(self.head(mu))
