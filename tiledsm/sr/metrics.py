"""Image quality of an SR result against the HR reference: PSNR, SSIM.

Both ignore NaN (nodata) pixels and can crop a border of ``border`` pixels
(customary: the scale factor) before measuring.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

__all__ = ["psnr", "ssim", "data_range_for"]


def data_range_for(bit_depth: int | None = None, data_range: float | None = None) -> float:
    """Peak value of the PSNR: ``data_range`` if given, else ``2**bit_depth - 1``."""
    if data_range is not None:
        if data_range <= 0:
            raise ValueError(f"data_range must be > 0, got {data_range}")
        return float(data_range)
    if bit_depth is None:
        raise ValueError("give bit_depth (e.g. 8, 11, 12, 16) or data_range")
    return float(2 ** int(bit_depth) - 1)


def _prepare(reference, test, border: int) -> tuple[np.ndarray, np.ndarray]:
    ref = np.asarray(reference, dtype=np.float64)
    tst = np.asarray(test, dtype=np.float64)
    if ref.shape != tst.shape:
        raise ValueError(f"reference shape {ref.shape} != test shape {tst.shape}")
    if border:
        ref = ref[..., border:-border, border:-border]
        tst = tst[..., border:-border, border:-border]
    return ref, tst


def psnr(reference, test, *, bit_depth: int | None = None, data_range: float | None = None, border: int = 0) -> float:
    """Peak signal-to-noise ratio in dB, ``10 log10(peak² / MSE)``.

    Parameters
    ----------
    reference, test : array_like
        Same shape, in the same units (sensor digital numbers).
    bit_depth : int, optional
        Sensor bit depth; the peak is ``2**bit_depth - 1`` (255 for 8 bit,
        4095 for 12 bit).
    data_range : float, optional
        Explicit peak value (overrides ``bit_depth``).
    border : int
        Pixels cropped on each side before measuring.

    Returns
    -------
    float
        PSNR in dB over pixels finite in both arrays; ``inf`` when equal.
    """
    peak = data_range_for(bit_depth, data_range)
    ref, tst = _prepare(reference, test, border)
    valid = np.isfinite(ref) & np.isfinite(tst)
    if not valid.any():
        raise ValueError("psnr: no pixel is finite in both images")
    mse = np.mean((ref[valid] - tst[valid]) ** 2)
    return float("inf") if mse == 0 else float(10 * np.log10(peak**2 / mse))


def ssim(reference, test, *, bit_depth: int | None = None, data_range: float | None = None, border: int = 0, win_size: int = 7) -> float:
    """Mean structural similarity (scikit-image's ``structural_similarity``,
    uniform ``win_size`` window, default constants) over the windows that
    contain no NaN.

    Parameters are as in :func:`psnr`. With no NaN this equals
    ``skimage.metrics.structural_similarity(ref, test, data_range=peak)``
    on the cropped arrays.
    """
    from skimage.metrics import structural_similarity

    peak = data_range_for(bit_depth, data_range)
    ref, tst = _prepare(reference, test, border)
    bad = ~(np.isfinite(ref) & np.isfinite(tst))
    if not bad.any():
        return float(structural_similarity(ref, tst, data_range=peak, win_size=win_size))
    fill = np.nanmean(np.where(bad, np.nan, ref))
    _, smap = structural_similarity(
        np.where(bad, fill, ref), np.where(bad, fill, tst), data_range=peak, win_size=win_size, full=True
    )
    # windows touching a NaN are left out (same crop of win_size // 2 as skimage)
    touched = ndimage.binary_dilation(bad, structure=np.ones((win_size, win_size), bool))
    pad = win_size // 2
    keep = ~touched
    keep[:pad] = keep[-pad:] = False
    keep[:, :pad] = keep[:, -pad:] = False
    if not keep.any():
        raise ValueError("ssim: no window free of NaN")
    return float(smap[keep].mean())
