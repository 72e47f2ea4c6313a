"""Building blocks shared by the SR networks.

Conventions
-----------
- Tensors are ``(N, C, H, W)``, float32, values normalised to about [0, 1]
  (image digital numbers divided by the sensor's full scale).
- Every convolution is preceded by explicit padding of ``k // 2`` pixels
  and runs with ``padding=0``, so a layer keeps the spatial size. Three
  modes (:data:`PAD_MODES`):

  - ``"symmetric"`` (the method's): mirror including the edge pixel,
    ``[a b c] -> [b a | a b c | c b]`` (numpy ``mode="symmetric"``,
    MATLAB ``padarray(..., "symmetric")``);
  - ``"reflect"``: mirror about the edge pixel, ``[c b | a b c | b a]``
    (the shipped networks trained before symmetric padding existed here);
  - ``"zeros"``: the published SRMD weights were trained with it.

  Inside a tiled image the halo hides the difference; only the image's own
  border sees it.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["PaddedConv2d", "PAD_MODES", "symmetric_pad", "bicubic_upsample", "conv_radius", "BICUBIC_RADIUS"]

#: support radius (input pixels) of the bicubic kernel on either side
BICUBIC_RADIUS = 2


#: padding modes of :class:`PaddedConv2d`
PAD_MODES = ("symmetric", "reflect", "zeros")


def symmetric_pad(x: torch.Tensor, pad: int) -> torch.Tensor:
    """Pad the last two dims of ``x`` by ``pad`` pixels on each side,
    mirroring about the image edge *including* the edge pixel (numpy's
    ``"symmetric"``). Needs ``pad <= min(H, W)``."""
    h, w = x.shape[-2:]
    if pad > min(h, w):
        raise ValueError(f"symmetric_pad: pad {pad} exceeds the image size {h} x {w}")
    if pad == 1:  # the 3 x 3 layers: one mirrored pixel is the edge pixel repeated (torch's fast path)
        return F.pad(x, (1, 1, 1, 1), mode="replicate")
    # one allocation, the image copied once, the borders as flipped slices (the columns taken from the
    # already padded rows, so the corners come with them): a reflect pad's time, where two torch.cat took
    # 2x and gathering by index 5x
    out = x.new_empty(*x.shape[:-2], h + 2 * pad, w + 2 * pad)
    out[..., pad : pad + h, pad : pad + w] = x
    out[..., :pad, pad : pad + w] = x[..., :pad, :].flip(-2)
    out[..., pad + h :, pad : pad + w] = x[..., h - pad :, :].flip(-2)
    out[..., :pad] = out[..., pad : 2 * pad].flip(-1)
    out[..., pad + w :] = out[..., w : w + pad].flip(-1)
    return out


class PaddedConv2d(nn.Conv2d):
    """``nn.Conv2d`` (odd square kernel, stride 1) with explicit padding before it.

    Parameters
    ----------
    in_channels, out_channels : int
        Channel counts.
    kernel_size : int
        Odd kernel size ``k``; the layer pads ``k // 2`` pixels on each side.
    bias : bool
        Learn a bias.
    pad_mode : str
        One of :data:`PAD_MODES` (see the module notes).
    """

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int, bias: bool = True, pad_mode: str = "symmetric") -> None:
        if kernel_size % 2 != 1:
            raise ValueError(f"PaddedConv2d: kernel_size must be odd, got {kernel_size}")
        if pad_mode not in PAD_MODES:
            raise ValueError(f"PaddedConv2d: pad_mode must be one of {PAD_MODES}, got {pad_mode!r}")
        super().__init__(in_channels, out_channels, kernel_size, padding=0, bias=bias)
        self.pad = kernel_size // 2
        self.pad_mode = pad_mode

    @property
    def radius(self) -> int:
        """Receptive-field growth of this layer, in pixels on each side."""
        return self.pad

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # noqa: D102
        if self.pad:
            if self.pad_mode == "symmetric":
                x = symmetric_pad(x, self.pad)
            elif self.pad_mode == "reflect":
                x = F.pad(x, (self.pad,) * 4, mode="reflect")
            else:
                x = F.pad(x, (self.pad,) * 4, mode="constant", value=0.0)
        return super().forward(x)


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
    """Sum of the radii of all :class:`PaddedConv2d` layers in ``module``.

    This is the receptive-field radius (in the layers' own pixel grid) of a
    plain chain of convolutions; it is also the depth up to which the
    padding at a tile edge can change the output.
    """
    return sum(m.radius for m in module.modules() if isinstance(m, PaddedConv2d))
