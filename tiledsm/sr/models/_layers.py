"""Building blocks shared by the SR networks.

Conventions
-----------
- Tensors are ``(N, C, H, W)``, float32, values normalised to about [0, 1]
  (image digital numbers divided by the sensor's full scale).
- Every convolution is preceded by **reflect padding** of ``k // 2`` pixels
  and runs with ``padding=0``, so a layer keeps the spatial size and pixels
  near a tile border see mirrored real content instead of zeros. Reflect
  mode mirrors about the edge pixel (``[a b c] -> [c b | a b c | b a]``).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["ReflectConv2d", "ZeroPadConv2d", "bicubic_upsample", "conv_radius", "BICUBIC_RADIUS"]

#: support radius (input pixels) of the bicubic kernel on either side
BICUBIC_RADIUS = 2


class ReflectConv2d(nn.Conv2d):
    """``nn.Conv2d`` (odd square kernel, stride 1) with reflect padding before it.

    Parameters
    ----------
    in_channels, out_channels : int
        Channel counts.
    kernel_size : int
        Odd kernel size ``k``; the layer pads ``k // 2`` pixels on each side.
    """

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int, bias: bool = True) -> None:
        if kernel_size % 2 != 1:
            raise ValueError(f"ReflectConv2d: kernel_size must be odd, got {kernel_size}")
        super().__init__(in_channels, out_channels, kernel_size, padding=0, bias=bias)
        self.pad = kernel_size // 2

    @property
    def radius(self) -> int:
        """Receptive-field growth of this layer, in pixels on each side."""
        return self.pad

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # noqa: D102
        if self.pad:
            x = F.pad(x, (self.pad,) * 4, mode="reflect")
        return super().forward(x)


class ZeroPadConv2d(ReflectConv2d):
    """:class:`ReflectConv2d` padded with zeros instead: the padding of
    networks trained that way (the published SRMD weights, see
    :mod:`tiledsm.sr.ncnn`), so that they give the outputs they were
    trained to give. Inside a tiled image the halo hides the difference;
    only the image's own border sees it."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # noqa: D102
        if self.pad:
            x = F.pad(x, (self.pad,) * 4, mode="constant", value=0.0)
        return nn.Conv2d.forward(self, x)


def bicubic_upsample(x: torch.Tensor, scale: int) -> torch.Tensor:
    """Bicubic upsampling by an integer factor (Keys kernel, ``a = -0.75``).

    Same kernel, pixel mapping and border rule as OpenCV ``INTER_CUBIC``
    and ``torch.nn.functional.interpolate(mode="bicubic",
    align_corners=False)``: output pixel centre ``i + 0.5`` samples input
    position ``(i + 0.5) / scale - 0.5`` (pixel centres at integers), and
    indices outside the image are clamped to the edge (replicate border).
    Each output pixel depends on input pixels within :data:`BICUBIC_RADIUS`.
    """
    if scale == 1:
        return x
    return F.interpolate(x, scale_factor=scale, mode="bicubic", align_corners=False)


def conv_radius(module: nn.Module) -> int:
    """Sum of the radii of all :class:`ReflectConv2d` layers (and
    subclasses) in ``module``.

    This is the receptive-field radius (in the layers' own pixel grid) of a
    plain chain of convolutions; it is also the depth up to which the
    padding at a tile edge can change the output.
    """
    return sum(m.radius for m in module.modules() if isinstance(m, ReflectConv2d))
