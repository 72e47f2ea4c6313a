"""Shared cases of tests/displace: a band-limited texture and its exact
sub-pixel translation (Fourier shift theorem), and orthos on a UTM grid."""

import numpy as np
import rioxarray  # noqa: F401
import xarray as xr
from affine import Affine
from scipy import ndimage


def texture(seed=0, n=384):
    rng = np.random.default_rng(seed)
    return ndimage.gaussian_filter(rng.normal(size=(n, n)), 1.5) * 200 + 100


def fourier_shift(img, dy, dx):
    """``img`` content moved by ``(dy, dx)`` pixels (rows down, columns right), exactly."""
    ky = np.fft.fftfreq(img.shape[0])[:, None]
    kx = np.fft.fftfreq(img.shape[1])[None, :]
    return np.real(np.fft.ifft2(np.fft.fft2(img) * np.exp(-2j * np.pi * (ky * dy + kx * dx))))


def ortho(a, res=0.5, x0=500000.0, y0=4000000.0, crs="EPSG:32631"):
    ny, nx = a.shape
    d = xr.DataArray(np.asarray(a, np.float32), dims=("y", "x"),
                     coords={"y": y0 - (np.arange(ny) + 0.5) * res, "x": x0 + (np.arange(nx) + 0.5) * res})
    return d.rio.write_crs(crs).rio.write_transform(Affine(res, 0, x0, 0, -res, y0))
