"""Input normalisation of every learned inverse model: raw ROI pixels -> a small standardised image.

It lives inside the exported ONNX graphs (``training.export``) so that the runtime feeds frames
exactly as stored. scene.md ("Camera") says absolute exposure is not part of the contract; the
per-frame standardisation makes the models blind to gain and offset by construction.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from service.errors import MeniscopeError
from service.inverse.pooling import STD_FLOOR_DN
from service.scene import Scene


def downsample_factor(scene: Scene, input_px: int) -> int:
    """The integer pooling factor that brings the scene's ROI height to ``input_px`` rows.

    Raises MeniscopeError unless it divides both ROI sides exactly (no resampling inside the graph).
    """
    height, width = scene.camera.height_px, scene.camera.width_px
    if input_px < 1 or height % input_px or width % (height // input_px):
        raise MeniscopeError(
            "scene", f"model input size {input_px} px must divide the {width}x{height} ROI into whole pixels"
        )
    return height // input_px


class Normalise(nn.Module):
    """(N, H, W) frames of any numeric dtype -> (N, 1, H/f, W/f) float32, zero mean and unit std per frame.

    Average pooling by ``factor`` first (linear, so it commutes with gain and offset and keeps the
    energy of sub-pixel highlights), then ``(x - mean) / std`` over each pooled frame. Mean and
    standard deviation rather than median and MAD: most pixels of a frame are the same black
    nozzle face, where the MAD collapses to 0, and the ONNX exporter has no median.
    """

    def __init__(self, factor: int) -> None:
        super().__init__()
        self.factor = int(factor)

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        x = frames.to(torch.float32).unsqueeze(1)  # (N, 1, H, W)
        x = F.avg_pool2d(x, self.factor)  # (N, 1, H/f, W/f)
        mean = x.mean(dim=(1, 2, 3), keepdim=True)  # (N, 1, 1, 1)
        std = x.std(dim=(1, 2, 3), keepdim=True)  # (N, 1, 1, 1)
        return (x - mean) / (std + STD_FLOOR_DN)
