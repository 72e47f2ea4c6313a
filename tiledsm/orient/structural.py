"""Structural tie-point matching: Wallis, Förstner, NCC along the RPC
"epipolar" curve, and probability relaxation.

The second tie-point extractor of :mod:`tiledsm.orient.tracks` (the point
matching of the deformation method), selected by
``OrientSpec(extractor="structural")`` (the default), its parameters
:class:`~tiledsm.orient.spec.StructuralParams` (``orient.tracks.structural``
in a recipe). In one reference tile:

1. :func:`wallis` filters both images with the same parameters (local
   contrast and brightness forced towards a target mean and standard
   deviation);
2. :func:`forstner` finds interest points in the filtered reference tile
   (gradient structure tensor: weight ``w = det / trace``, roundness
   ``q = 4 det / trace^2``, non-maximum suppression, sub-pixel position as
   the least-squares intersection of the edge lines in the window);
3. :func:`curve_candidates`: each point is localised by the reference RPC
   at heights across the guide's height range, spaced so that consecutive
   projections into the other image (plus the guide's shift) are at most
   ``curve_step_px`` apart; the zero-mean NCC of the point's template
   against the filtered other image is read along that curve (the largest
   within ``margin_px`` across it: the guide's shift leaves part of the
   relative bias there), and its
   ``top_k`` local maxima above ``min_ncc`` become candidates, each refined
   to the 2-D NCC peak near the curve (sub-pixel parabola): the final
   position is free across the curve too, so the tracks keep the relative
   bias the adjustment estimates;
4. :func:`relax` (structural matching, Barnard & Thompson 1980): initial
   probabilities from the NCC of each point's candidates plus a "no match"
   label; each candidate is supported by the neighbouring points (within
   ``radius_px``) whose candidates have a compatible parallax
   (``|ds| <= compat_px + max_gradient * distance``, a disparity-gradient
   limit); ``p <- p (A + B support)``, normalised, iterated; a point keeps
   its most probable candidate when that probability reaches ``min_prob``
   and its NCC ``accept_ncc``.

Every other image is matched on its own against the reference; a track is
the reference point and its matches.

Conventions: pixel coordinates GDAL (top-left image corner at (0, 0); the
centre of array element ``[i, j]`` at ``(i + .5, j + .5)``); heights metres
above the WGS84 ellipsoid; parallax ``s`` pixels of the other image along
the curve, from its low-height end.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from tiledsm.geometry.rpc import RPC
from tiledsm.io.scenes import read_window
from tiledsm.orient.spec import StructuralParams

__all__ = ["wallis", "forstner", "curve_candidates", "relax", "match_tile_structural"]


# ------------------------------------------------------------------ filters
def _local_mean(a: np.ndarray, ok: np.ndarray, size: int) -> np.ndarray:
    """Mean of ``a`` over the valid pixels of a ``size`` x ``size`` window."""
    from scipy.ndimage import uniform_filter

    num = uniform_filter(np.where(ok, a, 0.0), size, mode="constant")
    den = uniform_filter(ok.astype(np.float64), size, mode="constant")
    some = den > 0.5 / size**2  # at least one valid pixel (not filter round-off)
    return np.where(some, num / np.where(some, den, 1.0), np.nan)


def wallis(img: np.ndarray, params: StructuralParams = StructuralParams()) -> np.ndarray:
    """Wallis filter (Baltsavias 1991 formulation).

    ``out = r1 g + r0`` with ``r1 = c s_f / (c s_g + (1 - c) s_f)`` and
    ``r0 = b m_f + (1 - b - r1) m_g``: ``m_g``, ``s_g`` the local mean and
    standard deviation of the image over ``wallis_window`` (NaN pixels left
    out of the statistics), ``m_f``, ``s_f`` the targets, ``c`` the contrast
    and ``b`` the brightness constant.

    Parameters
    ----------
    img : numpy.ndarray
        2-D image, grey levels, NaN = no data.
    params : StructuralParams

    Returns
    -------
    numpy.ndarray
        float32, same shape, NaN where ``img`` is NaN.
    """
    g = np.asarray(img, np.float64)
    ok = np.isfinite(g)
    if not ok.any():
        return np.full(g.shape, np.nan, np.float32)
    g0 = g - np.mean(g[ok])  # centred: E[g^2] - E[g]^2 without cancellation
    mg = _local_mean(g0, ok, params.wallis_window)
    sg = np.sqrt(np.maximum(_local_mean(g0 * g0, ok, params.wallis_window) - mg * mg, 0.0))
    c, b, mf, sf = params.contrast, params.brightness, params.target_mean, params.target_std
    den = c * sg + (1.0 - c) * sf
    with np.errstate(invalid="ignore", divide="ignore"):
        r1 = np.where(den > 0, c * sf / den, 0.0)
    out = r1 * (g0 - mg) + b * mf + (1.0 - b) * (mg + g[ok].mean())
    return np.where(ok, out, np.nan).astype(np.float32)


def forstner(img: np.ndarray, params: StructuralParams = StructuralParams()) -> tuple[np.ndarray, np.ndarray]:
    """Förstner interest points (Förstner & Gülch 1987).

    Gradients by central differences; ``N`` their outer products summed
    over ``forstner_window``; weight ``w = det N / tr N``, roundness
    ``q = 4 det N / tr N^2``. Points: ``q >= min_roundness``,
    ``w > weight_factor * mean(w)``, ``w`` the maximum of its ``nms``
    neighbourhood (of points closer than ``nms / 2``, the strongest);
    position: the least-squares intersection of the lines through each
    window pixel normal to its gradient, ``N^-1 sum(g g^T x)``, kept only
    within ``max_offset_px`` of the maximum's pixel (in each axis; at most
    half the window). Windows touching NaN give no point.

    Parameters
    ----------
    img : numpy.ndarray
        2-D image (e.g. :func:`wallis` output), NaN = no data.
    params : StructuralParams

    Returns
    -------
    (pos, w) : (numpy.ndarray, numpy.ndarray)
        ``(n, 2)`` GDAL row/col in ``img`` (float) and ``(n,)`` weights,
        strongest first.
    """
    from scipy.ndimage import correlate1d, maximum_filter, uniform_filter

    g = np.asarray(img, np.float64)
    ok = np.isfinite(g)
    g = np.where(ok, g, 0.0)
    k = np.array([0.5, 0.0, -0.5])  # correlate: (a[i+1] - a[i-1]) / 2
    gr = correlate1d(g, k[::-1], axis=0, mode="nearest")
    gc = correlate1d(g, k[::-1], axis=1, mode="nearest")
    fw = params.forstner_window
    rr, cc = np.indices(g.shape, dtype=np.float64)
    nrr, nrc, ncc_ = (uniform_filter(a, fw) for a in (gr * gr, gr * gc, gc * gc))
    br = uniform_filter(gr * gr * rr + gr * gc * cc, fw)
    bc = uniform_filter(gr * gc * rr + gc * gc * cc, fw)
    det = nrr * ncc_ - nrc * nrc
    tr = nrr + ncc_
    valid = uniform_filter(ok.astype(np.float64), fw + 2) > 1.0 - 1e-9  # window and its gradients in data
    with np.errstate(invalid="ignore", divide="ignore"):
        w = np.where(valid & (tr > 0), det / tr, 0.0)
        q = np.where(valid & (tr > 0), 4.0 * det / (tr * tr), 0.0)
    if not valid.any():
        return np.zeros((0, 2)), np.zeros(0)
    thr = params.weight_factor * float(w[valid].mean())
    cand = (q >= params.min_roundness) & (w > thr) & (w > 0)
    cand &= w >= maximum_filter(w, params.nms, mode="constant")
    i, j = np.nonzero(cand)
    d = det[i, j]
    pr = (ncc_[i, j] * br[i, j] - nrc[i, j] * bc[i, j]) / d
    pc = (-nrc[i, j] * br[i, j] + nrr[i, j] * bc[i, j]) / d
    lim = min(params.max_offset_px, fw / 2.0)
    near = (np.abs(pr - i) <= lim) & (np.abs(pc - j) <= lim)
    pos = np.column_stack([pr, pc])[near] + 0.5
    wt = w[i, j][near]
    order = np.argsort(-wt, kind="stable")
    pos, wt = pos[order], wt[order]
    # a plateau of equal maxima (a symmetric corner) gives one point, the first
    keep = np.ones(len(pos), bool)
    if len(pos) > 1:
        from scipy.spatial import cKDTree

        for a, b in sorted(cKDTree(pos).query_pairs(params.nms / 2.0)):
            if keep[a]:
                keep[b] = False
    return pos[keep], wt[keep]


# ------------------------------------------------------------------ candidates
def _parabola(a, b, c):
    """Vertex offset of the parabola through ``(-1, a), (0, b), (1, c)``
    (0 where it is not a maximum)."""
    den = a - 2.0 * b + c
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den < 0, 0.5 * (a - c) / den, 0.0)


def curve_candidates(res: np.ndarray, curve: np.ndarray, params: StructuralParams = StructuralParams()) -> dict:
    """Candidates of one point along its curve in a dense NCC map.

    Parameters
    ----------
    res : numpy.ndarray
        ``(h, w)`` dense NCC map (``cv2.matchTemplate`` output: one value
        per template position).
    curve : numpy.ndarray
        ``(m, 2)`` the curve's points in ``res``'s array-index coordinates
        (template centre minus half the template), low height first,
        consecutive points at most ``curve_step_px`` apart.
    params : StructuralParams

    Returns
    -------
    dict
        ``pos`` ``(k, 2)`` sub-pixel array-index positions of the refined
        2-D peaks, ``ncc`` ``(k,)``, ``s`` ``(k,)`` parallax (pixels along
        the curve), ``t`` ``(k,)`` fractional curve index; best first,
        ``k <= top_k``.
    """
    from scipy.ndimage import map_coordinates, maximum_filter, maximum_filter1d

    empty = {"pos": np.zeros((0, 2)), "ncc": np.zeros(0), "s": np.zeros(0), "t": np.zeros(0)}
    r = int(np.ceil(params.margin_px))
    band = maximum_filter(res, 2 * r + 1, mode="nearest") if r > 0 else res
    prof = map_coordinates(band, curve.T, order=1, mode="constant", cval=-1.0)
    arc = np.r_[0.0, np.cumsum(np.hypot(*np.diff(curve, axis=0).T))]
    step = max(arc[-1] / max(len(curve) - 1, 1), 1e-6)
    sep = max(1, int(round(params.peak_separation_px / step)))
    peak = (prof >= params.min_ncc) & (prof >= maximum_filter1d(prof, 2 * sep + 1, mode="constant", cval=-2.0))
    t = np.flatnonzero(peak)
    if t.size == 0:
        return empty
    runs = np.split(t, np.flatnonzero(np.diff(t) > 1) + 1)  # a plateau (the band's max) counts once
    t = np.array([run[len(run) // 2] for run in runs])
    t = t[np.argsort(-prof[t], kind="stable")][: 2 * params.top_k]
    out_pos, out_ncc, out_t, seen = [], [], [], set()
    for ti in t:
        u, v = np.rint(curve[ti]).astype(int)
        u0, u1 = max(u - r, 1), min(u + r + 1, res.shape[0] - 1)  # a peak on the border has no parabola
        v0, v1 = max(v - r, 1), min(v + r + 1, res.shape[1] - 1)
        if u1 <= u0 or v1 <= v0:
            continue
        sub = res[u0:u1, v0:v1]
        a, b = np.unravel_index(int(np.argmax(sub)), sub.shape)
        iu, iv = u0 + a, v0 + b
        nb = max(res[iu - 1, iv], res[iu + 1, iv], res[iu, iv - 1], res[iu, iv + 1])
        if (iu, iv) in seen or res[iu, iv] < max(params.min_ncc, nb):  # not a peak: it lies past margin_px
            continue
        seen.add((iu, iv))
        fu = iu + _parabola(res[iu - 1, iv], res[iu, iv], res[iu + 1, iv])
        fv = iv + _parabola(res[iu, iv - 1], res[iu, iv], res[iu, iv + 1])
        out_pos.append((fu, fv))
        out_ncc.append(res[iu, iv])
        tt = float(ti)
        if 0 < ti < len(prof) - 1:
            tt += float(_parabola(prof[ti - 1], prof[ti], prof[ti + 1]))
        out_t.append(tt)
        if len(out_pos) == params.top_k:
            break
    if not out_pos:
        return empty
    tt = np.clip(np.array(out_t), 0, len(curve) - 1)
    return {"pos": np.array(out_pos, float), "ncc": np.array(out_ncc, float),
            "s": np.interp(tt, np.arange(len(arc)), arc), "t": tt}


# ------------------------------------------------------------------ relaxation
def relax(ncc: np.ndarray, s: np.ndarray, xy: np.ndarray,
          params: StructuralParams = StructuralParams()) -> tuple[np.ndarray, np.ndarray]:
    """Structural matching by probability relaxation (module docstring).

    Parameters
    ----------
    ncc : numpy.ndarray
        ``(n, K)`` NCC of each point's candidates, NaN where none.
    s : numpy.ndarray
        ``(n, K)`` their parallax, pixels along the curve.
    xy : numpy.ndarray
        ``(n, 2)`` the points' positions in the reference image, pixels.
    params : StructuralParams

    Returns
    -------
    (choice, prob) : (numpy.ndarray, numpy.ndarray)
        ``(n,)`` index of the chosen candidate (-1: no match) and its
        final probability.

    Notes
    -----
    Initial weights ``w = (ncc - min_ncc) / (1 - min_ncc)`` clipped to
    [0, 1]; ``p(none) = 1 - max w``, ``p(a) = (1 - p(none)) w_a / sum w``.
    Support ``q_i(a)`` = mean over the neighbours ``j`` of
    ``max_b p_j(b)`` over their candidates ``b`` compatible with ``a``.
    A point without neighbours keeps its initial probabilities.
    """
    from scipy.spatial import cKDTree

    ncc = np.asarray(ncc, float)
    n, k = ncc.shape
    if n == 0:
        return np.zeros(0, int), np.zeros(0)
    have = np.isfinite(ncc)
    w = np.where(have, np.clip((ncc - params.min_ncc) / (1.0 - params.min_ncc), 0.0, 1.0), 0.0)
    p = np.zeros((n, k + 1))
    p[:, 0] = 1.0 - w.max(axis=1)
    tot = w.sum(axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        p[:, 1:] = np.where(tot > 0, w / tot, 0.0) * (1.0 - p[:, :1])
    m = min(params.max_neighbours, n - 1)
    if m > 0:
        dist, nb = cKDTree(xy).query(xy, k=m + 1, distance_upper_bound=params.radius_px)
        dist, nb = dist[:, 1:], nb[:, 1:]
        ok = np.isfinite(dist)
        nb = np.where(ok, nb, 0)
        cnt = ok.sum(axis=1)
        sj = np.where(have, s, np.nan)[nb]  # (n, M, K)
        tol = params.compat_px + params.max_gradient * np.where(ok, dist, 0.0)
        comp = np.abs(np.where(have, s, np.nan)[:, :, None, None] - sj[:, None]) <= tol[:, None, :, None]
        comp &= ok[:, None, :, None]  # (n, K, M, K)
        for _ in range(params.iterations):
            pj = p[nb, 1:]  # (n, M, K)
            q = np.where(comp, pj[:, None], 0.0).max(axis=-1).sum(axis=-1)
            with np.errstate(invalid="ignore", divide="ignore"):
                q = np.where(cnt[:, None] > 0, q / cnt[:, None], 0.0)
            new = p.copy()
            new[:, 1:] *= params.relax_a + params.relax_b * q
            new /= new.sum(axis=1, keepdims=True)
            new[cnt == 0] = p[cnt == 0]
            change = float(np.max(np.abs(new - p)))
            p = new
            if change < params.tol:
                break
    lab = np.argmax(p, axis=1)
    prob = p[np.arange(n), lab]
    choice = np.where((lab > 0) & (prob >= params.min_prob), lab - 1, -1)
    return choice, np.where(choice >= 0, prob, 0.0)


# ------------------------------------------------------------------ one tile
def _filtered(path, a0, a1, params: StructuralParams) -> np.ndarray:
    """Wallis-filtered window ``[a0, a1)`` (array indices) of an image."""
    hw = params.wallis_window // 2 + 1
    raw = read_window(path, a0[0] - hw, a1[0] + hw, a0[1] - hw, a1[1] + hw)
    return wallis(raw, params)[hw:-hw, hw:-hw]


def match_tile_structural(
    paths: Sequence[str | Path],
    rpcs: Sequence[RPC],
    guide,
    window: tuple[int, int, int, int],
    params=StructuralParams(),
) -> dict:
    """Structural matching of one reference tile ``(r0, r1, c0, c1)`` into
    every other image (module docstring); same contract as
    :func:`tiledsm.orient.tracks.match_tile`.

    Parameters
    ----------
    paths, rpcs : sequence
        Images (band 1) and their RPCs; the first is the reference.
    guide : Guide
        Anything with ``h_range`` (metres) and ``shift`` (``(n_images, 2)``
        row/col added to the RPC predictions).
    window : (int, int, int, int)
        Reference tile, array indices.
    params : StructuralParams or TrackParams
        A :class:`~tiledsm.orient.spec.TrackParams` gives its
        ``structural`` field.

    Returns
    -------
    dict
        ``pos``: ``(n_images, n, 2)`` GDAL row/col (NaN: no match),
        ``ncc``: ``(n_images, n)``.
    """
    import cv2

    sp = params if isinstance(params, StructuralParams) else params.structural
    r0, r1, c0, c1 = window
    half = sp.template // 2
    halo = sp.wallis_window // 2 + max(half, sp.forstner_window // 2 + 1) + 2
    ref = wallis(read_window(paths[0], r0 - halo, r1 + halo, c0 - halo, c1 + halo), sp)
    pts, _ = forstner(ref, sp)
    inner = ((pts[:, 0] >= halo) & (pts[:, 0] < halo + r1 - r0) & (pts[:, 1] >= halo) & (pts[:, 1] < halo + c1 - c0)
             if len(pts) else np.zeros(0, bool))
    pts = pts[inner][: sp.points_per_tile]
    tmpls = [cv2.getRectSubPix(ref, (sp.template, sp.template), (float(c - 0.5), float(r - 0.5))) for r, c in pts]
    keep = np.array([bool(np.all(np.isfinite(t))) and t.std() > 0 for t in tmpls], bool)
    pts, tmpls = pts[keep] if len(pts) else pts, [t for t, k in zip(tmpls, keep) if k]
    n_img, n = len(paths), len(pts)
    pos = np.full((n_img, n, 2), np.nan)
    ncc = np.full((n_img, n), np.nan)
    if n == 0:
        return {"pos": pos, "ncc": ncc}
    p0 = pts + np.array([r0 - halo, c0 - halo])
    pos[0], ncc[0] = p0, 1.0
    lo, hi = guide.h_range
    lon2, lat2 = rpcs[0].localize(p0[:, 0:1], p0[:, 1:2], np.array([[lo, hi]]))
    reach = half + int(np.ceil(sp.margin_px)) + 2
    for k in range(1, n_img):
        ends = np.stack(rpcs[k].project(lon2, lat2, np.broadcast_to([[lo, hi]], lon2.shape)), -1)
        length = np.hypot(*(ends[:, 1] - ends[:, 0]).T)
        m = max(2, int(np.ceil(np.nanmax(length) / sp.curve_step_px)) + 1)
        hs = np.linspace(lo, hi, m)
        lon, lat = rpcs[0].localize(p0[:, 0:1], p0[:, 1:2], hs[None])
        q = np.stack(rpcs[k].project(lon, lat, np.broadcast_to(hs, lon.shape)), -1) + guide.shift[k]  # (n, m, 2)
        okq = np.all(np.isfinite(q), axis=(1, 2))
        if not okq.any():
            continue
        qmin = np.floor(np.nanmin(q, axis=1) - 0.5).astype(int) - reach
        qmax = np.ceil(np.nanmax(q, axis=1) - 0.5).astype(int) + reach + 1
        bmin, bmax = qmin[okq].min(axis=0), qmax[okq].max(axis=0)
        whole = max(bmax - bmin) <= sp.max_window
        big = _filtered(paths[k], bmin, bmax, sp) if whole else None
        cands = []
        for i in range(n):
            if not okq[i]:
                cands.append(None)
                continue
            a0, a1 = qmin[i], qmax[i]
            srch = (big[a0[0] - bmin[0]: a1[0] - bmin[0], a0[1] - bmin[1]: a1[1] - bmin[1]] if whole
                    else _filtered(paths[k], a0, a1, sp))
            if not np.all(np.isfinite(srch)):
                srch = np.where(np.isfinite(srch), srch, np.nanmean(srch) if np.isfinite(srch).any() else 0.0)
            res = cv2.matchTemplate(srch.astype(np.float32), tmpls[i], cv2.TM_CCOEFF_NORMED)
            c = curve_candidates(res, q[i] - 0.5 - a0 - half, sp)
            c["pos"] = c["pos"] + a0 + half + 0.5  # GDAL
            cands.append(c)
        kk = sp.top_k
        cn = np.full((n, kk), np.nan)
        cs = np.full((n, kk), np.nan)
        cp = np.full((n, kk, 2), np.nan)
        for i, c in enumerate(cands):
            if c is not None and len(c["ncc"]):
                j = len(c["ncc"])
                cn[i, :j], cs[i, :j], cp[i, :j] = c["ncc"], c["s"], c["pos"]
        choice, _ = relax(cn, cs, p0, sp)
        sel = np.flatnonzero(choice >= 0)
        sel = sel[cn[sel, choice[sel]] >= sp.accept_ncc]
        pos[k, sel] = cp[sel, choice[sel]]
        ncc[k, sel] = cn[sel, choice[sel]]
    return {"pos": pos, "ncc": ncc}
