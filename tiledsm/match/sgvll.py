"""Object-space dense matching: semi-global vertical line locus (SGVLL).

Zhang, Y., Zhang, Y., Mo, D., Zhang, Y., Li, X. (2017). Direct Digital
Surface Model Generation by Semi-Global Vertical Line Locus Matching.
Remote Sensing 9(3):214, doi:10.3390/rs9030214.

For every cell of a ground grid (projected CRS) and every candidate height
on the vertical line through the cell centre, all views are sampled at the
projection of ``(x, y, h)``; a windowed ZNCC on the ground grid scores the
candidate, semi-global aggregation (8 paths over the ground grid,
:mod:`tiledsm.match.sgm`) regularises, winner-take-all with a parabola gives
a sub-step height, and unreliable cells become NaN.

Conventions
-----------
- Pixel coordinates are GDAL's (:mod:`tiledsm.geometry.rpc`): the centre of
  array element ``[i, j]`` of a full image is at ``(i + 0.5, j + 0.5)``.
  A view is given as an image *window* (float32, NaN nodata) whose element
  ``[0, 0]`` is element ``[row0, col0]`` of the full image described by its
  RPC; OpenCV's ``remap`` is called with ``row - 0.5 - row0``.
- Ground cells: centres ``grid_x`` (nx,) and ``grid_y`` (ny,) in a projected
  CRS, regularly spaced (any sign of spacing); arrays are ``(ny, nx)``, row
  ``i`` at ``grid_y[i]``.
- Heights are metres above the WGS84 ellipsoid (the RPCs' heights).
- Candidate heights lie on a lattice shared by all cells and blocks,
  ``h = label * step`` (integer ``label``); a cell searches the labels
  covering ``[h_lo, h_hi]``. A block's results depend on each cell's own
  bounds only (not on the block's extent), so overlapping blocks agree.
"""

from __future__ import annotations

import math
from typing import Sequence

import cv2
import numpy as np

from tiledsm.errors import MatchingError
from tiledsm.geometry import RPC
from tiledsm.match.kernels import KERNELS
from tiledsm.match.params import SGVLLParams
from tiledsm.match.sgm import remove_speckles

__all__ = [
    "SGVLLParams",
    "height_step",
    "pair_weights",
    "match_block",
    "reference_surface",
]


def height_step(
    rpcs: Sequence[RPC], lon: float, lat: float, h: float, params: SGVLLParams | float = 0.5
) -> float:
    """Height step (metres) for which the best-separated view pair moves by
    ``step_px`` pixels of parallax at ground point ``(lon, lat, h)``.

    Parameters
    ----------
    rpcs : sequence of RPC
        Two or more cameras (pixel units of each image).
    lon, lat : float
        Degrees; h : float, ellipsoidal metres.
    params : SGVLLParams or float
        The parameters (``step_px`` is used) or ``step_px`` itself.

    Returns
    -------
    float
        Metres per step.
    """
    step_px = params.step_px if isinstance(params, SGVLLParams) else float(params)
    if len(rpcs) < 2:
        raise MatchingError(f"height_step needs at least two cameras, got {len(rpcs)}")
    best = float(_parallax(rpcs, lon, lat, h).max())
    if not best > 1e-9:
        raise MatchingError("the views have no parallax (identical viewing directions): heights cannot be matched")
    return step_px / best


def _parallax(rpcs: Sequence[RPC], lon: float, lat: float, h: float) -> np.ndarray:
    """``(nv, nv)`` parallax (pixels per metre of height) between every two
    views at ground point ``(lon, lat, h)``."""
    d = np.array([np.subtract(rpc.project(lon, lat, h + 1.0), rpc.project(lon, lat, h)) for rpc in rpcs], np.float64)
    return np.hypot(d[:, None, 0] - d[None, :, 0], d[:, None, 1] - d[None, :, 1])



def pair_weights(rpcs: Sequence[RPC], lon: float, lat: float, h: float) -> np.ndarray:
    """``(nv, nv)`` squared parallax per metre of height (pixels²/m²) of
    every view pair at ground point ``(lon, lat, h)`` (degrees, ellipsoidal
    metres): the inverse-variance weights of :func:`match_block`'s
    multi-view cost (a pair's height precision grows with its parallax)."""
    return (_parallax(rpcs, lon, lat, h) ** 2).astype(np.float32)


def _as_grid(v, shape, name) -> np.ndarray:
    a = np.asarray(v, np.float64)
    try:
        return np.broadcast_to(a, shape).astype(np.float64)
    except ValueError as exc:
        raise MatchingError(f"match_block: {name} has shape {a.shape}, expected scalar or {shape}") from exc


def _lonlat(crs, x, y):
    from pyproj import Transformer

    tr = Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
    return tr.transform(x, y)


def reference_surface(h_lo: np.ndarray, h_hi: np.ndarray, sigma: float) -> np.ndarray:
    """Smooth reference surface of a block: the Gaussian-smoothed (``sigma``
    cells, NaN-aware) midpoint of the per-cell bounds; constant bounds give
    the constant ``h_lo``."""
    lo = np.asarray(h_lo, np.float64)
    hi = np.asarray(h_hi, np.float64)
    ok = np.isfinite(lo) & np.isfinite(hi) & (hi >= lo)
    if not ok.any():
        return np.zeros(lo.shape)
    if np.ptp(lo[ok]) == 0 and np.ptp(hi[ok]) == 0:
        return np.full(lo.shape, lo[ok][0])
    mid = np.where(ok, (lo + hi) / 2, 0.0)
    if sigma <= 0:
        return np.where(ok, mid, float(np.mean(mid[ok])))
    w = cv2.GaussianBlur(ok.astype(np.float64), (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    m = cv2.GaussianBlur(mid, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    with np.errstate(invalid="ignore", divide="ignore"):
        ref = m / w
    return np.where(np.isfinite(ref) & (w > 1e-6), ref, float(np.mean(mid[ok])))


def match_block(
    images: Sequence[np.ndarray],
    rpcs: Sequence[RPC],
    windows: Sequence[tuple[int, int]] | None,
    grid_x: np.ndarray,
    grid_y: np.ndarray,
    crs,
    h_lo,
    h_hi,
    params: SGVLLParams = SGVLLParams(),
    step: float | None = None,
    h_ref: np.ndarray | None = None,
    details: dict | None = None,
    origin: tuple[int, int] = (0, 0),
    axes: tuple[float, float, float, float] | None = None,
    pair_weights: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Heights of a block of ground cells by SGVLL matching.

    Candidates and windows
    ----------------------
    Candidate heights of cell ``p`` are ``h_ref(p) + label * step`` for the
    integer labels covering ``[h_lo(p), h_hi(p)]``, where ``h_ref`` is a
    smooth reference surface (constant when the bounds are scalars, so the
    sweep is the classic horizontal-plane sweep; else the smoothed middle of
    the bounds, or the caller's ``h_ref``, e.g. the upsampled coarser DSM).
    For each label the whole grid is sampled on the surface
    ``h_ref + label * step``, so a ZNCC window always lies on a smooth
    surface (no staircase between cells with different ranges), and the
    semi-global smoothness penalises label changes, i.e. departures from
    surfaces parallel to ``h_ref``. A cell is sampled only at the labels
    of the cells whose window holds it (``kernel="fast"``,
    :mod:`tiledsm.match.sweep`; the ``"reference"`` kernel sweeps each
    label over the bounding box of the cells that need it, with the same
    result).

    Parameters
    ----------
    images : sequence of numpy.ndarray
        One 2-D window per view (float32 after conversion; NaN = nodata).
        Two views: cost = 1 - ZNCC; three or more: 1 - mean ZNCC over the
        view pairs (weighted by parallax, see ``weight_pairs``), ignoring invalid pairs.
    rpcs : sequence of RPC
        The camera of each *full* image (GDAL pixel convention).
    windows : sequence of (row0, col0) or None
        Offset of each window in its full image (element ``[0, 0]`` of the
        window is full-image element ``[row0, col0]``); ``None`` = all
        ``(0, 0)`` (the RPCs already describe the windows).
    grid_x, grid_y : numpy.ndarray
        Cell-centre coordinates (nx,) and (ny,) in ``crs``, regularly spaced.
    crs : str or pyproj.CRS
        Projected CRS of the grid.
    h_lo, h_hi : float or numpy.ndarray
        Per-cell height search bounds (scalars or ``(ny, nx)``), ellipsoidal
        metres. Cells with non-finite or reversed bounds get NaN.
    params : SGVLLParams
    step : float, optional
        Height step in metres; by default :func:`height_step` at the block
        centre. Pass the same value to all blocks of one level.
    h_ref : numpy.ndarray, optional
        ``(ny, nx)`` smooth reference surface, metres (see above).
    origin : (int, int)
        Index of the block's cell ``[0, 0]`` in the whole grid the block
        belongs to (a tiled run passes each block's offset).
    axes : (x_first, y_first, dx, dy), optional
        Centre of the whole grid's cell ``[0, 0]`` and the signed cell
        spacing; default: derived from ``grid_x``, ``grid_y`` and
        ``origin``. With ``origin`` and ``axes`` the sparse projection
        lattice sits on nodes of the whole grid (every ``proj_stride``
        cells, heights every ``lattice_steps * step`` metres from 0), so a
        cell's image coordinates, hence its cost, do not depend on the
        block it is computed in.
    pair_weights : numpy.ndarray, optional
        ``(nv, nv)`` weights of the view pairs (see ``weight_pairs``);
        default: measured at the block centre. A tiled run passes one
        matrix for the whole grid.
    details : dict, optional
        If given, filled with ``step`` (m), ``n_candidates`` (the most of
        a cell: the cost volume's depth), ``mean_candidates`` (over the
        searched cells), ``n_cells`` (searched), ``candidates`` (``(ny,
        nx)`` int32 per cell, 0 = not searched), ``n_labels`` (the block's
        label span), ``n_samples`` (image samples per view), ``kernel``,
        ``zncc``, ``ratio`` (arrays), ``h_ref`` and timings (s) ``t_cost``
        (sampling and ZNCC), ``t_sgm`` (aggregation), ``t_wta``
        (winner-take-all and masks).

    Returns
    -------
    height : numpy.ndarray
        ``(ny, nx)`` float32 heights, metres above the WGS84 ellipsoid, NaN
        where no reliable match.
    confidence : numpy.ndarray
        ``(ny, nx)`` float32 ZNCC of the winning height clipped to
        ``[0, 1]`` (NaN where no valid correlation), also for cells whose
        height was rejected.
    """
    import time

    nv = len(images)
    if nv < 2 or len(rpcs) != nv:
        raise MatchingError(f"match_block: need >= 2 images with one RPC each, got {nv} images and {len(rpcs)} RPCs")
    windows = [(0, 0)] * nv if windows is None else list(windows)
    if len(windows) != nv:
        raise MatchingError(f"match_block: {len(windows)} window offsets for {nv} images")
    gx = np.asarray(grid_x, np.float64).ravel()
    gy = np.asarray(grid_y, np.float64).ravel()
    ny, nx = len(gy), len(gx)
    height = np.full((ny, nx), np.nan, np.float32)
    conf = np.full((ny, nx), np.nan, np.float32)
    if ny == 0 or nx == 0:
        return height, conf
    imgs = [np.ascontiguousarray(im, np.float32) for im in images]
    for v, im in enumerate(imgs):
        if im.ndim != 2:
            raise MatchingError(f"match_block: image {v} must be 2-D, got shape {im.shape}")
    lo = _as_grid(h_lo, (ny, nx), "h_lo")
    hi = _as_grid(h_hi, (ny, nx), "h_hi")
    ok = np.isfinite(lo) & np.isfinite(hi) & (hi >= lo)
    if not ok.any() or not all(np.isfinite(im).any() and min(im.shape) > 1 for im in imgs):
        return height, conf

    # sparse lon/lat nodes on the whole grid's cell lattice (the RPC is
    # smooth: exact projections every `stride` cells)
    s = params.proj_stride
    gi0, gj0 = int(origin[0]), int(origin[1])
    if axes is None:
        dx = float(gx[1] - gx[0]) if nx > 1 else 1.0
        dy = float(gy[1] - gy[0]) if ny > 1 else -1.0
        axes = (float(gx[0]) - gj0 * dx, float(gy[0]) - gi0 * dy, dx, dy)
    x_first, y_first, dx, dy = (float(a) for a in axes)
    n0i, n0j = gi0 // s, gj0 // s
    nodes_i = np.arange(n0i, (gi0 + ny - 1) // s + 2)
    nodes_j = np.arange(n0j, (gj0 + nx - 1) // s + 2)
    X, Y = np.meshgrid(x_first + (nodes_j * s) * dx, y_first + (nodes_i * s) * dy)
    lon, lat = _lonlat(crs, X, Y)
    lon, lat = np.asarray(lon), np.asarray(lat)
    if step is None:
        hc = float(np.mean((lo[ok] + hi[ok]) / 2))
        step = height_step(rpcs, float(lon.mean()), float(lat.mean()), hc, params)
    step = float(step)

    # per-cell labels relative to the reference surface
    href = reference_surface(np.where(ok, lo, np.nan), np.where(ok, hi, np.nan), params.ref_sigma) if h_ref is None \
        else _as_grid(h_ref, (ny, nx), "h_ref")
    href = np.ascontiguousarray(np.where(np.isfinite(href), href, np.nanmean(href) if np.isfinite(href).any() else 0.0))
    base = np.where(ok, np.floor((np.where(ok, lo, 0) - href) / step + 1e-9), 0).astype(np.int64)
    top = np.where(ok, np.ceil((np.where(ok, hi, 0) - href) / step - 1e-9), -1).astype(np.int64)
    nvalid = np.where(ok, top - base + 1, 0).astype(np.int64)
    nd = int(nvalid.max())
    if nd > params.max_candidates:
        raise MatchingError(
            f"match_block: {nd} candidate heights per cell (range {np.nanmin(lo[ok]):.1f}..{np.nanmax(hi[ok]):.1f} m, "
            f"step {step:.3f} m) exceed max_candidates={params.max_candidates}; use a pyramid or a narrower range"
        )
    lab0 = int(base[ok].min())
    lab1 = int((base + nvalid - 1)[ok].max())
    # every sampled height (cells that do not need a label are sampled too:
    # they sit in the ZNCC windows of cells that do), so samples are
    # always interpolated in the lattice, never extrapolated
    h0 = float(href.min()) + lab0 * step
    h1 = float(href.max()) + lab1 * step
    # height nodes on the lattice k * dh shared by every block of the grid
    dh = params.lattice_steps * step
    k0 = int(math.floor(h0 / dh))
    nh = max(2, int(math.ceil(h1 / dh)) - k0 + 1)
    lat_r = np.empty((nv, nh, len(nodes_i), len(nodes_j)), np.float64)
    lat_c = np.empty_like(lat_r)
    for v, rpc in enumerate(rpcs):
        for t in range(nh):
            r, c = rpc.project(lon, lat, (k0 + t) * dh)
            # array-index convention: pixel centre [i, j] at (i, j)
            lat_r[v, t] = r - 0.5
            lat_c[v, t] = c - 0.5
    win_r = np.array([w[0] for w in windows], np.float64)
    win_c = np.array([w[1] for w in windows], np.float64)

    if not params.weight_pairs:
        pair_w = None
    elif pair_weights is not None:
        pair_w = np.asarray(pair_weights, np.float32)
    else:
        pair_w = (_parallax(rpcs, float(lon.mean()), float(lat.mean()), (h0 + h1) / 2) ** 2).astype(np.float32)
    t_start = time.perf_counter()
    kernel = KERNELS[params.kernel].for_device(params.device)
    sweep: dict = {}
    vol = kernel.cost_volume(
        imgs, lat_r, lat_c, s, k0, dh, href, step, (gi0, gj0), (n0i, n0j), win_r, win_c,
        params.interpolation == "cubic", base, nvalid, params.window // 2, pair_w, details=sweep,
    )
    t_cost = time.perf_counter() - t_start

    t_start = time.perf_counter()
    # aggregation and each cell's winner (t_sgm holds both)
    index, _, ratio, cbest = kernel.winners(
        vol, params.P1, params.P2, base=base, nvalid=nvalid, invalid_cost=params.invalid_cost,
        origin=(gi0, gj0), restart_period=params.path_period,
    )
    del vol
    t_sgm = time.perf_counter() - t_start
    t_start = time.perf_counter()

    zncc = 1.0 - cbest
    h = (href + (base + index) * step).astype(np.float32)
    good = ok & np.isfinite(zncc) & (zncc >= params.zncc_min) & (ratio <= params.ratio_max)
    if params.reject_edges:
        kb = np.rint(index)
        good &= (kb > 0) & (kb < nvalid - 1)
    height = np.where(good, h, np.float32(np.nan)).astype(np.float32)
    cell = abs(float(gx[1] - gx[0])) if gx.size > 1 else 0.0
    height = remove_speckles(height, params.speckle_max_diff(cell, step), params.speckle_size)
    conf = np.clip(zncc, 0.0, 1.0).astype(np.float32)
    t_wta = time.perf_counter() - t_start
    if details is not None:
        details.update(
            step=step, n_candidates=nd, mean_candidates=float(nvalid[ok].mean()), n_cells=int(ok.sum()),
            candidates=nvalid.astype(np.int32),
            n_labels=lab1 - lab0 + 1, n_samples=sweep.get("n_samples"), zncc=zncc, ratio=ratio, h_ref=href,
            t_cost=t_cost, t_sgm=t_sgm, t_wta=t_wta, kernel=params.kernel,
        )
    return height, conf
