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

import functools
import math
from typing import Literal, Sequence

import cv2
import numba as nb
import numpy as np
from pydantic import Field, ValidationInfo, field_validator, model_validator

from tiledsm.errors import MatchingError
from tiledsm.geometry import RPC
from tiledsm.match.cost import mean_zncc_cost
from tiledsm.match.sampling import sample_view
from tiledsm.match.sgm import aggregate, aggregate_best, remove_speckles
from tiledsm.match import cuda_kernel
from tiledsm.match.kernels import KERNELS, MatchKernel, register_kernel
from tiledsm.match.sweep import MASKED_COST, cost_volume
from tiledsm.spec import StrictModel, not_below, option, registered

__all__ = [
    "SGVLLParams",
    "height_step",
    "pair_weights",
    "match_block",
    "reference_surface",
]


class SGVLLParams(StrictModel):
    """Parameters of :func:`match_block`.

    Attributes
    ----------
    window : int
        ZNCC window side on the ground grid, cells (odd).
    P1, P2 : float
        SGM penalties in cost units (cost = 1 - ZNCC, 0..2) for a change of
        one height step / more than one step between path neighbours.
        P1 0.3 lowers the real pair's NMAD and RMSE for little completeness
        (docs: decisions/speckle-slope.md, which gives the measurements).
    step_px : float
        Height step expressed in parallax: one step moves the projections
        of the best-separated view pair apart by about ``step_px`` pixels.
    zncc_min : float
        Cells whose winning (unaggregated) ZNCC is below this are NaN.
        0.25 is the lowest value that keeps the real pair's cells off by
        more than 10 m within 0.01 % (docs: decisions/zncc-min.md).
    ratio_max : float
        Cells whose aggregated peak ratio ``S_best / S_second`` exceeds this
        (ambiguous minimum) are NaN.
    reject_edges : bool
        NaN where the winner is the first or last candidate of the cell's
        range (the true height is probably outside it).
    speckle_size : int
        Connected components of fewer cells than this are removed
        (:meth:`speckle_max_diff` says which neighbours are connected);
        150 cells is above the largest blunder patch of the real pair
        (docs: decisions/speckle-slope.md).
    speckle_slope : float
        Neighbours are connected when the slope between them is at most
        this, degrees: a blunder patch meets the terrain around it in a
        step steeper than any hillside, whereas a 45 degree hillside stays
        one component (docs: decisions/speckle-slope.md).
    speckle_steps : float
        ... but never less than this many height steps (the sub-step
        noise of a flat area must not split it).
    proj_stride : int
        Projections are computed exactly every ``proj_stride`` cells and on
        a height lattice every ``lattice_steps`` steps, then interpolated
        (bilinear in x/y, linear in h).
    lattice_steps : int
        See ``proj_stride``.
    interpolation : str
        Image resampling: ``"linear"`` or ``"cubic"`` (OpenCV remap).
    invalid_cost : float
        Cost used for candidates without a valid ZNCC (nodata, flat).
    max_candidates : int
        Refuse blocks needing more candidates per cell than this.
    ref_sigma : float
        Smoothing (cells) of the reference surface built from per-cell
        bounds when no ``h_ref`` is given (see :func:`match_block`).
    weight_pairs : bool
        With three or more views, weight each pair's ZNCC by its squared
        parallax per metre of height (inverse variance; see
        :func:`tiledsm.match.cost.mean_zncc_cost`); ``False``: plain mean.
        Weighted, a third view at half the base keeps the NMAD of two wide
        views better than a plain mean (docs: guides/dsm.md, two vs three
        views; ``benchmarks/views.py``).
    kernel : str
        Implementation of the sweep and aggregation (:data:`KERNELS`):
        ``"fast"`` (:mod:`tiledsm.match.sweep`: compiled candidate loop,
        only the candidates each cell needs), ``"reference"`` (the plain
        per-height sweep it is tested against) or ``"cuda"``
        (:mod:`tiledsm.match.cuda_kernel`: the fast kernel's arithmetic as
        compiled CUDA kernels, the volume kept on the GPU; the same
        heights bit for bit).
    device : str
        Where the ``"cuda"`` kernel runs: ``"cuda"``, ``"cuda:1"``...
        (``tiledsm dsm --device``); the other kernels run on the CPU
        (``"cpu"``).
    path_period : int
        Semi-global paths restart every ``path_period`` cells on lines of
        the whole grid (:func:`tiledsm.match.sgm.aggregate`): each cell's
        result depends only on cells within this distance, so tiles with
        this halo are exact; 0 = paths never restart (tiles then differ
        slightly near their borders).
    """

    window: int = Field(5, ge=1, description="ZNCC window side on the ground grid, cells (odd)")
    P1: float = Field(0.3, ge=0, description="SGM penalty for a change of one height step, cost units (1 - ZNCC)")
    P2: float = Field(2.0, validate_default=True,  # checked against a P1 given alone too
                     description="SGM penalty for a change of more than one step, cost units (>= P1)")
    step_px: float = Field(0.5, gt=0, description="height step as parallax of the best-separated view pair, pixels")
    zncc_min: float = Field(0.25, description="cells whose winning (unaggregated) ZNCC is below this are NaN")
    ratio_max: float = Field(0.98, description="cells whose aggregated peak ratio S_best / S_second exceeds this "
                             "(ambiguous minimum) are NaN")
    reject_edges: bool = Field(True, description="NaN where the winner is the first or last candidate of the cell")
    speckle_size: int = Field(150, ge=0, description="connected components of fewer cells than this are removed")
    speckle_slope: float = Field(60.0, gt=0, lt=90, description="neighbours are connected when the slope between "
                                 "them is at most this, degrees")
    speckle_steps: float = Field(0.5, description="... but never less than this many height steps")
    proj_stride: int = Field(8, ge=1, description="projections computed exactly every this many cells, "
                             "interpolated between")
    lattice_steps: int = Field(16, ge=1, description="projections computed exactly every this many height steps, "
                               "interpolated between")
    interpolation: Literal["linear", "cubic"] = Field("cubic", description="image resampling (OpenCV remap)")
    invalid_cost: float = Field(1.0, description="cost of a candidate without a valid ZNCC (nodata, flat), cost units")
    max_candidates: int = Field(2048, description="refuse blocks needing more candidates per cell than this")
    ref_sigma: float = Field(3.0, description="smoothing of the reference surface built from per-cell bounds, cells")
    weight_pairs: bool = Field(True, description="with three or more views, weight each pair's ZNCC by its squared "
                               "parallax per metre of height; false: plain mean")
    path_period: int = Field(64, ge=0, description="semi-global paths restart every this many cells (0: never), "
                             "which makes tiles exact with this halo")
    kernel: str = Field("fast", description="implementation of the sweep and aggregation: fast, reference or cuda")
    device: str = Field("cpu", description="where the cuda kernel runs: cuda, cuda:N; the others run on the cpu",
                        json_schema_extra=option("--device"))

    @model_validator(mode="before")
    @classmethod
    def _known_names(cls, data: object) -> object:
        """A misspelled parameter is named with the valid ones (issue 13)."""
        unknown = [k for k in data if k not in cls.model_fields] if isinstance(data, dict) else []
        if unknown:
            raise ValueError(f"unknown matching parameter(s) {', '.join(map(repr, unknown))}; "
                             f"valid: {', '.join(cls.model_fields)}")
        return data

    @field_validator("window")
    @classmethod
    def _odd_window(cls, value: int) -> int:
        if value % 2 == 0:
            raise ValueError(f"must be odd (a window has a centre cell), got {value}")
        return value

    _p2_above_p1 = field_validator("P2")(not_below("P1"))

    _known_kernel = field_validator("kernel")(registered(lambda: KERNELS, "matching kernel"))

    @field_validator("device")
    @classmethod
    def _kernel_runs_there(cls, value: str, info: ValidationInfo) -> str:
        kernel = info.data.get("kernel")  # absent when the kernel itself was refused
        if value != "cpu" and kernel is not None:
            if not KERNELS[kernel].on_device:
                raise ValueError(f"{value!r}: the {kernel!r} kernel runs on the CPU only")
            KERNELS[kernel].check_device(value)
        return value

    def speckle_max_diff(self, cell: float, step: float) -> float:
        """Largest height difference, metres, between connected neighbours
        of ``cell`` metres apart on a lattice of ``step`` metres (see
        ``speckle_slope``)."""
        return max(cell * math.tan(math.radians(self.speckle_slope)), self.speckle_steps * step)


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


# ------------------------------------------------------------ cost volumes
@nb.njit(nogil=True, cache=True)
def _scatter(cost, label, base, nvalid, r0, c0, vol):
    """``vol[i, j, label - base[i, j]] = cost[i - r0, j - c0]`` where that
    candidate exists."""
    h, w = cost.shape
    for a in range(h):
        i = a + r0
        for b in range(w):
            j = b + c0
            k = label - base[i, j]
            if 0 <= k < nvalid[i, j]:
                vol[i, j, k] = cost[a, b]


def cost_volume_reference(
    imgs, lat_r, lat_c, stride, k0, dh, href, step, origin, nodes0, win_r, win_c, cubic, base, nvalid, half,
    pair_w=None, details: dict | None = None,
) -> np.ndarray:
    """The SGVLL cost volume of a block, one candidate height at a time
    (the plain reference of :func:`tiledsm.match.sweep.cost_volume`, same
    arguments and result): for every label some cell needs, every view is
    resampled over the bounding box of those cells (plus the window) on
    the surface ``href + label * step``
    (:func:`~tiledsm.match.sampling.sample_view`), scored by
    :func:`~tiledsm.match.cost.mean_zncc_cost` and scattered into the
    cells' candidates."""
    nv = len(imgs)
    ny, nx = href.shape
    nd = max(1, int(nvalid.max()))
    ok = nvalid > 0
    gi0, gj0 = (int(o) for o in origin)
    n0i, n0j = (int(n) for n in nodes0)
    vol = np.full((ny, nx, nd), MASKED_COST, np.float32)
    buf = np.empty((nv, ny, nx), np.float32)
    top_lab = base + nvalid - 1
    n_samples = 0
    for label in range(int(base[ok].min()), int(top_lab[ok].max()) + 1):
        need = ok & (base <= label) & (top_lab >= label)
        rows = np.flatnonzero(need.any(axis=1))
        if rows.size == 0:
            continue
        cols = np.flatnonzero(need.any(axis=0))
        r0, r1 = max(0, rows[0] - half), min(ny, rows[-1] + half + 1)
        c0, c1 = max(0, cols[0] - half), min(nx, cols[-1] + half + 1)
        samples = []
        for v in range(nv):
            sample_view(
                imgs[v], lat_r[v], lat_c[v], stride, k0, dh, href, label * step, gi0, gj0, n0i, n0j,
                win_r[v], win_c[v], cubic, r0, r1, c0, c1, buf[v],
            )
            samples.append(buf[v, : r1 - r0, : c1 - c0])
        cost = mean_zncc_cost(samples, half, weights=pair_w)
        _scatter(cost, label, base, nvalid, r0, c0, vol)
        n_samples += (r1 - r0) * (c1 - c0)
    if details is not None:
        details["n_samples"] = n_samples
    return vol


register_kernel("reference", MatchKernel(cost_volume_reference, aggregate))
register_kernel("fast", MatchKernel(cost_volume, functools.partial(aggregate, fast=True), best=aggregate_best))
register_kernel("cuda", MatchKernel(cuda_kernel.cost_volume, cuda_kernel.aggregate, on_device=True,
                                    best=cuda_kernel.best, check_device=cuda_kernel.check_device))


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
