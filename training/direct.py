"""The direct CNN: the baseline Price et al. (2022, Sec. 3.2) argued against, trained end to end on renders.

Same normalisation, convolutional trunk and head sizes as the latent regressor, but no lab frames:
it learns the renderer's images, so any gap between renders and the real camera lands in its
predictions. Kept as the ``direct`` inverse method so the two can be compared on the same data.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from training.normalise import Normalise
from training.regressor import Head, split_outputs
from training.vae import ConvTrunk, NetConfig, trunk_shape


class DirectCNN(nn.Module):
    """Stored frames (N, H, W) -> coefficients (N, 4), centre (N,): normalise, conv trunk, head."""

    def __init__(
        self, config: NetConfig, normalise: Normalise, h: int, w: int, target_mean: np.ndarray, target_std: np.ndarray
    ) -> None:
        super().__init__()
        c, hh, ww = trunk_shape(config.channels, h, w)
        self.normalise = normalise
        self.trunk = ConvTrunk(config.channels)
        self.head = Head(c * hh * ww, config.hidden, target_mean, target_std)

    def predict(self, x: torch.Tensor) -> torch.Tensor:
        """Normalised images (N, 1, h, w) -> targets (N, 5) in physical units (what training calls)."""
        return self.head(self.trunk(x))

    def forward(self, frames: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return split_outputs(self.predict(self.normalise(frames)))
