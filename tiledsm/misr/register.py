"""Registration of an ortho to a reference ortho: sub-pixel translation by
OpenCV's enhanced correlation coefficient (ECC; Evangelidis & Psarakis
2008, IEEE TPAMI 30(10) 1858-1865) and a linear grey-level adjustment.

Conventions: orthos are ``(y, x)`` arrays on one grid, NaN = no value.
The translation ``(ty, tx)`` (cells) says that the moving ortho's content
at cell ``q + t`` is the reference's at ``q``: the registered ortho is
``moving(q + t)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Registration", "register"]


@dataclass(frozen=True)
class Registration:
    """Result of :func:`register`.

    Attributes
    ----------
    ty, tx : float
        Translation, cells (module conventions).
    gain, offset : float
        Grey-level adjustment ``reference ~ gain * moving + offset``.
    ecc : float
        Final correlation coefficient (1 = perfect).
    """

    ty: float = 0.0
    tx: float = 0.0
    gain: float = 1.0
    offset: float = 0.0
    ecc: float = 1.0


def register(moving: np.ndarray, reference: np.ndarray, *, iterations: int = 100, eps: float = 1e-6) -> Registration:
    """Translation and grey levels of ``moving`` relative to ``reference``.

    ECC (``cv2.findTransformECC``, ``MOTION_TRANSLATION``, Gaussian
    pre-filter 3) on the cells valid in both (NaN filled with the mean and
    masked out); then ``gain``/``offset`` by least squares on the common
    cells after the warp.
    """
    import cv2

    ref = np.asarray(reference, np.float32)
    mov = np.asarray(moving, np.float32)
    ok = np.isfinite(ref) & np.isfinite(mov)
    if ok.sum() < 64:
        return Registration(ecc=float("nan"))
    r = np.where(np.isfinite(ref), ref, np.nanmean(ref)).astype(np.float32)
    m = np.where(np.isfinite(mov), mov, np.nanmean(mov)).astype(np.float32)
    warp = np.eye(2, 3, dtype=np.float32)
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, iterations, eps)
    try:
        ecc, warp = cv2.findTransformECC(r, m, warp, cv2.MOTION_TRANSLATION, crit, ok.astype(np.uint8), 3)
    except cv2.error:
        return Registration(ecc=float("nan"))
    tx, ty = float(warp[0, 2]), float(warp[1, 2])
    warped = cv2.warpAffine(m, warp, (m.shape[1], m.shape[0]), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                            borderMode=cv2.BORDER_REPLICATE)
    # grey levels on the cells valid in the reference and, after the warp, in the moving ortho
    wok = cv2.warpAffine(np.isfinite(mov).astype(np.float32), warp, (m.shape[1], m.shape[0]),
                         flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderValue=0.0)
    ok = np.isfinite(ref) & (wok > 0.999)
    a, b = warped[ok].astype(np.float64), r[ok].astype(np.float64)
    A = np.stack([a, np.ones_like(a)], 1)
    (gain, offset), *_ = np.linalg.lstsq(A, b, rcond=None)
    return Registration(ty=ty, tx=tx, gain=float(gain), offset=float(offset), ecc=float(ecc))
