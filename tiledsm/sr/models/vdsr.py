"""VDSR of Kim, Lee & Lee (2016), "Accurate image super-resolution using
very deep convolutional networks", CVPR, doi:10.1109/CVPR.2016.182."""

from __future__ import annotations

import math

import torch
from torch import nn

from tiledsm.sr.models._layers import BICUBIC_RADIUS, PaddedConv2d, bicubic_upsample, conv_radius
from tiledsm.sr.models.base import SRModel

__all__ = ["VDSR"]


class VDSR(SRModel):
    """Bicubic pre-upsampling, ``depth`` 3x3 convolutions (``features``
    channels, ReLU between), and a global residual: output = bicubic +
    predicted residual. Padding before each convolution (symmetric, as the
    method states, unless ``padding`` says otherwise).

    The last layer starts at zero, so an untrained VDSR is exactly bicubic.

    Parameters
    ----------
    scale : int
        Upscaling factor.
    depth : int
        Number of convolution layers (paper: 20).
    features : int
        Channels of the hidden layers (paper: 64).
    padding : str
        Padding before each convolution, one of
        :data:`~tiledsm.sr.models._layers.PAD_MODES`.
    """

    def __init__(self, scale: int = 2, depth: int = 20, features: int = 64, padding: str = "symmetric") -> None:
        super().__init__(scale)
        if depth < 2:
            raise ValueError(f"VDSR: depth must be >= 2, got {depth}")
        layers: list[nn.Module] = [PaddedConv2d(1, features, 3, pad_mode=padding), nn.ReLU(inplace=True)]
        for _ in range(depth - 2):
            layers += [PaddedConv2d(features, features, 3, pad_mode=padding), nn.ReLU(inplace=True)]
        last = PaddedConv2d(features, 1, 3, pad_mode=padding)
        layers.append(last)
        self.body = nn.Sequential(*layers)
        for m in self.body.modules():
            if isinstance(m, PaddedConv2d):
                nn.init.kaiming_normal_(m.weight, nonlinearity="relu")
                nn.init.zeros_(m.bias)
        nn.init.zeros_(last.weight)

    @property
    def halo(self) -> int:
        return BICUBIC_RADIUS + math.ceil(conv_radius(self.body) / self.scale)

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # noqa: D102
        up = bicubic_upsample(x, self.scale)
        return up + self.body(up)
