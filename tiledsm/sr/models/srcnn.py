"""SRCNN, the 9-1-5 network of Dong et al. (2014), "Learning a deep
convolutional network for image super-resolution", ECCV,
doi:10.1007/978-3-319-10593-2_13."""

from __future__ import annotations

import math

import torch
from torch import nn

from tiledsm.sr.models._layers import BICUBIC_RADIUS, PaddedConv2d, bicubic_upsample, conv_radius
from tiledsm.sr.models.base import SRModel

__all__ = ["SRCNN"]


class SRCNN(SRModel):
    """Bicubic pre-upsampling followed by three convolutions (9x9, 1x1, 5x5)
    with ReLU after the first two; padding before each (symmetric, as the
    method states, unless ``padding`` says otherwise).

    Parameters
    ----------
    scale : int
        Upscaling factor.
    features : tuple of int
        Channels of the first two layers (paper: 64, 32).
    kernels : tuple of int
        Kernel sizes (paper: 9, 1, 5).
    residual : bool
        Add the bicubic image to the output (global skip, as in VDSR). The
        paper has none (``False``); with it the network learns only the
        missing detail and converges in far fewer steps.
    """

    def __init__(self, scale: int = 2, features: tuple[int, int] = (64, 32), kernels: tuple[int, int, int] = (9, 1, 5), residual: bool = False, padding: str = "symmetric") -> None:
        super().__init__(scale)
        f1, f2 = features
        k1, k2, k3 = kernels
        self.residual = bool(residual)
        self.body = nn.Sequential(
            PaddedConv2d(1, f1, k1, pad_mode=padding), nn.ReLU(inplace=True),
            PaddedConv2d(f1, f2, k2, pad_mode=padding), nn.ReLU(inplace=True),
            PaddedConv2d(f2, 1, k3, pad_mode=padding),
        )

    @property
    def halo(self) -> int:
        # bicubic edge effect (<= 2 LR px) + conv radius in HR px, in LR px
        return BICUBIC_RADIUS + math.ceil(conv_radius(self.body) / self.scale)

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # noqa: D102
        up = bicubic_upsample(x, self.scale)
        return up + self.body(up) if self.residual else self.body(up)
