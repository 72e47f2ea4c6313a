"""One pyramid level of the DSM: its grid and geometry, and the matching
of one of its chunks plus halo (:func:`match_task`), searching around the
coarser level; where the chunks and halos are is
:mod:`tiledsm.dsm.layout`'s."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from tiledsm.errors import MatchingError
from tiledsm.geometry.grid import GroundGrid
from tiledsm.dsm.params import DSMParams
from tiledsm.dsm.views import View, read_window


# --------------------------------------------------------------------- blocks
def level_grid(grid: GroundGrid, level: int) -> GroundGrid:
    """The grid of pyramid level ``level``: cells ``2**level`` times larger,
    same top-left corner (coarse cell ``I`` covers cells ``2I, 2I+1`` of the
    next finer level), same chunk side in cells."""
    from tiledsm.match.pyramid import level_shape

    f = 2**level
    h, w = level_shape(grid.shape, level)
    return GroundGrid(crs=grid.crs, x0=grid.x0, y0=grid.y0, resolution=grid.resolution * f, width=w, height=h, chunk=grid.chunk)


@dataclass(frozen=True)
class LevelGeometry:
    """What every task of one pyramid level shares: its grid, image
    decimation, height step and view-pair weights, all measured once at the
    grid centre so that every chunk sweeps the same candidate lattice and
    scores candidates the same way.

    Attributes
    ----------
    level : int
        0 = full resolution.
    grid : GroundGrid
        The level's grid (:func:`level_grid`).
    step : float
        Height step, metres (about ``step_px`` pixels of parallax).
    pair_weights : numpy.ndarray
        ``(nv, nv)`` squared parallax per metre of each view pair.
    """

    level: int
    grid: GroundGrid
    step: float
    pair_weights: np.ndarray

    @property
    def factor(self) -> int:
        return 2**self.level


def level_geometry(
    views: Sequence[View], grid: GroundGrid, level: int, h_range, params: DSMParams, levels: int = 1
) -> LevelGeometry:
    """The :class:`LevelGeometry` of level ``level`` of a pyramid of
    ``levels`` levels over ``grid``.

    With two or more levels, the coarsest (``levels - 1``) sweeps the whole
    height range with steps ``params.sweep_step_factor`` times its own
    (see :class:`~tiledsm.dsm.params.DSMParams`)."""
    from tiledsm.match.sgvll import height_step, pair_weights

    lgrid = level_grid(grid, level)
    lon, lat = _grid_centre_lonlat(lgrid)
    f = 2**level
    rpcs = [v.rpc.scaled(1.0 / f) if f > 1 else v.rpc for v in views]
    h = float(np.mean(h_range))
    step = float(height_step(rpcs, lon, lat, h, params.match))
    if level > 0 and level == levels - 1:
        step *= params.sweep_step_factor
    return LevelGeometry(level, lgrid, step, pair_weights(rpcs, lon, lat, h))


def _level_image(view: View, sub: GroundGrid, h_band: tuple[float, float], f: int):
    """Pixels of ``view`` that see the ground cells ``sub`` over ``h_band``,
    at decimation ``f``: ``(image, (row0, col0))`` with the window's origin
    in pixels of the decimated image, or ``None`` when the view does not
    see the cells (or sees only nodata).

    The window's origin is a multiple of ``f`` in the full image, so its
    decimated pixels are exactly those of the whole decimated image
    (whichever chunk asks for them).
    """
    from tiledsm.geometry.footprint import image_window
    from tiledsm.match.pyramid import downsample

    win = image_window(view.rpc, sub, h_band, view.shape, margin=4 * f + 8)
    if win is None:
        return None
    r0, r1, c0, c1 = win
    r0, c0 = (r0 // f) * f, (c0 // f) * f
    r1 = min(view.shape[0], -(-r1 // f) * f)
    c1 = min(view.shape[1], -(-c1 // f) * f)
    if (r1 - r0) < 2 * f or (c1 - c0) < 2 * f:
        return None
    img = read_window(view, (r0, r1, c0, c1))
    if not np.isfinite(img).any():
        return None
    return downsample(img, f), (r0 // f, c0 // f)


def match_cells(
    views: Sequence[View],
    geom: LevelGeometry,
    cells: tuple[int, int, int, int],
    search: np.ndarray | None,
    h_range: tuple[float, float],
    params: DSMParams,
    details: dict | None = None,
) -> np.ndarray:
    """Heights and confidence of the level cells ``cells = (row0, row1,
    col0, col1)`` (a chunk plus its halo), matched together.

    ``search`` is ``(3, rows, cols)`` ``h_ref, lo, hi`` from the coarser
    level (:func:`tiledsm.match.pyramid.search_from_coarse`), or ``None``
    at the coarsest level (the whole ``h_range``, a horizontal sweep).
    ``details``, if given, is filled by
    :func:`~tiledsm.match.sgvll.match_block` (e.g. ``candidates``, the
    candidate heights of each cell; left empty when nothing is matched).

    Returns
    -------
    numpy.ndarray
        ``(2, rows, cols)`` float32: height (ellipsoidal metres, NaN =
        none) and confidence (winning ZNCC, 0..1).
    """
    from tiledsm.cluster import single_threaded_libraries
    from tiledsm.match.sgvll import match_block

    single_threaded_libraries()
    r0, r1, c0, c1 = cells
    sub = geom.grid.subgrid(r0, r1, c0, c1)
    out = np.full((2, r1 - r0, c1 - c0), np.nan, np.float32)
    if search is None:
        lo, hi, h_ref = float(h_range[0]), float(h_range[1]), None
        band = (lo, hi)
    else:
        h_ref, lo, hi = search
        if not np.isfinite(lo).any():
            return out
        band = (float(np.nanmin(lo)), float(np.nanmax(hi)))
        if params.search.relative_labels:
            # cells the coarser level gives nothing to search still get a
            # deterministic surface: their samples enter neighbours' windows
            h_ref = np.where(np.isfinite(h_ref), h_ref, np.float32(np.mean(h_range)))
        else:
            # the scene-wide lattice: one constant for every block, so chunks agree
            h_ref = np.full(h_ref.shape, np.float32(np.mean(h_range)), np.float32)
    f = geom.factor
    images, rpcs, windows = [], [], []
    for v in views:
        got = _level_image(v, sub, band, f)
        if got is None:
            return out  # a view does not see these cells
        images.append(got[0])
        windows.append(got[1])
        rpcs.append(v.rpc.scaled(1.0 / f) if f > 1 else v.rpc)
    g = geom.grid
    # speckles are removed afterwards over the whole level (tiledsm.dsm.stages), with
    # their own halo: the component sizes are then exact in any chunking
    kernel = params.match.model_copy(update={"speckle_size": 0})
    height, conf = match_block(
        images, rpcs, windows, sub.x, sub.y, sub.crs, lo, hi, kernel, step=geom.step, h_ref=h_ref,
        origin=(r0, c0), axes=(float(g.x[0]), float(g.y[0]), g.resolution, -g.resolution),
        pair_weights=geom.pair_weights, details=details,
    )
    out[0], out[1] = height, conf
    return out


def match_task(coarse, views, geom: LevelGeometry, layout, h_range, params: DSMParams, i: int, j: int,
               details: dict | None = None) -> np.ndarray:
    """Chunk ``(i, j)`` of ``layout`` (a :class:`~tiledsm.dsm.layout.LevelLayout`):
    match the cells of its :meth:`~tiledsm.dsm.layout.LevelLayout.task_window`,
    return the chunk, ``(2, rows, cols)`` heights and confidence.

    ``coarse`` is the coarser level's heights under the chunk
    (:meth:`~tiledsm.dsm.layout.LevelLayout.coarse_window`: NaN beyond the
    grid), from which the chunk's search band over its halo is derived
    (:func:`~tiledsm.match.pyramid.search_from_coarse`); ``None`` at the
    coarsest level (the whole height range is searched). ``details``, if
    given, gets ``candidates``: the candidate heights of each cell of the
    chunk (0 where none was searched)."""
    from tiledsm.match.pyramid import search_from_coarse

    r0, r1, hr0, hr1 = layout.task_window(0, i)
    c0, c1, hc0, hc1 = layout.task_window(1, j)
    search = None
    if coarse is not None:
        band = search_from_coarse(coarse, layout.search_depth, params.refine_steps * geom.step, tuple(h_range),
                                  params.search)
        # the band's cells start at the chunk's first cell less the halo (coarse_depth coarse cells)
        a, b = hr0 - (r0 - layout.halo), hc0 - (c0 - layout.halo)
        search = band[:, a : a + hr1 - hr0, b : b + hc1 - hc0]
        if search.shape[1:] != (hr1 - hr0, hc1 - hc0):
            raise MatchingError(f"internal: search block {search.shape} for cells {(hr0, hr1, hc0, hc1)}")
    found: dict | None = {} if details is not None else None
    res = match_cells(views, geom, (hr0, hr1, hc0, hc1), search, h_range, params, details=found)
    if details is not None:
        cand = found.get("candidates")
        details["candidates"] = (
            np.zeros((r1 - r0, c1 - c0), np.int32) if cand is None else cand[r0 - hr0 : r1 - hr0, c0 - hc0 : c1 - hc0]
        )
    return res[:, r0 - hr0 : r1 - hr0, c0 - hc0 : c1 - hc0]


def _grid_centre_lonlat(grid: GroundGrid) -> tuple[float, float]:
    from pyproj import Transformer

    tr = Transformer.from_crs(grid.crs, "EPSG:4326", always_xy=True)
    lon, lat = tr.transform(float(np.mean(grid.x)), float(np.mean(grid.y)))
    return float(lon), float(lat)


def auto_levels(views: Sequence[View], grid: GroundGrid, h_range: tuple[float, float], params: DSMParams) -> int:
    """Pyramid levels so the coarsest sweep needs at most
    ``params.max_candidates`` heights (at most 5 levels)."""
    n = (h_range[1] - h_range[0]) / level_geometry(views, grid, 0, h_range, params).step
    levels = 1
    while n > params.max_candidates and levels < 5:
        n /= 2
        levels += 1
    return levels
