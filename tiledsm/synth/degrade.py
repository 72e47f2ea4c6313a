"""Low-resolution versions of images, with exact regenerated cameras.

Output pixel ``j`` covers input pixels ``[j s, (j + 1) s)`` (GDAL corner
convention), so its centre is at input index coordinate ``(j + .5) s - .5``
and the output camera is exactly ``rpc.scaled(1 / s)`` (for georeferenced
rasters the geotransform is scaled likewise).

Methods (registry :data:`tiledsm.sr.degradation.KERNELS`, the image formation SR inverts):

- ``"bicubic"``: antialiased bicubic, as MATLAB's ``imresize`` and the SR
  literature's "bicubic x s" degradation: Keys' cubic kernel (``a = -0.5``)
  stretched by ``s``;
- ``"gaussian"``: Gaussian blur of ``sigma`` input pixels (default ``s / 2``)
  then decimation at the output centres (blur and sampling in one step).

Optional additive Gaussian noise (DN, from a counter-based hash: the same
for the same ``seed`` and pixel), then rounding and clipping to ``bits`` for
integer images. Processed by strips of output rows: memory stays bounded.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from scipy import sparse

from tiledsm.errors import InputFileError, TiledsmError
from tiledsm.sr.degradation import KERNELS, gaussian_sigma

__all__ = ["degrade", "gaussian_sigma", "resample_matrix", "KERNELS"]


def resample_matrix(n_in: int, scale: float, method: str = "bicubic", sigma: float | None = None,
                    out_range: tuple[int, int] | None = None) -> sparse.csr_matrix:
    """Sparse ``(n_out, n_in)`` matrix resampling one axis by ``1 / scale``.

    Rows are normalised to sum 1; input indices beyond the edges are
    clamped (edge replication). ``out_range`` restricts to output indices
    ``[o0, o1)``.
    """
    if method not in KERNELS:
        raise TiledsmError(f"degrade: unknown method {method!r} (known: {sorted(KERNELS)})")
    kernel, radius = KERNELS[method](scale, sigma)
    n_out = int(math.floor(n_in / scale))
    o0, o1 = out_range or (0, n_out)
    j = np.arange(o0, o1)
    centre = (j + 0.5) * scale - 0.5
    offs = np.arange(-int(math.ceil(radius)) - 1, int(math.ceil(radius)) + 2)
    k = np.floor(centre)[:, None] + offs[None, :]
    w = kernel(k - centre[:, None])
    w = np.where(np.abs(k - centre[:, None]) < radius, w, 0.0)
    w /= w.sum(axis=1, keepdims=True)
    rows = np.repeat(np.arange(o1 - o0), offs.size)
    cols = np.clip(k, 0, n_in - 1).astype(np.int64).ravel()
    return sparse.csr_matrix((w.ravel(), (rows, cols)), shape=(o1 - o0, n_in))


def degrade(
    in_tif,
    out_tif,
    scale: float = 2,
    method: str = "bicubic",
    sigma: float | None = None,
    noise: float = 0.0,
    seed: int = 0,
    bits: int | None = 12,
    strip: int = 512,
) -> Path:
    """Write a low-resolution version of a raster with its regenerated camera.

    Parameters
    ----------
    in_tif, out_tif : path-like
        Input raster (RPC tags and/or CRS kept) and output path (written
        atomically).
    scale : float
        Downsampling factor (> 1 for a smaller image; output size
        ``floor(n / scale)``).
    method : {"bicubic", "gaussian"}
        Resampling kernel (see module docstring).
    sigma : float, optional
        Gaussian standard deviation, input pixels (default ``scale / 2``).
    noise : float
        Standard deviation of additive Gaussian noise, DN.
    seed : int
        Noise stream.
    bits : int or None
        Integer outputs are rounded and clipped to ``[0, 2**bits - 1]``
        (None: the dtype's range). Float outputs are written as float32.
    strip : int
        Output rows per processing strip.

    Returns
    -------
    Path
        ``out_tif``.
    """
    import rasterio
    from rasterio.errors import NotGeoreferencedWarning
    from rasterio.rpc import RPC as RioRPC
    from rasterio.windows import Window
    import warnings

    from tiledsm.geometry import RPC
    from tiledsm.io import atomic_path
    from tiledsm.synth.render import finish_dn
    from tiledsm.synth.scene import raster_profile

    in_tif, out_tif = Path(in_tif), Path(out_tif)
    if not in_tif.exists():
        raise InputFileError(f"{in_tif}: no such file")
    scale = float(scale)
    if not (math.isfinite(scale) and scale > 0):
        raise TiledsmError(f"degrade: scale must be > 0, got {scale}")
    if method not in KERNELS:
        raise TiledsmError(f"degrade: unknown method {method!r} (known: {sorted(KERNELS)})")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        src = rasterio.open(in_tif)
    with src:
        ny, nx = src.height, src.width
        my, mx = int(ny // scale), int(nx // scale)
        if my < 1 or mx < 1:
            raise TiledsmError(f"degrade: {in_tif} ({ny}x{nx}) is too small for scale {scale}")
        dtype = np.dtype(src.dtypes[0])
        integer = dtype.kind in "ui"
        out_dtype = dtype if integer else np.dtype(np.float32)
        rpc = None
        if src.rpcs is not None:
            rpc = RPC.from_gdal(src.rpcs.to_gdal(), source=str(in_tif)).scaled(1.0 / scale)
        profile = raster_profile(out_dtype, (my, mx), rpc=rpc)
        if src.crs is not None:
            profile.update(crs=src.crs, transform=src.transform * src.transform.scale(scale))
        if src.nodata is not None and integer:
            profile["nodata"] = src.nodata
        dn_max = float(2**bits - 1) if (integer and bits) else float(np.iinfo(dtype).max) if integer else 0.0
        wx = resample_matrix(nx, scale, method, sigma).T.tocsr()
        with atomic_path(out_tif) as tmp, warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            with rasterio.open(tmp, "w", **profile) as dst:
                for o0 in range(0, my, strip):
                    o1 = min(o0 + strip, my)
                    wy = resample_matrix(ny, scale, method, sigma, (o0, o1)).tocsc()
                    used = np.flatnonzero(np.diff(wy.indptr))
                    i0, i1 = int(used.min()), int(used.max()) + 1
                    data = src.read(1, window=Window(0, i0, nx, i1 - i0)).astype(np.float64)
                    low = wy[:, i0:i1] @ data
                    low = np.asarray((wx.T @ low.T).T)
                    if integer:
                        q = np.empty(low.shape, out_dtype)
                        finish_dn(np.ascontiguousarray(low), o0, 0, int(seed), 7919, float(noise), dn_max, q)
                        low = q
                    elif noise > 0:
                        rng = np.random.default_rng([int(seed), o0])
                        low = low + noise * rng.standard_normal(low.shape)
                    dst.write(low.astype(out_dtype, copy=False), 1, window=Window(0, o0, mx, o1 - o0))
    return out_tif
