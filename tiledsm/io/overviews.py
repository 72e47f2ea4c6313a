"""COG overview levels averaged while a raster is streamed, as GDAL's ``COG``
driver would compute them.

GDAL's ``COG`` driver (``OVERVIEW_RESAMPLING=AVERAGE``) builds its overviews
from the written full-resolution source: it reads the whole grid again and
averages it level by level, which on an 8192² float32 grid cost more CPU
than compressing the file. When every level halves the grid exactly (both
sizes divisible by ``2**levels``), each overview cell is the NaN-aware mean
of the 2 x 2 cells below it, summed in float64 and rounded once to float32:
:func:`average_2x2` is that arithmetic (bit-for-bit the values GDAL 3.10
writes, tested against it), applied to each row band of the grid as it
goes by, so the overviews cost one pass over data already in memory.

Pixel convention: overview cell ``[i, j]`` of level ``k`` (factor ``2**k``)
covers cells ``[i*2**k : (i+1)*2**k, j*2**k : (j+1)*2**k]`` of the grid.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["average_2x2", "cog_overview_count", "streamable_overviews"]


def cog_overview_count(shape: tuple[int, int], blocksize: int) -> int:
    """Number of overview levels GDAL's ``COG`` driver makes for a grid of
    ``shape`` (rows, columns) with tiles of ``blocksize``: factors 2, 4, ...
    until the level's larger side (``floor(size / factor)``) fits in one
    tile."""
    n, side = 0, max(shape)
    while side > blocksize:
        n += 1
        side = max(shape) >> n
    return n


def streamable_overviews(shape: tuple[int, int], dtype, levels: int) -> bool:
    """Whether :func:`average_2x2` reproduces GDAL's ``AVERAGE`` overviews of
    a grid: floating-point cells (GDAL rounds integer averages) and both
    sizes divisible by ``2**levels`` (GDAL floors odd level sizes and then
    averages windows that are not 2 x 2)."""
    f = 1 << levels
    return np.dtype(dtype).kind == "f" and shape[0] % f == 0 and shape[1] % f == 0


def average_2x2(a: np.ndarray) -> np.ndarray:
    """Mean of each 2 x 2 cell group of ``a`` ignoring NaN (NaN where all
    four are NaN), summed in float64 in row order, as float32: the ``(rows/2, cols/2)`` overview of ``a``.

    Parameters
    ----------
    a : ndarray
        ``(rows, cols)`` float grid, both sizes even.
    """
    rows, cols = a.shape
    if rows % 2 or cols % 2:
        raise ValueError(f"average_2x2: sizes must be even, got {a.shape}")
    out = np.empty((rows // 2, cols // 2), np.float32)
    _average_2x2(np.ascontiguousarray(a, dtype=np.float32), out)
    return out


@numba.njit(nogil=True, cache=True)
def _average_2x2(a, out):  # pragma: no cover - compiled
    h, w = out.shape
    for i in range(h):
        for j in range(w):
            s = 0.0
            n = 0
            for di in range(2):
                for dj in range(2):
                    v = a[2 * i + di, 2 * j + dj]
                    if not np.isnan(v):  # NaN is the nodata; GDAL averages infinities too
                        s += np.float64(v)
                        n += 1
            out[i, j] = np.float32(s / n) if n else np.float32(np.nan)
