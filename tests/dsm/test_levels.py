"""A finer level's candidate heights: the scene-wide lattice (absolute
labels, the default) or steps around the coarser surface (relative labels;
see :class:`tiledsm.match.pyramid.SearchParams`). Chunk invariance of both
is in ``tests/test_dsm_engine.py``."""

from __future__ import annotations

import dataclasses

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
    params = dataclasses.replace(params, search=SearchParams(relative_labels=relative))
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


def test_task_window_reaches_the_restart_lines_plus_half_a_window():
    from tiledsm.dsm.levels import task_window

    params = DSMParams(chunk=96)  # path period 64, window 5
    chunks = (96, 96, 96, 96)
    assert [task_window(chunks, k, params) for k in range(4)] == [
        (0, 96, 0, 130), (96, 192, 62, 194), (192, 288, 190, 322), (288, 384, 254, 384)]
    # chunks on the restart lines need only the window's cells
    assert task_window((512, 512), 1, DSMParams(chunk=512)) == (512, 1024, 510, 1024)
    assert DSMParams().halo() == 64  # the most a chunk on even cells needs: 62 + 2
    no_restarts = DSMParams(match=dataclasses.replace(DSMParams().match, path_period=0))
    assert task_window(chunks, 1, no_restarts) == (96, 192, 96 - 10, 192 + 10)


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
    from tiledsm.dsm.levels import task_window

    views, geom, h_range, params, truth = level0
    start, stop, lo, hi = task_window((96, 96, 96, 96), 1, params)

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
