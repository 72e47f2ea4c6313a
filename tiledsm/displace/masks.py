"""Why a displacement cell is NaN (pure numpy).

The correlation refuses a cell rather than guess (:mod:`tiledsm.displace.
correlate`: a phase-correlation peak under ``min_peak``, a phase coherence
under ``min_quality``, a residual past half a pixel, a window short of
data or of texture); this names the reason per cell, so that a user tells
a changed surface (a new building, a cloud, a moved shadow: decorrelated)
from ground nobody imaged (no data). Nothing is interpolated.
"""

from __future__ import annotations

import numpy as np

__all__ = ["STATUS", "cell_status"]

#: status codes of the ``status`` layer
STATUS = {"measured": 0, "no_data": 1, "no_texture": 2, "decorrelated": 3}


def cell_status(field, pre: np.ndarray, post: np.ndarray, step: int, min_texture: float) -> np.ndarray:
    """Why each cell is NaN (:data:`STATUS`): no data where a tenth of its
    ``step x step`` pixels lack PRE or POST, no texture where the PRE
    window's std is under ``min_texture``, decorrelated otherwise."""
    ny, nx = field["dE"].shape
    gone = (~np.isfinite(pre[: ny * step, : nx * step]) | ~np.isfinite(post[: ny * step, : nx * step]))
    share = gone.reshape(ny, step, nx, step).mean(axis=(1, 3))
    st = np.full((ny, nx), STATUS["decorrelated"], np.uint8)
    st[np.asarray(field["texture"]) < min_texture] = STATUS["no_texture"]
    st[share > 0.1] = STATUS["no_data"]
    st[np.isfinite(field["dE"]) & np.isfinite(field["dN"])] = STATUS["measured"]
    return st
