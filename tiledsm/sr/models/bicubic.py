"""Bicubic interpolation as an SR "model": the reference every CNN must beat."""

from __future__ import annotations

import torch

from tiledsm.sr.models._layers import BICUBIC_RADIUS, bicubic_upsample
from tiledsm.sr.models.base import SRModel

__all__ = ["Bicubic"]


class Bicubic(SRModel):
    """Bicubic upsampling (Keys, a = -0.75), identical to OpenCV
    ``cv2.resize(..., interpolation=cv2.INTER_CUBIC)`` and to
    ``torch.nn.functional.interpolate(mode="bicubic", align_corners=False)``.
    No weights."""

    def __init__(self, scale: int = 2) -> None:
        super().__init__(scale)

    @property
    def halo(self) -> int:
        return BICUBIC_RADIUS

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # noqa: D102
        return bicubic_upsample(x, self.scale)
