"""Ortho pairs with a known displacement field for ``tiledsm displace``:
a still block and a moved one across a straight trace, POST on any grid.

The source image is a continuous function (a quintic spline through the
pixels of a real image, or the synthetic world's albedo), so POST on any
grid samples exactly ``pre(q - d(q))``: the displacement ``d`` is the truth
at every POST pixel, whatever its CRS, cell size or origin.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import rasterio
from affine import Affine
from scipy import ndimage


@dataclass(frozen=True)
class Trace:
    """A straight trace through ``point`` (map metres, PRE's CRS) along
    ``strike`` (unit east/north); the right block (right-hand normal
    ``(sy, -sx)``) moves by ``shift`` metres east/north, the left one stays."""

    point: tuple[float, float]
    strike: tuple[float, float]
    shift: tuple[float, float]

    @property
    def normal(self) -> np.ndarray:
        return np.array([self.strike[1], -self.strike[0]])

    def distance(self, x, y) -> np.ndarray:
        return (np.asarray(x) - self.point[0]) * self.normal[0] + (np.asarray(y) - self.point[1]) * self.normal[1]

    def lonlat(self, crs: str, half_length: float = 50.0) -> list[float]:
        """Two (lon, lat) points of the trace, as ``--fault-trace`` takes them."""
        from pyproj import Transformer

        t = Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
        p, s = np.asarray(self.point), np.asarray(self.strike)
        a = t.transform(*(p - half_length * s))
        b = t.transform(*(p + half_length * s))
        return [a[0], a[1], b[0], b[1]]


def write_tif(path, array, transform: Affine, crs: str | None) -> str:
    prof = dict(driver="GTiff", width=array.shape[1], height=array.shape[0], count=1, dtype="float32",
                transform=transform, tiled=True, blockxsize=128, blockysize=128)
    if crs is not None:
        prof["crs"] = crs
    with rasterio.open(path, "w", **prof) as dst:
        dst.write(np.asarray(array, np.float32), 1)
    return str(path)


def spline_source(img: np.ndarray):
    """``sample(rows, cols)``: the quintic spline through ``img`` at
    array-index coordinates (pixel ``[i, j]`` centred at ``(i, j)``)."""
    coef = ndimage.spline_filter(np.asarray(img, np.float64), order=5)

    def sample(rows, cols):
        return ndimage.map_coordinates(coef, [rows, cols], order=5, prefilter=False, mode="nearest")

    return sample


def post_on_grid(sample, pre_transform: Affine, pre_crs: str, trace: Trace, transform: Affine, shape, crs: str):
    """POST on the grid ``(transform, shape, crs)``: at each pixel centre
    ``q`` (taken into PRE's CRS), ``pre(q - shift)`` on the right block of
    ``trace``, ``pre(q)`` on the left; ``sample`` reads PRE's continuous
    image at array-index coordinates of PRE's grid."""
    from pyproj import Transformer

    j, i = np.meshgrid(np.arange(shape[1]) + 0.5, np.arange(shape[0]) + 0.5)
    x, y = transform @ (j, i)
    if crs != pre_crs:
        x, y = Transformer.from_crs(crs, pre_crs, always_xy=True).transform(x, y)
    right = trace.distance(x, y) >= 0
    xs = np.where(right, x - trace.shift[0], x)
    ys = np.where(right, y - trace.shift[1], y)
    col, row = ~pre_transform @ (xs, ys)
    return sample(row - 0.5, col - 0.5).reshape(shape)
