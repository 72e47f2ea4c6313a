"""Coarse to fine: displacements far beyond the correlation's search
(pure numpy, on one block of the field).

A surface rupture moves the ground by metres: 10 to 30 px at 0.5 m, where a
single-level correlation searching ``search`` px around zero finds nothing.
The block is first correlated at ``f = 2**levels`` times coarser pixels
(box means of ``f x f``: the same correlator, ``search`` px there reaching
``search * f`` px), on a lattice of coarse cells every ``step * f``
full-resolution px. Each full-resolution cell then takes **several
candidates** from that level -- the median of the 3 x 3 coarse cells
around it and each of those cells' own value, deduplicated within
``refine_search / 2`` px -- and the full-resolution correlation searches
``refine_search`` px around each, keeping the candidate whose
phase-correlation peak is highest (:func:`tiledsm.displace.correlate.
correlate_windows` with ``guesses``).

Why several candidates and not one median-filtered predictor: at a fault
the coarse windows (``f`` times wider) straddle the trace over ``f``
times more cells, and a phase correlation does not average two motions,
it picks the dominant one; so the coarse cells next to the trace carry
one side's motion or the other's, and a single predictor (median or not)
is the wrong side's for the full-resolution cells just across it, which
then find no peak within ``refine_search`` (NaN) or a wrong one: the
discontinuity smears by a coarse cell. With both sides' values among the
candidates, a full-resolution window on one side matches that side's
candidate with a clear peak and the other's with noise only, so the step
is placed by the full-resolution windows, as in a single-level
correlation. Away from discontinuities the candidates agree and one is
kept: the cost is the single level's plus the coarse level's (``1 /
f**2`` of the cells) plus the few cells along the trace.

The full-resolution measure, its precision and its formal sigma are those
of the single-level correlation (the same windows, the same fine passes):
the pyramid only chooses where the coarse stage looks.

Block independence: the coarse lattice is global (coarse cell ``k`` is
centred on full-resolution coordinate ``(k + 0.5) * step * f``) and the
box means are aligned on the global ``f``-pixel lattice, so a cell's value
does not depend on the chunking, given the halo
:attr:`CorrelationParams.halo`.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from tiledsm.displace.correlate import CorrelationParams, correlate_windows

__all__ = ["box_mean", "coarse_candidates", "correlate_cells"]

#: share of NaN pixels a coarse window may hold (its value is a candidate, verified at full resolution)
COARSE_MAX_NODATA = 0.5


def box_mean(img: np.ndarray, f: int, phase: tuple[int, int]) -> tuple[np.ndarray, tuple[int, int]]:
    """Means of ``f x f`` pixel boxes (NaN if any pixel is), the first box
    starting at array index ``phase`` (rows, columns); returns the coarse
    image and the array index of its first box's first pixel."""
    r0, c0 = phase
    a = img[r0:, c0:]
    ny, nx = a.shape[0] // f, a.shape[1] // f
    a = a[: ny * f, : nx * f].reshape(ny, f, nx, f)
    return a.mean(axis=(1, 3)), (r0, c0)


def _dedupe(cands: np.ndarray, tol: float) -> np.ndarray:
    """``cands`` ``(n, K, 2)`` with each candidate within ``tol`` px (both
    axes) of an earlier one of its cell set to NaN."""
    c = cands.copy()
    k = c.shape[1]
    for j in range(1, k):
        near = (np.abs(c[:, :j] - c[:, j:j + 1]) <= tol).all(axis=2).any(axis=1)
        c[near, j] = np.nan
    return c


def coarse_candidates(pre: np.ndarray, post: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                      params: CorrelationParams, origin: tuple[int, int], halo: int) -> np.ndarray:
    """Candidate displacements of full-resolution cells from the coarsest level.

    Parameters
    ----------
    pre, post : ndarray
        The block's full-resolution pixels plus ``halo`` on every side.
    rows, cols : ndarray
        Global indices of the block's output cells (2-D, same shape).
    params : CorrelationParams
        With ``levels > 0``.
    origin : (int, int)
        Global indices of the block's first output cell.

    Returns
    -------
    ndarray
        ``(n, 26, 2)`` candidates ``(dy, dx)``, full-resolution pixels, NaN
        where none (module notes): the median of the 3 x 3 coarse cells
        around, their values, and, where none of them has one, the values
        of the 5 x 5 ring around them.
    """
    f, s = params.factor, params.step
    # global full-resolution pixel of the block arrays' [0, 0], and the phase that aligns boxes on the global lattice
    g0 = (origin[0] * s - halo, origin[1] * s - halo)
    phase = tuple(int((-g) % f) for g in g0)
    pre_c, _ = box_mean(pre, f, phase)
    post_c, _ = box_mean(post, f, phase)
    # coarse cells k (global) around the block's cells: k = i // f - 2 ... i // f + 2
    k_r = np.arange(rows.min() // f - 2, rows.max() // f + 3)
    k_c = np.arange(cols.min() // f - 2, cols.max() // f + 3)
    # centre of coarse cell k: full-resolution (k + 0.5) * s * f, coarse pixel (k + 0.5) * s (global); local coarse
    # pixel = that minus the coarse image's first pixel ((g0 + phase) / f, an integer)
    lr = ((k_r + 0.5) * s - (g0[0] + phase[0]) // f).astype(np.int64)
    lc = ((k_c + 0.5) * s - (g0[1] + phase[1]) // f).astype(np.int64)
    R, C = np.meshgrid(lr, lc, indexing="ij")
    # a coarse value is only a hypothesis the full resolution verifies: windows half outside the data still give one
    coarse_params = dataclasses.replace(params, levels=0, max_nodata=max(params.max_nodata, COARSE_MAX_NODATA))
    out = correlate_windows(pre_c, post_c, R.ravel(), C.ravel(), coarse_params)
    pred = np.stack([out[0], out[1]], axis=-1).reshape(len(lr), len(lc), 2) * f
    # each cell's 5 x 5 coarse neighbourhood: the inner 3 x 3, and the outer ring where the inner has no value (an
    # edge of the data, a decorrelated patch)
    off = np.arange(-2, 3)
    ir = (rows.ravel() // f - k_r[0])[:, None] + off[None, :]
    ic = (cols.ravel() // f - k_c[0])[:, None] + off[None, :]
    nb = pred[ir[:, :, None], ic[:, None, :]].reshape(rows.size, 25, 2)
    inner_idx = np.array([12, 7, 11, 13, 17, 6, 8, 16, 18])  # the cell's own coarse cell first, then its 8 neighbours
    ring_idx = np.setdiff1d(np.arange(25), inner_idx)
    inner, ring = nb[:, inner_idx], nb[:, ring_idx].copy()
    has_inner = np.isfinite(inner).all(axis=2).any(axis=1)
    ring[has_inner] = np.nan
    none = ~np.isfinite(inner).any(axis=1)  # no coarse value around: no median (not numpy's All-NaN warning)
    med = np.nanmedian(np.where(none[:, None, :], 0.0, inner), axis=1)
    med = np.where(none, np.nan, med)[:, None, :]
    # the median first (ties go to it), then the neighbours
    cands = np.concatenate([med, inner, ring], axis=1)
    cands[~np.isfinite(cands).all(axis=2)] = np.nan
    return _dedupe(cands, params.refine_search / 2)


def correlate_cells(pre: np.ndarray, post: np.ndarray, n_rows: int, n_cols: int, params: CorrelationParams,
                    halo: int, origin: tuple[int, int] = (0, 0)) -> np.ndarray:
    """``(N_LAYERS, n_rows, n_cols)`` cells of one block: ``pre``/``post``
    are the block's pixels plus ``halo`` on every side (NaN past the
    grid); ``origin`` the global indices of its first cell (the coarse
    lattice is global). One level, or coarse to fine (module notes)."""
    s = params.step
    # window centres (GDAL coordinates of the block): the middle of each output cell
    rows = halo + (np.arange(n_rows) + 0.5) * s
    cols = halo + (np.arange(n_cols) + 0.5) * s
    R, C = np.meshgrid(rows.astype(np.int64), cols.astype(np.int64), indexing="ij")
    if not params.levels:
        out = correlate_windows(pre, post, R.ravel(), C.ravel(), params)
    else:
        gi, gj = np.meshgrid(origin[0] + np.arange(n_rows), origin[1] + np.arange(n_cols), indexing="ij")
        guesses = coarse_candidates(pre, post, gi, gj, params, origin, halo)
        out = correlate_windows(pre, post, R.ravel(), C.ravel(), params, guesses=guesses,
                                search=params.refine_search)
    return out.reshape(out.shape[0], n_rows, n_cols)
