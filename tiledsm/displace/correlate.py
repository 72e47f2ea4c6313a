"""Sub-pixel correlation of two images in the frequency domain (pure numpy).

The displacement of a window of ``post`` with respect to the same window of
``pre`` is measured in two stages:

1. **Coarse**: phase correlation of a window widened by ``search`` pixels on
   each side (so content that moved up to ``search`` px is still inside
   it); the peak of the inverse normalised cross-power spectrum, searched
   within ``|d| <= search`` and refined by a 3-point parabola per axis.
2. **Fine** (``iterations`` times): ``post`` is resampled at the window's
   pixels plus the current estimate (separable Lanczos, ``a = 4``: local,
   no global prefilter, so the result does not depend on the tiling, and
   with a much smaller position bias at fractional shifts than cubic
   convolution: on a Fourier-shifted noise texture, 0.010 px with Keys'
   ``a = -0.5`` against at most 0.0023 px with Lanczos-4), and the small residual shift is the slope of the cross-power
   spectrum's phase, fitted by weighted least squares over the frequencies
   below ``frequency_cut`` of Nyquist (the phase-plane method of the
   COSI-Corr family, Leprince et al. 2007, doi:10.1109/TGRS.2006.888937).
   Because the window follows the content, the taper's bias on the shift
   vanishes as the residual goes to zero.

The frequency mask makes the measure aliasing-safe: the highest
frequencies of resampled orthoimages hold aliasing and interpolation
artefacts that carry no shift information. The result is
resolution-limited: each value is the shift of a ``window``-pixel window,
so features of motion narrower than the window are averaged (sample the
field at ``step <= window / 2`` to keep that averaged field alias-free).

Conventions
-----------
- Shifts are in pixels, ``(dy, dx)`` along rows (down) and columns (right):
  ``post(p) = pre(p - d)``, i.e. the content of ``pre`` at ``p`` is found in
  ``post`` at ``p + d``.
- Window centres are given as GDAL pixel coordinates of the block (top-left
  corner of the array at ``(0, 0)``, pixel ``[i, j]`` centred at
  ``(i + .5, j + .5)``); a window of even side ``w`` centred on an integer
  coordinate ``c`` holds pixels ``c - w/2 .. c + w/2 - 1``.
- NaN pixels: a window with more than ``max_nodata`` of them gives NaN; fewer
  are replaced by the window's mean before the taper.
- ``quality`` is the phase coherence of the fine fit,
  ``|sum w exp(i (phase - model))| / sum w`` in ``[0, 1]`` (1: a pure
  shift); cells below ``min_quality``, or whose ``pre`` window has a
  standard deviation below ``min_texture`` (no texture: NaN, not noise),
  are NaN, and so are cells whose coarse phase-correlation peak is under
  ``min_peak`` (no true match within ``search``: refused, not guessed).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from tiledsm.errors import InvalidOptionError

__all__ = ["CorrelationParams", "N_LAYERS", "correlate_windows", "phase_plane_shift", "coarse_shift", "shifted_windows"]


@dataclass(frozen=True)
class CorrelationParams:
    """Parameters of :func:`correlate_windows` (pixels unless stated).

    Attributes
    ----------
    window : int
        Side of the fine correlation window (even, >= 8).
    step : int
        Spacing of the output cells (even); the field is sampled every
        ``step`` pixels (``step <= window / 2`` keeps it alias-free).
    search : int
        Largest displacement looked for, pixels per axis (the coarse window
        is ``window + 2 * search``).
    iterations : int
        Fine passes after the coarse one.
    frequency_cut : float
        Share of the Nyquist frequency used by the phase-plane fit, (0, 1].
    min_quality : float
        Phase coherence under which a cell is NaN.
    min_peak : float
        Height of the coarse phase-correlation peak under which a cell is
        NaN: a displacement beyond ``search`` (or no match at all) leaves
        only noise peaks (measured: <= 0.11 at the 99th percentile on a
        texture moved past ``search``, against >= 0.24 at the 1st
        percentile for real matches of the s2p orthos).
    min_texture : float
        Standard deviation of the ``pre`` window (image units) under which
        a cell is NaN.
    max_nodata : float
        Largest share of NaN pixels in a window.
    batch : int
        Windows transformed together (memory: ~``batch * (window + 2 *
        search)**2 * 48`` bytes).
    levels : int
        Coarse levels of the pyramid (:mod:`tiledsm.displace.pyramid`):
        0, one level searching ``search`` px around zero; ``L > 0``, the
        images are first correlated at ``2**L`` times coarser pixels with
        ``search`` there (reach ``search * 2**L`` full-resolution px), and
        the full-resolution level searches ``refine_search`` px around the
        candidates that level predicts.
    refine_search : int
        Search of the full-resolution level around each predicted
        candidate, pixels (``levels > 0`` only).
    """

    window: int = 32
    step: int = 8
    search: int = 8
    iterations: int = 2
    frequency_cut: float = 0.6
    min_quality: float = 0.5
    min_peak: float = 0.15
    min_texture: float = 1.0
    max_nodata: float = 0.2
    batch: int = 1024
    levels: int = 0
    refine_search: int = 4

    def __post_init__(self) -> None:
        if self.window < 8 or self.window % 2:
            raise InvalidOptionError(f"window: an even number of pixels >= 8, got {self.window}")
        if self.step < 2 or self.step % 2:
            raise InvalidOptionError(f"step: an even number of pixels >= 2, got {self.step}")
        if self.search < 1:
            raise InvalidOptionError(f"search: at least 1 pixel, got {self.search}")
        if self.iterations < 1:
            raise InvalidOptionError(f"iterations: at least 1, got {self.iterations}")
        if not 0 < self.frequency_cut <= 1:
            raise InvalidOptionError(f"frequency_cut: in (0, 1], got {self.frequency_cut}")
        if not 0 <= self.max_nodata < 1:
            raise InvalidOptionError(f"max_nodata: in [0, 1), got {self.max_nodata}")
        if not 0 <= self.levels <= 6:
            raise InvalidOptionError(f"levels: 0 to 6 coarse levels, got {self.levels}")
        if self.refine_search < 1:
            raise InvalidOptionError(f"refine_search: at least 1 pixel, got {self.refine_search}")

    @property
    def factor(self) -> int:
        """Pixels of the full-resolution level per pixel of the coarsest."""
        return 2**self.levels

    @property
    def reach(self) -> int:
        """Largest displacement looked for, full-resolution pixels per axis."""
        return self.search * self.factor

    @property
    def coarse_window(self) -> int:
        return self.window + 2 * self.search

    @property
    def halo(self) -> int:
        """Pixels a block needs around its cells: the coarse window's half,
        and the fine window moved by up to ``search`` plus the Lanczos
        support; with a pyramid, the coarsest level's windows of the coarse
        cells two cells beyond the block (at ``2**levels`` px per pixel) and
        the full-resolution windows moved by up to the reach."""
        single = max(self.coarse_window // 2, self.window // 2 + self.search + LANCZOS_A + 1) + 1
        if not self.levels:
            return single
        f = self.factor
        coarse = 3 * self.step * f + f * single + f
        moved = self.reach + f + self.refine_search
        fine = max(self.window // 2 + moved, self.window // 2 + moved + LANCZOS_A + 1) + 1
        return max(coarse, fine)


def _taper(n: int) -> np.ndarray:
    """Separable Hann taper, ``(n, n)``."""
    w = np.hanning(n + 2)[1:-1]
    return np.outer(w, w)


def _prepare(stack: np.ndarray, max_nodata: float, taper: np.ndarray):
    """Mean-removed, NaN-filled, tapered windows; share of NaN and std per window."""
    finite = np.isfinite(stack)
    share_nan = 1.0 - finite.mean(axis=(1, 2))
    cnt = np.maximum(finite.sum(axis=(1, 2)), 1)
    mean = np.where(finite, stack, 0.0).sum(axis=(1, 2)) / cnt
    centred = np.where(finite, stack - mean[:, None, None], 0.0)
    std = np.sqrt((centred**2).sum(axis=(1, 2)) / cnt)
    return centred * taper, share_nan <= max_nodata, std


def coarse_shift(pre_w: np.ndarray, post_w: np.ndarray, search: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Phase-correlation shift of tapered windows, within ``|d| <= search``.

    Parameters
    ----------
    pre_w, post_w : ndarray
        ``(n, w, w)`` tapered, mean-removed windows.

    Returns
    -------
    dy, dx : ndarray
        Shift, pixels (module conventions), parabola-refined.
    peak : ndarray
        Height of the phase-correlation peak (1 for a pure circular shift).
    """
    n, w, _ = pre_w.shape
    q = np.conj(np.fft.rfft2(pre_w)) * np.fft.rfft2(post_w)
    q /= np.maximum(np.abs(q), 1e-12)
    pc = np.fft.irfft2(q, s=(w, w))
    pc = np.fft.fftshift(pc, axes=(1, 2))  # zero shift at [w//2, w//2]
    c = w // 2
    lo, hi = c - search, c + search + 1
    sub = pc[:, lo:hi, lo:hi]
    k = sub.reshape(n, -1).argmax(axis=1)
    iy, ix = np.unravel_index(k, sub.shape[1:])
    peak = sub[np.arange(n), iy, ix]
    # 3-point parabola per axis on the full surface (neighbours exist: the search box is inside it)
    ry, rx = iy + lo, ix + lo
    idx = np.arange(n)

    def vertex(m, z, p):
        den = m - 2 * z + p
        return np.where(np.abs(den) > 1e-12, 0.5 * (m - p) / np.where(den == 0, 1, den), 0.0).clip(-0.5, 0.5)

    fy = vertex(pc[idx, ry - 1, rx], peak, pc[idx, (ry + 1) % w, rx])
    fx = vertex(pc[idx, ry, rx - 1], peak, pc[idx, ry, (rx + 1) % w])
    return (ry - c + fy).astype(np.float64), (rx - c + fx).astype(np.float64), peak


def phase_plane_shift(pre_w: np.ndarray, post_w: np.ndarray, frequency_cut: float):
    """Residual shift from the slope of the cross-power phase.

    Parameters
    ----------
    pre_w, post_w : ndarray
        ``(n, w, w)`` tapered, mean-removed windows whose residual shift is
        well below one pixel (no phase wrapping under the cut).
    frequency_cut : float
        Share of Nyquist of the frequencies used (a square mask).

    Returns
    -------
    dy, dx : ndarray
        Residual shift, pixels.
    coherence : ndarray
        ``|sum w exp(i (phase - model))| / sum w``, in ``[0, 1]``.
    sigma_dy, sigma_dx : ndarray
        Formal standard errors of ``dy``, ``dx`` (pixels): the weighted
        phase residual's variance times the diagonal of the inverse normal
        matrix (weights scaled to their sum), the least-squares precision
        of the fit. They grow where the two windows' contents differ
        beyond a shift (noise, resampling, a changed surface) and where
        the window has little texture across that axis.
    """
    n, w, _ = pre_w.shape
    q = np.conj(np.fft.rfft2(pre_w)) * np.fft.rfft2(post_w)  # = |F|^2 exp(-i 2pi (k dy + l dx) / w)
    ky = np.fft.fftfreq(w) * w
    kx = np.fft.rfftfreq(w) * w
    KY, KX = np.meshgrid(ky, kx, indexing="ij")
    cut = frequency_cut * w / 2
    use = (np.abs(KY) <= cut) & (KX <= cut) & ((KY != 0) | (KX != 0))
    # the half plane kx = 0 holds each frequency and its conjugate: count it once
    use &= ~((KX == 0) & (KY < 0))
    qs = q[:, use]
    ky, kx = KY[use], KX[use]
    wgt = np.abs(qs)
    phi = -np.angle(qs)  # = 2 pi (k dy + l dx) / w
    a11 = (wgt * ky * ky).sum(1)
    a12 = (wgt * ky * kx).sum(1)
    a22 = (wgt * kx * kx).sum(1)
    b1 = (wgt * ky * phi).sum(1)
    b2 = (wgt * kx * phi).sum(1)
    det = a11 * a22 - a12 * a12
    ok = det > 1e-12 * np.maximum(a11 * a22, 1e-300)
    det = np.where(ok, det, 1.0)
    sy = (a22 * b1 - a12 * b2) / det
    sx = (a11 * b2 - a12 * b1) / det
    scale = w / (2 * math.pi)
    model = sy[:, None] * ky + sx[:, None] * kx
    tw = wgt.sum(1)
    coh = np.abs((wgt * np.exp(1j * (phi - model))).sum(1)) / np.maximum(tw, 1e-300)
    dy = np.where(ok, sy * scale, np.nan)
    dx = np.where(ok, sx * scale, np.nan)
    res = np.angle(np.exp(1j * (phi - model)))  # wrapped to [-pi, pi]
    s2 = (wgt * res * res).sum(1) / np.maximum(tw, 1e-300)
    var_y, var_x = s2 * a22 / det * tw, s2 * a11 / det * tw
    sig_y = np.where(ok, np.sqrt(var_y) * scale, np.nan)
    sig_x = np.where(ok, np.sqrt(var_x) * scale, np.nan)
    return dy, dx, np.where(ok & (tw > 0), coh, 0.0), sig_y, sig_x


LANCZOS_A = 4

#: rows of :func:`correlate_windows`'s output
N_LAYERS = 7


@numba.njit(cache=True, nogil=True)
def _lanczos_weights(f, a, out):  # pragma: no cover - compiled
    """Normalised Lanczos-``a`` weights of the ``2a`` taps ``-a+1 .. a`` at fraction ``f``."""
    s = 0.0
    for t in range(2 * a):
        u = f - (t - a + 1)
        if u == 0.0:
            out[t] = 1.0
        elif abs(u) >= a:
            out[t] = 0.0
        else:
            pu = np.pi * u
            out[t] = a * np.sin(pu) * np.sin(pu / a) / (pu * pu)
        s += out[t]
    for t in range(2 * a):
        out[t] /= s


@numba.njit(cache=True, nogil=True)
def _lanczos_windows(img, rows, cols, dy, dx, w, out):  # pragma: no cover - compiled
    """``out[k]``: the ``w x w`` window of ``img`` centred on GDAL ``(rows[k],
    cols[k])`` moved by ``(dy[k], dx[k])``, Lanczos resampled. Taps that
    are NaN or off the image are left out and the others renormalised, so
    a missing pixel does not blank its 8 x 8 neighbourhood; a sample is NaN
    where its nearest pixel is, or where the taps left hold under half the
    weight. The fraction is the same for the whole window: weights once."""
    a = LANCZOS_A
    h = w // 2
    ny, nx = img.shape
    wy = np.empty(2 * a)
    wx = np.empty(2 * a)
    for k in range(rows.shape[0]):
        y0 = rows[k] - h + dy[k]
        x0 = cols[k] - h + dx[k]
        iy0 = int(np.floor(y0))
        ix0 = int(np.floor(x0))
        _lanczos_weights(y0 - iy0, a, wy)
        _lanczos_weights(x0 - ix0, a, wx)
        ny0 = iy0 + (1 if y0 - iy0 >= 0.5 else 0)  # nearest pixel of the first sample
        nx0 = ix0 + (1 if x0 - ix0 >= 0.5 else 0)
        for i in range(w):
            for j in range(w):
                yn, xn = ny0 + i, nx0 + j
                if yn < 0 or yn >= ny or xn < 0 or xn >= nx or img[yn, xn] != img[yn, xn]:
                    out[k, i, j] = np.nan
                    continue
                acc = 0.0
                wsum = 0.0
                for ty in range(2 * a):
                    yy = iy0 + i + ty - a + 1
                    if yy < 0 or yy >= ny:
                        continue
                    for tx in range(2 * a):
                        xx = ix0 + j + tx - a + 1
                        if xx < 0 or xx >= nx:
                            continue
                        v = img[yy, xx]
                        if v != v:
                            continue
                        wt = wy[ty] * wx[tx]
                        acc += wt * v
                        wsum += wt
                out[k, i, j] = acc / wsum if wsum > 0.5 else np.nan


def shifted_windows(img: np.ndarray, rows: np.ndarray, cols: np.ndarray, dy: np.ndarray, dx: np.ndarray,
                    w: int) -> np.ndarray:
    """``(n, w, w)`` windows centred on the integer GDAL coordinates
    ``(rows, cols)`` moved by ``(dy, dx)`` pixels (Lanczos-4; NaN where the
    nearest pixel is NaN or off ``img``; other NaN taps are left out)."""
    out = np.empty((rows.size, w, w), np.float64)
    # array coordinate of the first pixel centre of a window is rows - w/2 (GDAL centre i + .5 -> array i)
    _lanczos_windows(np.ascontiguousarray(img, np.float64), rows.astype(np.float64), cols.astype(np.float64),
                     np.ascontiguousarray(dy, np.float64), np.ascontiguousarray(dx, np.float64), w, out)
    return out


def _windows(img: np.ndarray, rows: np.ndarray, cols: np.ndarray, w: int) -> np.ndarray:
    """``(n, w, w)`` windows of ``img`` centred on the integer GDAL
    coordinates ``rows, cols`` (copies; NaN outside)."""
    h = w // 2
    oy = np.arange(-h, w - h)
    r = rows.astype(np.int64)[:, None] + oy[None, :]
    c = cols.astype(np.int64)[:, None] + oy[None, :]
    inside_r = (r >= 0) & (r < img.shape[0])
    inside_c = (c >= 0) & (c < img.shape[1])
    out = img[np.clip(r, 0, img.shape[0] - 1)[:, :, None], np.clip(c, 0, img.shape[1] - 1)[:, None, :]]
    out = out.astype(np.float64)
    out[~(inside_r[:, :, None] & inside_c[:, None, :])] = np.nan
    return out


def _guided_coarse(pre: np.ndarray, post: np.ndarray, r: np.ndarray, c: np.ndarray, gy: np.ndarray, gx: np.ndarray,
                   params: CorrelationParams, search: int):
    """Coarse stage around integer guesses ``(gy, gx)``: the ``post`` window
    is taken at the cell moved by the guess, so only the residual needs to
    lie within ``search``. Returns the shift (guess included), the peak
    height and whether both windows had enough data."""
    wc = params.window + 2 * search
    taper_c = _taper(wc)
    a, ok_a, _ = _prepare(_windows(pre, r, c, wc), params.max_nodata, taper_c)
    b, ok_b, _ = _prepare(_windows(post, r + gy, c + gx, wc), params.max_nodata, taper_c)
    dy, dx, peak = coarse_shift(a, b, search)
    return dy + gy, dx + gx, peak, ok_a & ok_b


def _best_guess(pre: np.ndarray, post: np.ndarray, r: np.ndarray, c: np.ndarray, guesses: np.ndarray,
                params: CorrelationParams, search: int):
    """The coarse stage at every finite candidate of ``guesses`` ``(n, K,
    2)`` (pixels, rounded to integers), keeping per cell the candidate whose
    phase-correlation peak is highest (a window that lies on one side of a
    discontinuity matches that side's motion with a clear peak, the other
    side's with noise only)."""
    n, k = guesses.shape[:2]
    g = np.rint(np.nan_to_num(guesses)).astype(np.int64)
    use = np.isfinite(guesses).all(axis=2)
    cell, cand = np.nonzero(use)
    best = np.full(n, -np.inf)
    dy, dx = np.zeros(n), np.zeros(n)
    gy, gx = np.zeros(n, np.int64), np.zeros(n, np.int64)
    ok = np.zeros(n, bool)
    if cell.size:
        ry, rx, peak, ok_p = _guided_coarse(pre, post, r[cell], c[cell], g[cell, cand, 0], g[cell, cand, 1], params,
                                            search)
        score = np.where(ok_p, peak, -1.0)
        # per cell, the pair of highest score: sort by (cell, score) and keep each cell's last
        order = np.lexsort((score, cell))
        last = np.r_[cell[order][1:] != cell[order][:-1], True]
        pick = order[last]
        at = cell[pick]
        best[at], dy[at], dx[at], ok[at] = peak[pick], ry[pick], rx[pick], ok_p[pick]
        gy[at], gx[at] = g[cell[pick], cand[pick], 0], g[cell[pick], cand[pick], 1]
    return dy, dx, np.where(np.isfinite(best), best, 0.0), ok, gy, gx


def correlate_windows(pre: np.ndarray, post: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                      params: CorrelationParams = CorrelationParams(), guesses: np.ndarray | None = None,
                      search: int | None = None) -> np.ndarray:
    """Displacement of ``post`` against ``pre`` in windows centred at ``(rows, cols)``.

    Parameters
    ----------
    pre, post : ndarray
        Two images on the same grid, ``(h, w)``, NaN = no data.
    rows, cols : ndarray
        Integer GDAL pixel coordinates of the window centres (module
        conventions), 1-D of the same length; each needs ``params.halo``
        pixels of the images around it (fewer: NaN pixels count as nodata),
        plus the largest guess.
    params : CorrelationParams
    guesses : ndarray, optional
        ``(n, K, 2)`` candidate displacements ``(dy, dx)`` per cell, pixels
        (NaN: no candidate), e.g. from a coarser level
        (:mod:`tiledsm.displace.pyramid`): the coarse stage looks ``search``
        px around each (rounded) and keeps the candidate with the highest
        peak. None: one candidate, zero, and ``search = params.search``
        (the values are then those of the plain single-level correlation).
    search : int, optional
        Search around the guesses, pixels (default ``params.search``).

    Returns
    -------
    ndarray
        ``(7, n)`` float32: ``dy, dx`` (pixels, module conventions; NaN where
        unreliable), ``quality`` (phase coherence of the last fine pass),
        ``texture`` (standard deviation of the ``pre`` window), ``sigma_dy,
        sigma_dx`` (formal standard errors of the last fine pass, pixels;
        :func:`phase_plane_shift`), ``peak`` (height of the coarse
        phase-correlation peak).
    """
    pre = np.asarray(pre, np.float64)
    post = np.asarray(post, np.float64)
    if pre.shape != post.shape:
        raise ValueError(f"correlate_windows: pre {pre.shape} and post {post.shape} differ")
    rows = np.asarray(rows, np.int64).ravel()
    cols = np.asarray(cols, np.int64).ravel()
    n = rows.size
    search = params.search if search is None else int(search)
    if guesses is None:
        guesses = np.zeros((n, 1, 2))
    guesses = np.asarray(guesses, np.float64).reshape(n, -1, 2)
    out = np.full((N_LAYERS, n), np.nan, np.float32)
    w = params.window
    taper = _taper(w)
    for s in range(0, n, params.batch):
        r, c = rows[s:s + params.batch], cols[s:s + params.batch]
        dy, dx, peak, ok_c, gy, gx = _best_guess(pre, post, r, c, guesses[s:s + params.batch], params, search)
        fa, ok_f, texture = _prepare(_windows(pre, r, c, w), params.max_nodata, taper)
        ok = ok_c & ok_f & (peak >= params.min_peak)
        quality = np.zeros(r.size)
        for _ in range(params.iterations):
            moved = shifted_windows(post, r, c, dy, dx, w)  # NaN outside or next to NaN
            fb, ok_m, _ = _prepare(moved, params.max_nodata, taper)
            ry, rx, quality, sig_y, sig_x = phase_plane_shift(fa, fb, params.frequency_cut)
            ok &= ok_m & np.isfinite(ry)
            # a residual beyond half a pixel means the coarse pass locked on a wrong peak
            ok &= (np.abs(ry) < 0.75) & (np.abs(rx) < 0.75)
            dy = dy + np.nan_to_num(ry)
            dx = dx + np.nan_to_num(rx)
        ok &= (np.abs(dy - gy) <= search) & (np.abs(dx - gx) <= search)
        ok &= (quality >= params.min_quality) & (texture >= params.min_texture)
        out[0, s:s + r.size] = np.where(ok, dy, np.nan)
        out[1, s:s + r.size] = np.where(ok, dx, np.nan)
        out[2, s:s + r.size] = quality
        out[3, s:s + r.size] = texture
        out[4, s:s + r.size] = np.where(ok, sig_y, np.nan)
        out[5, s:s + r.size] = np.where(ok, sig_x, np.nan)
        out[6, s:s + r.size] = peak
    return out
