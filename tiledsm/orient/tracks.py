"""Multi-view tie-point tracks over whole scenes, tiled.

The first image is the reference. Its tiles are the tasks of one
:func:`dask.array.map_blocks` call (a 40k-line scene never sits in memory:
a task reads its tile plus a template halo, and in every other image only
the window its points can fall in):

1. a coarse guide (:func:`coarse_guide`): SIFT matches between overviews
   (:func:`tiledsm.match.tiepoints.match_tiepoints`), intersected with the
   RPCs as they are, give the scene's height range and, per image, the
   translation that makes the RPC prediction land on the matches (the
   relative bias across the epipolar direction; along it, the bias is
   absorbed by the heights);
2. in each reference tile, corner features (Shi-Tomasi,
   ``cv2.goodFeaturesToTrack``); each one is localised at the two ends of
   the height range and projected into every other image: the segment
   between the two projections, shifted by the guide and widened by a
   margin, is where ``cv2.matchTemplate`` (zero-mean NCC) looks; the NCC
   peak is refined to a sub-pixel position by a parabola in each axis
   (``OrientSpec.extractor="features"``); or, the default, structural
   matching (``"structural"``, :mod:`tiledsm.orient.structural`: Wallis,
   Förstner points, NCC along the RPC curve, probability relaxation; more
   matches, and more of them within 1 px of the truth, on synthetic
   scenes: ``benchmarks/tiepoints.py``);
3. per image pair, P2L mismatch rejection (:mod:`tiledsm.orient.p2l`).

A track is a reference point and its matches in the other images (two or
more views).

Conventions: pixel coordinates GDAL (top-left image corner at (0, 0); the
centre of array element ``[i, j]`` at ``(i + .5, j + .5)``); heights metres
above the WGS84 ellipsoid.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from tiledsm.errors import MatchingError
from tiledsm.geometry.rpc import RPC
from tiledsm.io.scenes import read_window
from tiledsm.orient.p2l import p2l_filter
from tiledsm.orient.spec import OrientSpec, TrackParams
from tiledsm.orient.structural import match_tile_structural

__all__ = ["Guide", "Tracks", "EXTRACTORS", "coarse_guide", "match_tile", "tie_point_tracks",
           "read_window"]

#: Tie-point extractors by ``OrientSpec.extractor`` name: ``f(paths, rpcs,
#: guide, window, params: TrackParams) -> {"pos", "ncc"}`` (see
#: :func:`match_tile`); the spec's ``Literal`` names the same keys.
#: Filled below :func:`match_tile` (empty only while this module loads).
EXTRACTORS: dict[str, Callable[..., dict]] = {}


@dataclass(frozen=True)
class Guide:
    """Where to look: the height range and per-image prediction shifts.

    Attributes
    ----------
    h_range : (float, float)
        Metres, ellipsoidal, as seen through the RPCs as they are.
    shift : numpy.ndarray
        ``(n_images, 2)`` row/col translation added to the RPC prediction
        in each image (0 for the reference).
    n_matches : tuple of int
        Coarse matches used per image (0 for the reference).
    """

    h_range: tuple[float, float]
    shift: np.ndarray
    n_matches: tuple[int, ...]


@dataclass(frozen=True)
class Tracks:
    """Tie-point tracks.

    Attributes
    ----------
    pos : numpy.ndarray
        ``(n_images, n, 2)`` row/col of each track in each image (GDAL
        convention), NaN where the track has no match.
    ncc : numpy.ndarray
        ``(n_images, n)`` NCC of each match (1 in the reference).
    rejected_p2l : tuple of int
        Matches rejected by P2L per image.
    """

    pos: np.ndarray
    ncc: np.ndarray
    rejected_p2l: tuple[int, ...]

    @property
    def n(self) -> int:
        return int(self.pos.shape[1])

    def observations(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(img, pt, row, col)`` of every measurement."""
        ok = np.isfinite(self.pos[..., 0])
        img, pt = np.nonzero(ok)
        return img, pt, self.pos[img, pt, 0], self.pos[img, pt, 1]


# ------------------------------------------------------------------ reading
def _overview(path: str | Path, size: int) -> tuple[np.ndarray, tuple[float, float]]:
    """Area-averaged overview (longest side <= size) and its (row, col)
    scale factors to full-image pixels."""
    import rasterio
    from rasterio.enums import Resampling
    from rasterio.errors import NotGeoreferencedWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with rasterio.open(path) as ds:
            f = max(1, int(np.ceil(max(ds.height, ds.width) / size)))
            oh, ow = max(1, ds.height // f), max(1, ds.width // f)
            a = ds.read(1, out_shape=(oh, ow), masked=True, resampling=Resampling.average)
            return a.astype(np.float32).filled(np.nan), (ds.height / oh, ds.width / ow)


# ------------------------------------------------------------------ guide
def _across_curve(rpc0: RPC, rpcj: RPC, p0: np.ndarray, pj: np.ndarray, h: np.ndarray,
                  dh: float = 50.0) -> tuple[np.ndarray, np.ndarray]:
    """Where ``pj`` lies with respect to the curve of ``p0`` in image j.

    The curve is the projection into image j of the reference pixel ``p0``
    localised at every height; near a point it is a straight segment, so
    two Gauss-Newton steps on the height find the foot of the
    perpendicular from ``pj``.

    Returns
    -------
    dev : numpy.ndarray
        ``(n, 2)`` row/col from the curve's nearest point to ``pj``, pixels.
    h : numpy.ndarray
        ``(n,)`` height of that point, metres (ellipsoidal).
    """
    # a step may not leave the cameras' height validity range (localisation diverges far outside)
    lo = max(r.height_off - abs(r.height_scale) for r in (rpc0, rpcj))
    hi = min(r.height_off + abs(r.height_scale) for r in (rpc0, rpcj))
    h = np.clip(np.asarray(h, float), lo, hi)
    for _ in range(3):
        lon, lat = rpc0.localize(p0[:, 0], p0[:, 1], h)
        a = np.stack(rpcj.project(lon, lat, h), -1)
        lon, lat = rpc0.localize(p0[:, 0], p0[:, 1], h + dh)
        d = (np.stack(rpcj.project(lon, lat, h + dh), -1) - a) / dh  # pixels per metre along the curve
        h = np.clip(h + np.sum((pj - a) * d, axis=1) / np.sum(d * d, axis=1), lo, hi)
    lon, lat = rpc0.localize(p0[:, 0], p0[:, 1], h)
    return pj - np.stack(rpcj.project(lon, lat, h), -1), h


def coarse_guide(paths: Sequence[str | Path], rpcs: Sequence[RPC], params: TrackParams = TrackParams()) -> Guide:
    """Height range and prediction shifts from overview SIFT matches
    between the reference and every other image (module docstring).

    Raises
    ------
    MatchingError
        An image shares fewer than 8 coarse matches with the reference.
    """
    from tiledsm.match.tiepoints import match_tiepoints
    from tiledsm.orient.adjust import intersect

    ref, (sr, sc) = _overview(paths[0], params.coarse_size)
    shifts = [np.zeros(2)]
    counts = [0]
    heights = []
    for j in range(1, len(paths)):
        other, (tr, tc) = _overview(paths[j], params.coarse_size)
        q0, qj = match_tiepoints(ref, other, max_size=params.coarse_size)
        p0 = q0 * np.array([sr, sc])
        pj = qj * np.array([tr, tc])
        if len(p0) < 8:
            raise MatchingError(f"tie points: only {len(p0)} coarse matches between {Path(paths[0]).name} "
                                f"and {Path(paths[j]).name} (need >= 8)")
        n = len(p0)
        img = np.r_[np.zeros(n, int), np.full(n, 1)]
        pt = np.r_[np.arange(n), np.arange(n)]
        g, _ = intersect([rpcs[0], rpcs[j]], img, pt, np.r_[p0[:, 0], pj[:, 0]], np.r_[p0[:, 1], pj[:, 1]], n)
        ok = np.all(np.isfinite(g), axis=1)
        # the extractors hold the reference point fixed and search along its curve in image j:
        # the shift is what is left across that curve (the intersection's residual would split
        # it between both images and count its along-curve part twice, once as height)
        dev, hj = _across_curve(rpcs[0], rpcs[j], p0[ok], pj[ok], g[ok, 2])
        fin = np.all(np.isfinite(dev), axis=1)
        dev, hj = dev[fin], hj[fin]
        shift = np.median(dev, axis=0)
        good = np.hypot(*(dev - shift).T) < max(3.0, 3 * float(np.median(np.hypot(*(dev - shift).T))))
        shifts.append(shift)
        counts.append(int(good.sum()))
        heights.append(hj[good])
    h = np.concatenate(heights)
    lo, hi = np.percentile(h, [1, 99]) if h.size >= 20 else (h.min(), h.max())
    m = params.height_margin_m + 0.1 * (hi - lo)
    return Guide((float(lo - m), float(hi + m)), np.array(shifts), tuple(counts))


# ------------------------------------------------------------------ one tile
def _subpixel(res: np.ndarray, i: int, j: int) -> tuple[float, float]:
    def para(a, b, c):
        den = a - 2 * b + c
        return 0.0 if den >= 0 else 0.5 * (a - c) / den

    return i + para(res[i - 1, j], res[i, j], res[i + 1, j]), j + para(res[i, j - 1], res[i, j], res[i, j + 1])


def _features(tile: np.ndarray, halo: int, params: TrackParams) -> np.ndarray:
    """Array indices ``(i, j)`` (in the tile with halo) of corner features
    of the tile interior."""
    import cv2

    ok = np.isfinite(tile)
    if ok.sum() < 16:
        return np.zeros((0, 2), int)
    lo, hi = np.percentile(tile[ok], [1, 99])
    u8 = np.clip((np.where(ok, tile, lo) - lo) * (255.0 / max(hi - lo, 1e-6)), 0, 255).astype(np.uint8)
    mask = np.zeros(tile.shape, np.uint8)
    mask[halo:-halo, halo:-halo] = 1
    mask &= cv2.erode(ok.astype(np.uint8), np.ones((2 * halo + 1, 2 * halo + 1), np.uint8))
    pts = cv2.goodFeaturesToTrack(u8, params.features_per_tile, params.quality, params.min_distance, mask=mask,
                                  blockSize=5)
    if pts is None:
        return np.zeros((0, 2), int)
    xy = np.rint(pts.reshape(-1, 2)).astype(int)
    return xy[:, ::-1]


def match_tile(
    paths: Sequence[str | Path],
    rpcs: Sequence[RPC],
    guide: Guide,
    window: tuple[int, int, int, int],
    params: TrackParams = TrackParams(),
) -> dict:
    """Features of one reference tile ``(r0, r1, c0, c1)`` matched into
    every other image (module docstring, step 2).

    Returns
    -------
    dict
        ``pos``: ``(n_images, n, 2)`` GDAL row/col (NaN: no match),
        ``ncc``: ``(n_images, n)``.
    """
    import cv2

    r0, r1, c0, c1 = window
    half = params.template // 2
    halo = half + 2
    tile = read_window(paths[0], r0 - halo, r1 + halo, c0 - halo, c1 + halo)
    ij = _features(tile, halo, params)
    n_img = len(paths)
    pos = np.full((n_img, len(ij), 2), np.nan)
    ncc = np.full((n_img, len(ij)), np.nan)
    if len(ij) == 0:
        return {"pos": pos, "ncc": ncc}
    p0 = ij + np.array([r0 - halo, c0 - halo]) + 0.5
    pos[0], ncc[0] = p0, 1.0
    tmpls = [tile[i - half: i + half + 1, j - half: j + half + 1] for i, j in ij]
    lo, hi = guide.h_range
    lon, lat = rpcs[0].localize(p0[:, 0:1], p0[:, 1:2], np.array([[lo, hi]]))
    reach = half + int(np.ceil(params.margin_px)) + 2
    for k in range(1, n_img):
        q = np.stack(rpcs[k].project(lon, lat, np.broadcast_to([[lo, hi]], lon.shape)), -1) + guide.shift[k]
        qmin = np.floor(q.min(axis=1) - 0.5).astype(int) - reach  # array indices
        qmax = np.ceil(q.max(axis=1) - 0.5).astype(int) + reach + 1
        ok = np.all(np.isfinite(q), axis=(1, 2))
        if not ok.any():
            continue
        bmin, bmax = qmin[ok].min(axis=0), qmax[ok].max(axis=0)
        whole = max(bmax - bmin) <= params.max_window
        big = read_window(paths[k], bmin[0], bmax[0], bmin[1], bmax[1]) if whole else None
        for n in np.flatnonzero(ok):
            t = tmpls[n]
            if not np.all(np.isfinite(t)) or t.std() < params.min_std:
                continue
            a0, a1 = qmin[n], qmax[n]
            if whole:
                s = big[a0[0] - bmin[0]: a1[0] - bmin[0], a0[1] - bmin[1]: a1[1] - bmin[1]]
            else:
                s = read_window(paths[k], a0[0], a1[0], a0[1], a1[1])
            if not np.all(np.isfinite(s)):
                s = np.where(np.isfinite(s), s, np.nanmean(s) if np.isfinite(s).any() else 0.0)
            if s.shape[0] < t.shape[0] + 2 or s.shape[1] < t.shape[1] + 2:
                continue
            res = cv2.matchTemplate(s.astype(np.float32), t.astype(np.float32), cv2.TM_CCOEFF_NORMED)
            i, j = np.unravel_index(int(np.argmax(res)), res.shape)
            if res[i, j] < params.min_ncc or not (0 < i < res.shape[0] - 1 and 0 < j < res.shape[1] - 1):
                continue
            fi, fj = _subpixel(res, i, j)
            pos[k, n] = (a0[0] + fi + half + 0.5, a0[1] + fj + half + 0.5)
            ncc[k, n] = res[i, j]
    return {"pos": pos, "ncc": ncc}


EXTRACTORS.update(features=match_tile, structural=match_tile_structural)


# ------------------------------------------------------------------ scene
def _tile_task(paths, rpcs, guide, shape, spec: OrientSpec, block_info=None):
    (bi, bj) = block_info[None]["chunk-location"]
    t = spec.tile
    win = (bi * t, min((bi + 1) * t, shape[0]), bj * t, min((bj + 1) * t, shape[1]))
    out = np.empty((1, 1), object)
    out[0, 0] = EXTRACTORS[spec.extractor](paths, rpcs, guide, win, spec.tracks)
    return out


def tie_point_tracks(
    paths: Sequence[str | Path],
    rpcs: Sequence[RPC],
    spec: OrientSpec = OrientSpec(),
    guide: Guide | None = None,
    scheduler: str | None = None,
) -> tuple[Tracks, Guide]:
    """Multi-view tie-point tracks of a block of images (module docstring).

    Parameters
    ----------
    paths : sequence of path-like
        Images (band 1 is used); the first is the reference.
    rpcs : sequence of RPC
        Their cameras (GDAL convention, as they are: biased is fine).
    spec : OrientSpec
        Its ``tile`` (reference tile side, pixels: one task per tile),
        ``extractor`` (a key of :data:`EXTRACTORS`) and ``tracks`` (the
        matching's parameters) are read.
    guide : Guide, optional
        Default: :func:`coarse_guide`.
    scheduler : str, optional
        Dask scheduler for the tile tasks (default: the current one).

    Returns
    -------
    (Tracks, Guide)
    """
    import dask
    import dask.array as da
    import rasterio

    if len(paths) < 2:
        raise MatchingError(f"tie points: need >= 2 images, got {len(paths)}")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with rasterio.open(paths[0]) as ds:
            shape = (ds.height, ds.width)
    guide = guide or coarse_guide(paths, rpcs, spec.tracks)
    t = spec.tile
    nb = (-(-shape[0] // t), -(-shape[1] // t))
    graph = da.map_blocks(_tile_task, [str(p) for p in paths], list(rpcs), guide, shape, spec,
                          chunks=((1,) * nb[0], (1,) * nb[1]), dtype=object, meta=np.empty((0, 0), object))
    with dask.config.set(scheduler=scheduler) if scheduler else _nullcontext():
        parts = graph.compute()
    pos = np.concatenate([p["pos"] for p in parts.ravel()], axis=1)
    ncc = np.concatenate([p["ncc"] for p in parts.ravel()], axis=1)
    rejected = [0]
    for k in range(1, len(paths)):
        m = np.isfinite(pos[k, :, 0])
        if m.sum() >= 8:
            r = p2l_filter(rpcs[0], rpcs[k], pos[0, m], pos[k, m], guide.h_range, spec.tracks.p2l)
            bad = np.flatnonzero(m)[~r.inlier]
            pos[k, bad] = np.nan
            ncc[k, bad] = np.nan
            rejected.append(int(bad.size))
        else:
            rejected.append(0)
    keep = np.isfinite(pos[..., 0]).sum(axis=0) >= 2
    return Tracks(pos[:, keep], ncc[:, keep], tuple(rejected)), guide


class _nullcontext:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False
