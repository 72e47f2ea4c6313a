"""A finer level's candidate heights: the scene-wide lattice (absolute
labels, the default) or steps around the coarser surface (relative labels;
see :class:`tiledsm.match.pyramid.SearchParams`). Chunk invariance of both
is in ``tests/test_dsm_engine.py``."""

from __future__ import annotations

import numpy as np
import pytest
import rasterio

from tiledsm.dsm import DSMParams, open_views, prepare_views
from tiledsm.dsm.levels import level_geometry, match_cells
from tiledsm.io.grids import grid_like
from tiledsm.match.pyramid import SearchParams
from tiledsm.synth import make_scene

N = 96  # cells matched: a block of the 384-cell truth grid


@pytest.fixture(scope="module")
def level0(tmp_path_factory):
    scene = make_scene(tmp_path_factory.mktemp("scene"), size=384, gsd=0.5, bh=0.4, seed=3, views=2)
    params = DSMParams(levels=2, chunk=384)
    h_range, views, _ = prepare_views(open_views([str(v) for v in scene.views]), params)
    grid = grid_like(scene.truth_dsm, chunk=384)
    geom = level_geometry(views, grid, 0, h_range, params)
    with rasterio.open(scene.truth_dsm) as src:  # the grid is the truth's own
        truth = src.read(1, masked=True).astype(np.float64).filled(np.nan)
    return views, geom, h_range, params, truth


def _band(truth: np.ndarray, step: float, r0: int, c0: int) -> np.ndarray:
    """A coarser level's search: a smooth surface off the truth by a tilt of
    up to 1.5 steps, +- 3 steps around it."""
    t = truth[r0 : r0 + N, c0 : c0 + N].astype(np.float64)
    yy, xx = np.mgrid[0:N, 0:N] / N
    h_ref = np.where(np.isfinite(t), np.nan_to_num(t) + 1.5 * step * (yy - xx), np.nan)
    return np.stack([h_ref, h_ref - 3 * step, h_ref + 3 * step]).astype(np.float32)


@pytest.mark.parametrize("relative", [False, True], ids=["absolute", "relative"])
def test_candidates_lie_on_the_scene_lattice_unless_relative(level0, relative):
    views, geom, h_range, params, truth = level0
    params = params.model_copy(update={"search": SearchParams(relative_labels=relative)})
    r0 = c0 = 144
    search = _band(truth, geom.step, r0, c0)
    details: dict = {}
    out = match_cells(views, geom, (r0, r0 + N, c0, c0 + N), search, tuple(h_range), params, details)
    h_ref = details["h_ref"]
    if relative:
        ok = np.isfinite(search[0])
        np.testing.assert_allclose(h_ref[ok], search[0][ok], rtol=0, atol=1e-3)
    else:
        # one constant for every block: candidates h_ref + k step are the whole scene's lattice
        assert np.ptp(h_ref) == 0 and h_ref.flat[0] == pytest.approx(np.float32(np.mean(h_range)))
    # either way a real DSM: heights where the truth is, close to it
    height = out[0]
    err = height - truth[r0 : r0 + N, c0 : c0 + N]
    assert np.isfinite(err).mean() > 0.7
    assert np.nanmedian(np.abs(err)) < 0.5


def _layout(n: int, params: DSMParams):
    """The layout of a level-0 grid of ``n`` x ``n`` cells chunked ``params.chunk``."""
    from types import SimpleNamespace

    from tiledsm.dsm.layout import level_layout

    geom = SimpleNamespace(level=0, grid=SimpleNamespace(shape=(n, n), resolution=0.5), step=0.3)
    return level_layout(geom, params.chunk, params)


def test_task_window_reaches_the_restart_lines_plus_half_a_window():
    params = DSMParams(chunk=96)  # path period 64, window 5
    layout = _layout(384, params)
    assert layout.chunks == ((96,) * 4,) * 2
    assert [layout.task_window(0, k) for k in range(4)] == [
        (0, 96, 0, 130), (96, 192, 62, 194), (192, 288, 190, 322), (288, 384, 254, 384)]
    assert layout.largest_task() == (132, 132)
    # chunks on the restart lines need only the window's cells
    assert _layout(1024, DSMParams(chunk=512)).task_window(1, 1) == (512, 1024, 510, 1024)
    assert DSMParams().halo() == 64  # the most a chunk on even cells needs: 62 + 2
    no_restarts = DSMParams(chunk=96, match=DSMParams().match.model_copy(update={"path_period": 0}))
    assert _layout(384, no_restarts).task_window(0, 1) == (96, 192, 96 - 10, 192 + 10)


def test_coarse_window_and_reads_of_a_finer_chunk():
    """Chunks of 96 over 384 cells: finer chunk 1 lies over coarse cells
    [48, 96) of the 192-cell coarser level; its search reads ``coarse_depth``
    (the search band's support, 13, plus half the halo, 32) coarse cells
    around them; the store read adds the coarser level's speckle halo
    (speckle_size 150 // 4 = 37 cells), clipped to the grid; the writers
    are the coarser chunks (of 96) that hold those cells."""
    from types import SimpleNamespace

    from tiledsm.dsm.layout import level_layout

    params = DSMParams(chunk=96)
    fine = _layout(384, params)
    coarse = level_layout(SimpleNamespace(level=1, grid=SimpleNamespace(shape=(192, 192), resolution=1.0), step=0.6),
                          96, params)
    d = fine.coarse_depth
    assert d == 13 + 32 and fine.search_depth == 13 and coarse.speckle_halo == 37
    assert fine.coarse_window(1, 3, coarse.shape) == (48 - 45, 96 + 45, 144 - 45, 192 + 45)
    assert fine.coarse_window(0, 0, coarse.shape) == (-45, 48 + 45, -45, 48 + 45)
    assert fine.coarse_reads(1, 3, coarse) == (0, 96 + 45 + 37, 144 - 45 - 37, 192)
    rows, cols = coarse.writers(fine.coarse_reads(1, 3, coarse))
    assert (list(rows), list(cols)) == ([0, 1], [0, 1])
    rows, cols = coarse.writers(fine.coarse_reads(0, 0, coarse))  # coarse cells [0, 130): both chunks
    assert (list(rows), list(cols)) == ([0, 1], [0, 1])


def _global_band(truth: np.ndarray, step: float, rows: tuple[int, int], cols: tuple[int, int]) -> np.ndarray:
    """:func:`_band` on whole-grid coordinates: a cell's band does not depend
    on the block it is cut from."""
    t = truth[rows[0] : rows[1], cols[0] : cols[1]].astype(np.float64)
    yy, xx = np.mgrid[rows[0] : rows[1], cols[0] : cols[1]] / truth.shape[0]
    h_ref = np.where(np.isfinite(t), np.nan_to_num(t) + 1.5 * step * (yy - xx), np.nan)
    return np.stack([h_ref, h_ref - 3 * step, h_ref + 3 * step]).astype(np.float32)


def test_a_task_window_matches_its_chunk_as_a_full_halo_does(level0):
    """The chunk [96, 192)^2 matched over its task window [62, 194)^2 equals
    the same chunk matched with a 64-cell halo on every side, bit for bit;
    a window one cell short of the restart line's window differs."""
    views, geom, h_range, params, truth = level0
    start, stop, lo, hi = _layout(384, params.model_copy(update={"chunk": 96})).task_window(0, 1)

    def chunk(a: int, b: int) -> np.ndarray:
        search = _global_band(truth, geom.step, (a, b), (a, b))
        out = match_cells(views, geom, (a, b, a, b), search, tuple(h_range), params)
        return out[:, start - a : stop - a, start - a : stop - a]

    tight = chunk(lo, hi)
    wide = chunk(start - 64, stop + 64)
    assert np.isfinite(tight[0]).all()  # measured: every cell of the chunk has a height
    np.testing.assert_array_equal(tight, wide)
    short = chunk(lo + 1, hi)
    assert not np.array_equal(short, wide, equal_nan=True)
