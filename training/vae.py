"""The convolutional variational autoencoder of Price et al. (2022), Sec. 3.2 (b), "learned inverse".

Trained on unlabeled lab frames only, so that its 10-dimensional latent space describes what the
real camera sees; the regressor (``training.regressor``) then maps that space to Eq. 1's
coefficients using renders passed through the frozen encoder. Inputs are the standardised images
of ``training.normalise.Normalise``, shape (N, 1, h, w).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from training.normalise import Normalise


@dataclass(frozen=True)
class NetConfig:
    """Sizes of the networks; ``input_px`` is the model input height after in-graph pooling."""

    input_px: int = 32
    #: one stride-2 3x3 conv per entry; (16, 32, 64) before 2026-11-29: no more accurate through the analysis, a
    #: dearer graph per frame (docs/benchmarks.md, "A narrower trunk")
    channels: tuple[int, ...] = (8, 16, 32)
    latent: int = 10  # Price et al. (2022): 10 latent dimensions
    hidden: int = 64  # width of the regression heads


def trunk_shape(channels: tuple[int, ...], h: int, w: int) -> tuple[int, int, int]:
    """(C, h', w') after the stride-2 convolutions of :class:`ConvTrunk` on an (h, w) input."""
    for _ in channels:
        h, w = (h + 1) // 2, (w + 1) // 2
    return channels[-1], h, w


class ConvTrunk(nn.Module):
    """(N, 1, h, w) -> (N, C*h'*w'): stride-2 3x3 convolutions with ReLU, then flattened.

    Shared by the VAE encoder and the direct CNN (``training.direct``), so that the two inverse
    methods differ in how they are trained, not in capacity or speed.
    """

    def __init__(self, channels: tuple[int, ...]) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        c_in = 1
        for c_out in channels:
            layers += [nn.Conv2d(c_in, c_out, 3, stride=2, padding=1), nn.ReLU()]
            c_in = c_out
        self.convs = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.convs(x).flatten(1)  # (N, C*h'*w')


class Encoder(nn.Module):
    """(N, 1, h, w) -> mean and log-variance of q(z | x), each (N, latent)."""

    def __init__(self, config: NetConfig, h: int, w: int) -> None:
        super().__init__()
        c, hh, ww = trunk_shape(config.channels, h, w)
        self.trunk = ConvTrunk(config.channels)
        self.moments = nn.Linear(c * hh * ww, 2 * config.latent)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mu, logvar = self.moments(self.trunk(x)).chunk(2, dim=1)  # (N, latent) each
        return mu, logvar


class Decoder(nn.Module):
    """(N, latent) -> (N, 1, h, w): the encoder mirrored with stride-2 transposed convolutions."""

    def __init__(self, config: NetConfig, h: int, w: int) -> None:
        super().__init__()
        self.h, self.w = h, w
        self.start = trunk_shape(config.channels, h, w)  # (C, h', w')
        self.expand = nn.Linear(config.latent, self.start[0] * self.start[1] * self.start[2])
        layers: list[nn.Module] = []
        widths = list(reversed(config.channels)) + [1]
        for i, (c_in, c_out) in enumerate(zip(widths[:-1], widths[1:])):
            layers.append(nn.ConvTranspose2d(c_in, c_out, 4, stride=2, padding=1))  # doubles h and w
            if i < len(widths) - 2:
                layers.append(nn.ReLU())
        self.deconvs = nn.Sequential(*layers)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        x = F.relu(self.expand(z)).view(-1, *self.start)  # (N, C, h', w')
        x = self.deconvs(x)  # (N, 1, h' * 2^k, w' * 2^k), at least (h, w)
        return x[:, :, : self.h, : self.w]  # (N, 1, h, w)


class VAE(nn.Module):
    """Encoder, reparameterised sample, decoder (Kingma and Welling, 2014)."""

    def __init__(self, config: NetConfig, h: int, w: int) -> None:
        super().__init__()
        self.config = config
        self.encoder = Encoder(config, h, w)
        self.decoder = Decoder(config, h, w)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Reconstruction (N, 1, h, w) of a sample from q(z | x), and its mean and log-variance (N, latent)."""
        mu, logvar = self.encoder(x)
        z = mu + torch.randn_like(mu) * torch.exp(0.5 * logvar)  # (N, latent)
        return self.decoder(z), mu, logvar


def vae_loss(
    x: torch.Tensor, recon: torch.Tensor, mu: torch.Tensor, logvar: torch.Tensor, beta: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Negative ELBO per frame (unit-variance Gaussian likelihood) and its KL part, batch means.

    ``beta`` weighs the KL divergence to N(0, I) (beta = 1: the plain VAE).
    """
    recon_term = 0.5 * (recon - x).pow(2).flatten(1).sum(1)  # (N,)
    kl = -0.5 * (1 + logvar - mu.pow(2) - logvar.exp()).sum(1)  # (N,)
    return (recon_term + beta * kl).mean(), kl.mean()


class Reconstruction(nn.Module):
    """Stored frames (N, H, W) -> the VAE's input (N, 1, h, w) and its reconstruction from the posterior mean.

    Exported beside the inverse graphs (``autoencoder.onnx``) so that ``meniscope validate`` can show
    lab frames next to their reconstructions (Price et al. 2022, Fig. 13) without torch.
    """

    def __init__(self, normalise: Normalise, vae: VAE) -> None:
        super().__init__()
        self.normalise = normalise
        self.vae = vae

    def forward(self, frames: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = self.normalise(frames)  # (N, 1, h, w)
        mu, _ = self.vae.encoder(x)  # (N, latent): no sampling
        return x, self.vae.decoder(mu)
