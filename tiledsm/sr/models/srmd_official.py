"""The published SRMD weights' network (Zhang, Zuo & Zhang 2018,
"Learning a single convolutional super-resolution network for multiple
degradations", CVPR, doi:10.1109/CVPR.2018.00344), for weights converted by
:mod:`tiledsm.sr.ncnn`.

Twelve 3x3 convolutions on the LR grid with zero padding, bias and a ReLU
after each but the last, 128 channels, pixel shuffle: the paper's network
as its authors trained it (no batch normalisation left at inference: it is
folded into the convolutions). The input is the LR image plus constant
maps: the 15-dimensional PCA code of the degradation's blur kernel and,
for the ``SRMD`` weights (not ``SRMDNF``, "noise-free"), the noise level.
The authors' PCA basis is not published with the converted weights, only
the code of one kernel, the bicubic downsampling kernel (carried in the
weights as the buffer ``code``): these weights super-resolve bicubic-
degraded images, and the blur cannot be chosen (compare :class:`SRMD`,
whose basis is ours and whose blur is a parameter).
"""

from __future__ import annotations

import torch
from torch import nn

from tiledsm.sr.models._layers import PaddedConv2d, conv_radius
from tiledsm.sr.models.base import SRModel

__all__ = ["OfficialSRMD", "PCA_DIM"]

#: dimension of the published kernel code
PCA_DIM = 15


class OfficialSRMD(SRModel):
    """The network of the published SRMD weights, single band.

    Parameters
    ----------
    scale : int
        Upscaling factor (the published weights: 2, 3, 4).
    noise_level : float or None
        Noise standard deviation of the LR image in 8-bit DN (0-255; the
        published range is 0-75), given to the network as the constant map
        ``noise_level / 255``; ``None`` for the noise-free weights
        (``SRMDNF``), which take no noise map.
    layers, features : int
        Convolutions and hidden channels (published: 12, 128).

    Notes
    -----
    Input and output are normalised to [0, 1] (the weights were trained on
    8-bit images divided by 255; any bit depth divided by its full scale
    gives the same range). ``forward(x)`` takes no degradation: the kernel
    code is the stored ``code`` buffer.
    """

    def __init__(self, scale: int = 2, noise_level: float | None = None, layers: int = 12, features: int = 128) -> None:
        super().__init__(scale)
        if layers < 2:
            raise ValueError(f"OfficialSRMD: layers must be >= 2, got {layers}")
        if noise_level is not None and not 0 <= float(noise_level) <= 255:
            raise ValueError(f"OfficialSRMD: noise_level must be in [0, 255] DN or None, got {noise_level}")
        self.noise_level = None if noise_level is None else float(noise_level)
        maps = PCA_DIM + (0 if noise_level is None else 1)
        self.register_buffer("code", torch.zeros(PCA_DIM))
        mods: list[nn.Module] = [PaddedConv2d(1 + maps, features, 3, pad_mode="zeros"), nn.ReLU(inplace=True)]
        for _ in range(layers - 2):
            mods += [PaddedConv2d(features, features, 3, pad_mode="zeros"), nn.ReLU(inplace=True)]
        mods += [PaddedConv2d(features, self.scale**2, 3, pad_mode="zeros"), nn.PixelShuffle(self.scale)]
        self.body = nn.Sequential(*mods)

    @property
    def halo(self) -> int:
        return conv_radius(self.body)

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # noqa: D102
        n, _, h, w = x.shape
        values = self.code if self.noise_level is None else torch.cat(
            [self.code, torch.tensor([self.noise_level / 255.0], dtype=self.code.dtype, device=self.code.device)])
        maps = values.to(x.dtype)[None, :, None, None].expand(n, values.numel(), h, w)
        return self.body(torch.cat([x, maps], dim=1))
