"""Synthetic stereo scene with analytic affine RPC cameras (test helper).

Ground: UTM 31N around (3.0E, 43.0N); terrain = smooth hills + a box with
vertical walls; a random smooth texture draped on it. Two views with
affine RPCs: rows depend on latitude only, columns on longitude plus
``tilt * (h - h_ref)`` (``tilt`` px/m, ±0.4 at GSD 0.5 m gives B/H = 0.4).
Images are rendered exactly by ray casting along image rows (z-buffer: the
highest surface point on a pixel's ray is the one seen).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np
from pyproj import Transformer
from scipy import ndimage

from tiledsm.geometry import RPC

CRS = "EPSG:32631"
LON0, LAT0 = 3.0, 43.0
GSD = 0.5
H_REF = 100.0


@dataclass
class Scene:
    images: list
    rpcs: list
    height: callable  # (x, y) -> h, UTM metres
    x0: float  # west edge of the scene, UTM
    y0: float  # north edge
    size_m: float
    tilts: tuple


def _affine_rpc(lat_n, lon_w, dlat, dlon, tilt, col_margin):
    """RPC with row = (lat_n - lat)/dlat, col = (lon - lon_w)/dlon + tilt*(h-H_REF) + margin (GDAL px)."""
    lat_off, lon_off, h_off = LAT0, LON0, H_REF
    lat_scale, lon_scale, h_scale = 0.01, 0.01, 100.0
    line_num = np.zeros(20)
    samp_num = np.zeros(20)
    den = np.zeros(20)
    den[0] = 1.0
    line_num[0] = (lat_n - lat_off) / dlat - 0.5
    line_num[2] = -lat_scale / dlat
    samp_num[0] = (lon_off - lon_w) / dlon + col_margin + tilt * (h_off - H_REF) - 0.5
    samp_num[1] = lon_scale / dlon
    samp_num[3] = tilt * h_scale
    return RPC(
        line_off=0.0, samp_off=0.0, lat_off=lat_off, lon_off=lon_off, height_off=h_off,
        line_scale=1.0, samp_scale=1.0, lat_scale=lat_scale, lon_scale=lon_scale, height_scale=h_scale,
        line_num=line_num, line_den=den, samp_num=samp_num, samp_den=den.copy(), source="synthetic affine",
    )


@nb.njit(cache=True)
def _render_rows(col, h, tex, ncols):
    nr, nf = col.shape
    img = np.full((nr, ncols), np.nan, np.float32)
    zbuf = np.full((nr, ncols), -1e30)
    for r in range(nr):
        for k in range(nf - 1):
            c0, c1 = col[r, k], col[r, k + 1]
            lo, hi = min(c0, c1), max(c0, c1)
            j0 = int(np.ceil(lo - 0.5))
            j1 = int(np.floor(hi - 0.5))
            for j in range(max(j0, 0), min(j1, ncols - 1) + 1):
                cc = j + 0.5
                f = 0.0 if hi == lo else (cc - c0) / (c1 - c0)
                hh = h[r, k] + f * (h[r, k + 1] - h[r, k])
                if hh > zbuf[r, j]:
                    zbuf[r, j] = hh
                    img[r, j] = tex[r, k] + f * (tex[r, k + 1] - tex[r, k])
    return img


def make_scene(size_m=100.0, tilts=(0.4, -0.4), seed=0, noise=0.5, box=True) -> Scene:
    rng = np.random.default_rng(seed)
    to_utm = Transformer.from_crs("EPSG:4326", CRS, always_xy=True)
    to_ll = Transformer.from_crs(CRS, "EPSG:4326", always_xy=True)
    xc, yc = to_utm.transform(LON0, LAT0)
    x0, y0 = xc - size_m / 2, yc + size_m / 2

    def height(x, y):
        u, v = x - x0, y0 - y
        h = H_REF + 6.0 * np.sin(2 * np.pi * u / 70.0) * np.cos(2 * np.pi * v / 90.0) + 0.05 * u
        if box:
            inside = (u > 0.40 * size_m) & (u < 0.62 * size_m) & (v > 0.35 * size_m) & (v < 0.55 * size_m)
            h = h + np.where(inside, 8.0, 0.0)
        return h

    # texture: smoothed noise on a 0.25 m grid with margin
    m = 40.0
    n = int((size_m + 2 * m) / 0.25)
    tex_grid = ndimage.gaussian_filter(rng.standard_normal((n, n)), 2.0)
    tex_grid += 0.5 * ndimage.gaussian_filter(rng.standard_normal((n, n)), 6.0)
    tex_grid = 100.0 + 40.0 * tex_grid / tex_grid.std()

    def texture(x, y):
        r = (y0 + m - y) / 0.25
        c = (x - (x0 - m)) / 0.25
        return ndimage.map_coordinates(tex_grid, [r, c], order=1, mode="nearest")

    # lon/lat spacing of one pixel at the centre
    lon_e, _ = to_ll.transform(xc + GSD, yc)
    _, lat_n1 = to_ll.transform(xc, yc + GSD)
    dlon, dlat = lon_e - LON0, lat_n1 - LAT0
    lon_w, lat_n = to_ll.transform(x0, y0)
    npx = int(size_m / GSD)
    margin = 30
    ncols = npx + 2 * margin
    images, rpcs = [], []
    for t in tilts:
        rpc = _affine_rpc(lat_n, lon_w, dlat, dlon, t, margin)
        rows = np.arange(npx) + 0.5
        lat = lat_n - rows * dlat
        fine = np.arange(-(margin + 20) * 8, (npx + margin + 20) * 8) / 8.0
        lon = lon_w + fine * dlon
        LON, LAT = np.meshgrid(lon, lat)
        X, Y = to_utm.transform(LON, LAT)
        H = height(X, Y)
        _, col = rpc.project(LON, LAT, H)
        tex = texture(X, Y)
        img = _render_rows(col, H, tex, ncols)
        img = img + noise * rng.standard_normal(img.shape)
        images.append(img.astype(np.float32))
        rpcs.append(rpc)
    return Scene(images, rpcs, height, x0, y0, size_m, tuple(tilts))


def scene_grid(scene: Scene, margin_m=8.0, res=GSD):
    n = int((scene.size_m - 2 * margin_m) / res)
    gx = scene.x0 + margin_m + (np.arange(n) + 0.5) * res
    gy = scene.y0 - margin_m - (np.arange(n) + 0.5) * res
    return gx, gy




def band_with_holes(scene: Scene, rows: slice, cols: slice, hole: tuple[slice, slice], seed: int = 4):
    """A finer level's search on cells ``rows x cols`` of :func:`scene_grid`:
    the truth +- 3 m, one cell in ten +- 9 m (a coarse hole), the cells
    ``hole`` (block indices) not searched. Returns ``gx, gy, truth, lo, hi,
    kw`` with ``kw`` the ``match_block`` arguments that place the block on
    the whole grid (``origin``, ``axes``) and its reference surface."""
    gx, gy = scene_grid(scene)
    gx, gy = gx[cols], gy[rows]
    X, Y = np.meshgrid(gx, gy)
    truth = scene.height(X, Y)
    rng = np.random.default_rng(seed)
    margin = np.where(rng.random(truth.shape) < 0.1, 9.0, 3.0)
    lo, hi = truth - margin, truth + margin
    lo[hole] = np.nan
    r0, c0 = rows.start, cols.start
    kw = {"origin": (r0, c0), "h_ref": truth + 0.3, "axes": (gx[0] - c0 * GSD, gy[0] + r0 * GSD, GSD, -GSD)}
    return gx, gy, truth, lo, hi, kw
