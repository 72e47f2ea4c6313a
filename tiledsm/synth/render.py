"""Rendering a world through a pushbroom camera, with occlusion.

For one image window:

1. the ground rectangle its rays can cross between the scene's lowest and
   highest surface heights is found by localising the window corners at
   both heights (rows and columns of a pushbroom map to straight lines on
   level ground, so the corners bound it);
2. the world is sampled on an absolute lattice of step ``gsd /
   oversample`` over that rectangle: heights, and radiance = albedo x
   Lambertian shading (``ambient + (1 - ambient) max(0, n . sun)``, normals
   from the sampled heights);
3. every pixel's line of sight is marched down from the window's highest
   sample (:func:`march`): coarse jumps while the ray is above the maximum
   of the surrounding 3 x 3 coarse cells, half-cell steps near the surface,
   bisection at the first crossing. The surface seen is the bilinear
   interpolation of the lattice, so building walls are vertical to within
   one lattice step and hidden ground is never seen;
4. digital numbers ``offset + gain * radiance``, a Gaussian PSF (the window
   is rendered with a ``ceil(4 sigma)`` halo, so tiles agree with a
   single-tile render), Gaussian noise from a counter-based hash of
   ``(seed, view, row, col)`` (identical whatever the tiling), rounding and
   clipping to ``bits``.

Pixel convention: GDAL's (pixel ``[i, j]`` centre at ``(i+0.5, j+0.5)``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
from scipy import ndimage

from tiledsm.synth.noise import hash_normal

__all__ = ["RadiometryParams", "render_window", "surface_lattice", "march", "ground_window"]

#: coarse cell edge of the max pyramid used to skip empty space, lattice steps
COARSE = 8


@dataclass(frozen=True)
class RadiometryParams:
    """Sensor and illumination parameters.

    Attributes
    ----------
    psf_sigma : float
        Standard deviation of the Gaussian PSF, pixels (0: none).
    noise : float
        Standard deviation of the additive Gaussian noise, DN.
    gain, offset : float
        ``DN = offset + gain * radiance`` (radiance = albedo x shading, in [0, 1]).
    bits : int
        Quantisation depth; DN are clipped to ``[0, 2**bits - 1]``.
    sun_azimuth_deg, sun_elevation_deg : float
        Sun direction, degrees (azimuth clockwise from north).
    ambient : float
        Share of diffuse light in the shading, in [0, 1].
    oversample : int
        Lattice steps per image GSD of the surface the rays hit.
    """

    psf_sigma: float = 0.5
    noise: float = 3.0
    gain: float = 3800.0
    offset: float = 120.0
    bits: int = 12
    sun_azimuth_deg: float = 150.0
    sun_elevation_deg: float = 50.0
    ambient: float = 0.35
    oversample: int = 2

    @property
    def halo(self) -> int:
        """Pixels rendered around a window so the PSF is exact inside it."""
        return int(math.ceil(4.0 * self.psf_sigma)) if self.psf_sigma > 0 else 0

    @property
    def sun(self) -> np.ndarray:
        az, el = math.radians(self.sun_azimuth_deg), math.radians(self.sun_elevation_deg)
        return np.array([math.sin(az) * math.cos(el), math.cos(az) * math.cos(el), math.sin(el)])


# --------------------------------------------------------------- lattice
def ground_window(camera, row0, row1, col0, col1, h_range, origin, pad):
    """Local-coordinate rectangle ``(xmin, xmax, ymin, ymax)`` (metres) that
    the lines of sight of image rows ``row0:row1``, columns ``col0:col1``
    (pixel edges, GDAL convention) cross between heights ``h_range``,
    widened by ``pad`` metres."""
    r = np.array([row0, row0, row1, row1] * 2, float)
    c = np.array([col0, col1, col0, col1] * 2, float)
    h = np.repeat(np.asarray(h_range, float), 4)
    x, y = camera.localize_xy(r, c, h)
    x = x - origin[0]
    y = y - origin[1]
    return x.min() - pad, x.max() + pad, y.min() - pad, y.max() + pad


def surface_lattice(ground, xmin, xmax, ymin, ymax, step, radiometry: RadiometryParams):
    """Sample a world on the absolute lattice ``(i * step)`` covering a rectangle.

    Returns
    -------
    x0, y0 : float
        Local coordinates of lattice sample ``[0, 0]`` (rows go north).
    height, radiance : numpy.ndarray
        float32 samples, metres and shaded albedo.
    """
    j0, j1 = int(math.floor(xmin / step)), int(math.ceil(xmax / step))
    i0, i1 = int(math.floor(ymin / step)), int(math.ceil(ymax / step))
    xs = np.arange(j0, j1 + 1) * step
    ys = np.arange(i0, i1 + 1) * step
    height, albedo, _ = ground.evaluate(xs, ys)
    gy, gx = np.gradient(height.astype(np.float64), step)
    sun = radiometry.sun
    lam = (sun[2] - gx * sun[0] - gy * sun[1]) / np.sqrt(1.0 + gx * gx + gy * gy)
    shade = radiometry.ambient + (1.0 - radiometry.ambient) * np.maximum(lam, 0.0)
    radiance = (albedo * shade).astype(np.float32)
    return float(xs[0]), float(ys[0]), height, radiance


@numba.njit(nogil=True, cache=True)
def coarse_max(h, cs):
    ny, nx = h.shape
    cny = (ny - 1) // cs + 1
    cnx = (nx - 1) // cs + 1
    out = np.full((cny, cnx), -np.inf, np.float32)
    for ci in range(cny):
        for cj in range(cnx):
            m = -np.inf
            for i in range(ci * cs, min(ci * cs + cs + 1, ny)):
                for j in range(cj * cs, min(cj * cs + cs + 1, nx)):
                    if h[i, j] > m:
                        m = h[i, j]
            out[ci, cj] = m
    # 3 x 3 dilation
    dil = np.empty_like(out)
    for ci in range(cny):
        for cj in range(cnx):
            m = -np.inf
            for i in range(max(ci - 1, 0), min(ci + 2, cny)):
                for j in range(max(cj - 1, 0), min(cj + 2, cnx)):
                    if out[i, j] > m:
                        m = out[i, j]
            dil[ci, cj] = m
    return dil


@numba.njit(nogil=True, cache=True, inline="always")
def bilinear_at(img, fy, fx):
    ny, nx = img.shape
    i = int(math.floor(fy))
    j = int(math.floor(fx))
    i = min(max(i, 0), ny - 2)
    j = min(max(j, 0), nx - 2)
    ty = fy - i
    tx = fx - j
    top = img[i, j] * (1.0 - tx) + img[i, j + 1] * tx
    bot = img[i + 1, j] * (1.0 - tx) + img[i + 1, j + 1] * tx
    return top * (1.0 - ty) + bot * ty


@numba.njit(nogil=True, cache=True)
def march(origins, dirs, height, radiance, x0, y0, step, cmax, cs, ztop, zbot, out_rad, out_xyz):
    """First intersection of each pixel's line of sight with the surface.

    Parameters
    ----------
    origins : (nr, 3) float64
        Sensor position per image row, local metres (x, y, height).
    dirs : (nc, 3) float64
        Look direction per image column (height component < 0).
    height, radiance : (ny, nx) float32
        Surface lattice, sample ``[i, j]`` at ``(x0 + j step, y0 + i step)``.
    cmax : 2-D float32
        3 x 3-dilated maxima of ``height`` over ``cs x cs`` coarse cells.
    ztop, zbot : float
        Heights between which to march (``>=`` max and ``<=`` min of ``height``).
    out_rad : (nr, nc) float32
        Radiance at the hit point (output).
    out_xyz : (nr, nc, 3) float64
        Hit point, local metres (output).
    """
    nr = origins.shape[0]
    nc = dirs.shape[0]
    cny, cnx = cmax.shape
    for r in range(nr):
        sx = origins[r, 0]
        sy = origins[r, 1]
        sz = origins[r, 2]
        for c in range(nc):
            gx = dirs[c, 0] / dirs[c, 2]
            gy = dirs[c, 1] / dirs[c, 2]
            g = math.sqrt(gx * gx + gy * gy)
            fine = 0.5 * step / g if g > 0 else 1e30
            coarse = cs * step / g if g > 0 else 1e30
            z = ztop
            za = ztop
            hit = False
            while True:
                fx = (sx + (z - sz) * gx - x0) / step
                fy = (sy + (z - sz) * gy - y0) / step
                ci = min(max(int(math.floor(fy / cs)), 0), cny - 1)
                cj = min(max(int(math.floor(fx / cs)), 0), cnx - 1)
                cm = cmax[ci, cj]
                if z > cm:
                    za = z
                    z = max(cm, z - coarse, zbot)
                    continue
                if z - bilinear_at(height, fy, fx) <= 0.0:
                    hit = True
                    break
                za = z
                if z <= zbot:
                    break
                z = max(z - fine, zbot)
            if hit:
                zb = z
                for _ in range(18):
                    zm = 0.5 * (za + zb)
                    fxm = (sx + (zm - sz) * gx - x0) / step
                    fym = (sy + (zm - sz) * gy - y0) / step
                    if zm - bilinear_at(height, fym, fxm) > 0.0:
                        za = zm
                    else:
                        zb = zm
                z = 0.5 * (za + zb)
            fx = (sx + (z - sz) * gx - x0) / step
            fy = (sy + (z - sz) * gy - y0) / step
            out_rad[r, c] = bilinear_at(radiance, fy, fx)
            out_xyz[r, c, 0] = x0 + fx * step
            out_xyz[r, c, 1] = y0 + fy * step
            out_xyz[r, c, 2] = z


@numba.njit(nogil=True, cache=True)
def finish_dn(dn, row0, col0, seed, view, noise, dn_max, out):
    ny, nx = dn.shape
    for i in range(ny):
        for j in range(nx):
            v = dn[i, j]
            if noise > 0:
                v += noise * hash_normal(seed, row0 + i, col0 + j, view)
            v = math.floor(v + 0.5)
            out[i, j] = min(max(v, 0.0), dn_max)


def render_window(
    ground,
    camera,
    origin: tuple[float, float],
    h_range: tuple[float, float],
    rows: tuple[int, int],
    cols: tuple[int, int],
    radiometry: RadiometryParams = RadiometryParams(),
    seed: int = 0,
    view: int = 0,
    truth: bool = False,
):
    """Render image rows ``rows[0]:rows[1]``, columns ``cols[0]:cols[1]``.

    Parameters
    ----------
    ground : World or PostEventWorld
        What is seen (``evaluate(x, y)`` on separable local grids).
    camera : PushbroomCamera
        The view; its frame is the world's CRS.
    origin : (float, float)
        Easting and northing of the world's local origin, metres.
    h_range : (float, float)
        Guaranteed bounds of the surface height over the scene, metres.
    rows, cols : (int, int)
        Half-open pixel index ranges of the window.
    radiometry : RadiometryParams
        Sensor model.
    seed, view : int
        Noise stream: the same ``(seed, view, row, col)`` always gets the
        same noise value.
    truth : bool
        Also return the noise-free radiance and the hit points.

    Returns
    -------
    numpy.ndarray
        uint16 digital numbers, shape ``(rows[1]-rows[0], cols[1]-cols[0])``;
        with ``truth=True`` a tuple ``(dn, radiance, xyz)`` where ``radiance``
        (float32) is the PSF-free radiance of each pixel centre's hit and
        ``xyz`` (float64, ``(..., 3)``) the hit point in local metres.
    """
    r0, r1 = rows
    c0, c1 = cols
    halo = radiometry.halo
    step = camera.gsd / radiometry.oversample
    pad = 2.0 * step
    xmin, xmax, ymin, ymax = ground_window(camera, r0 - halo, r1 + halo, c0 - halo, c1 + halo, h_range, origin, pad)
    x0, y0, height, radiance = surface_lattice(ground, xmin, xmax, ymin, ymax, step, radiometry)
    cmax = coarse_max(height, COARSE)
    rr = np.arange(r0 - halo, r1 + halo) + 0.5
    cc = np.arange(c0 - halo, c1 + halo) + 0.5
    o, _ = camera.rays(rr, np.full_like(rr, 0.5 * camera.cols))
    _, d = camera.rays(np.full_like(cc, 0.5 * camera.rows), cc)
    o = o - np.array([origin[0], origin[1], 0.0])
    rad = np.empty((rr.size, cc.size), np.float32)
    xyz = np.empty((rr.size, cc.size, 3), np.float64)
    ztop = float(height.max()) + 1e-3
    zbot = float(height.min()) - 1e-3
    march(np.ascontiguousarray(o), np.ascontiguousarray(d), height, radiance, x0, y0, step, cmax, COARSE,
          ztop, zbot, rad, xyz)
    dn = radiometry.offset + radiometry.gain * rad.astype(np.float64)
    if radiometry.psf_sigma > 0:
        dn = ndimage.gaussian_filter(dn, radiometry.psf_sigma, truncate=4.0, mode="nearest")
    inner = (slice(halo, halo + r1 - r0), slice(halo, halo + c1 - c0))
    out = np.empty((r1 - r0, c1 - c0), np.uint16)
    finish_dn(np.ascontiguousarray(dn[inner]), r0, c0, int(seed), int(view), float(radiometry.noise),
            float(2**radiometry.bits - 1), out)
    if truth:
        return out, rad[inner], xyz[inner]
    return out
