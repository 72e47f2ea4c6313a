"""Common interface of every SR network."""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["SRModel"]


class SRModel(nn.Module):
    """Base class: a single-band SR network with an integer scale.

    Subclasses implement :meth:`forward` and :attr:`halo`.

    Conventions
    -----------
    ``forward(x)`` takes ``(N, 1, h, w)`` float32 images normalised to about
    [0, 1] and returns ``(N, 1, h * scale, w * scale)``. Output pixel
    ``[i, j]`` covers input area ``[i / scale, (i + 1) / scale)`` (corner
    convention, same as :meth:`tiledsm.geometry.RPC.scaled`).

    Attributes
    ----------
    scale : int
        Upscaling factor (2, 3, 4, ...).
    takes_degradation : bool
        Whether ``forward`` accepts ``blur_sigma`` and ``noise`` (SRMD).
    """

    takes_degradation = False

    def __init__(self, scale: int) -> None:
        super().__init__()
        if int(scale) != scale or scale < 1:
            raise ValueError(f"{type(self).__name__}: scale must be a positive integer, got {scale!r}")
        self.scale = int(scale)

    @property
    def halo(self) -> int:
        """Input (LR) pixels of context needed on each side of a tile so that
        the tile's output equals the whole-image output exactly (the
        receptive-field radius, including the border effects of padding)."""
        raise NotImplementedError

    def extra_repr(self) -> str:
        return f"scale={self.scale}, halo={self.halo}"

    @torch.no_grad()
    def predict(self, x: torch.Tensor, **degradation) -> torch.Tensor:
        """``forward`` without gradients, in eval mode."""
        self.eval()
        return self(x, **degradation) if degradation else self(x)
