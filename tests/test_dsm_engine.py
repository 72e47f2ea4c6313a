"""The DSM engine's guarantees: the result does not depend on the chunking
(bit for bit), on synthetic scenes and on the real Pleiades pair, and a tall
narrow structure keeps its roof.

Every DSM here is computed in process with the synchronous scheduler
(``ds["height"].values``): no store, no cluster.
"""

from __future__ import annotations

import dask
import numpy as np
import pytest

from tiledsm.dsm import DSMParams, dsm_from_pair
from tiledsm.geometry.grid import GroundGrid
from tiledsm.io.grids import grid_like
from tiledsm.match.pyramid import SearchParams
from tiledsm.workflows.common import reference_on_grid
from tiledsm.synth import TowerParams, make_scene

SIZE = 384  # scene side, pixels (= truth grid side, cells)
CHUNKS = (64, 100, 256, SIZE)  # 100 does not divide the grid; SIZE: one chunk for the whole grid


def nmad(d: np.ndarray) -> float:
    d = d[np.isfinite(d)]
    return float(1.4826 * np.median(np.abs(d - np.median(d))))


def _dsm(views, grid: GroundGrid, params: DSMParams):
    """``(height, confidence, dataset, report)``: the DSM computed in memory."""
    ds, report = dsm_from_pair(*views, grid=grid, params=params)
    with dask.config.set(scheduler="synchronous"):
        height, conf = dask.compute(ds["height"].data, ds["confidence"].data)
    return np.asarray(height), np.asarray(conf), ds, report


_SCENES: dict = {}


@pytest.fixture(scope="module")
def scene_of(tmp_path_factory):
    """``scene_of(views)``: the 384 px scene (GSD 0.5 m, B/H 0.4, seed 3)
    with 2 or 3 views, made once per module."""

    def get(views: int):
        if views not in _SCENES:
            _SCENES[views] = make_scene(
                tmp_path_factory.mktemp(f"scene{views}"), size=SIZE, gsd=0.5, bh=0.4, seed=3, views=views
            )
        return _SCENES[views]

    yield get
    _SCENES.clear()


def _accuracy(scene, height: np.ndarray, like) -> tuple[float, float]:
    """NMAD (m) and completeness on the visible cells of the truth grid,
    without a 2 % frame (the views' footprints miss the grid's corners)."""
    truth = reference_on_grid(scene.truth_dsm, like).values
    vis = (reference_on_grid(scene.visible_mask, like, resampling="nearest").values > 0.5) & np.isfinite(truth)
    m = int(0.02 * vis.shape[0]) + 1
    frame = np.zeros_like(vis)
    frame[m:-m, m:-m] = True
    d = height[vis & frame] - truth[vis & frame]
    return nmad(d), float(np.isfinite(d).mean())


# ------------------------------------------------------------------ chunk invariance
@pytest.mark.parametrize(
    "levels, views, given_range, relative",
    [
        pytest.param(2, 2, False, False, id="L2-2views"),
        pytest.param(2, 2, False, True, id="L2-2views-relative-labels", marks=pytest.mark.slow),
        pytest.param(3, 2, True, False, id="L3-2views", marks=pytest.mark.slow),
        pytest.param(2, 3, False, False, id="L2-3views", marks=pytest.mark.slow),
    ],
)
def test_dsm_is_bit_identical_in_every_chunking(scene_of, levels, views, given_range, relative):
    """Chunk sides 64, 100 (does not divide the 384-cell grid), 256 and one
    chunk for the whole grid give the **bit-identical** DSM: same NaN mask,
    same heights and confidences to the last bit (``assert_array_equal``),
    at every pyramid depth and with 2 or 3 views. The result is also checked
    against the truth, so the test cannot pass on an empty DSM.

    ``given_range``: the scene's guaranteed height range is given instead of
    the tie-point estimate (a wider search, where 3 levels make sense).
    ``relative``: finer levels count candidates from the coarser surface
    instead of the scene-wide lattice (absolute labels, the default, shift
    neighbouring bands against each other: the aggregation must leave out
    each block's padding)."""
    scene = scene_of(views)
    results = {}
    for chunk in CHUNKS:
        grid = grid_like(scene.truth_dsm, chunk=chunk)
        params = DSMParams(
            chunk=chunk, levels=levels, height_range=tuple(scene.height_range) if given_range else None,
            search=SearchParams(relative_labels=relative),
        )
        height, conf, ds, report = _dsm(scene.views, grid, params)
        assert ds.attrs["levels"] == levels
        assert ds["height"].data.chunks == grid.chunks
        results[chunk] = (height, conf, report["height_range_m"], ds)
    ref_h, ref_c, ref_range, ref_ds = results[SIZE]
    for chunk, (h, c, h_range, _) in results.items():
        assert h_range == ref_range, f"chunk {chunk}: height range {h_range} != {ref_range}"
        mask_diff = int((np.isfinite(h) != np.isfinite(ref_h)).sum())
        assert mask_diff == 0, f"chunk {chunk}: {mask_diff} cells differ in NaN-ness from the one-chunk DSM"
        both = np.isfinite(h) & np.isfinite(ref_h)
        max_diff = float(np.abs(h[both] - ref_h[both]).max())
        assert max_diff <= 1e-3, f"chunk {chunk}: max |diff| {max_diff:.4g} m"
        np.testing.assert_array_equal(h, ref_h, err_msg=f"chunk {chunk}: heights not bit-identical")
        np.testing.assert_array_equal(c, ref_c, err_msg=f"chunk {chunk}: confidence not bit-identical")
    # a real DSM, not an identical pair of empty ones
    err, completeness = _accuracy(scene, ref_h, ref_ds["height"])
    assert completeness > 0.8, f"completeness on visible cells {completeness:.3f}"
    assert err < 0.5, f"NMAD vs truth on visible cells {err:.3f} m"


def test_level_chunks_merges_a_short_last_chunk_into_its_neighbour():
    """:func:`tiledsm.dsm.level_chunks` as documented: ``chunk`` cells each,
    the last one merged into its neighbour when shorter than ``min_size``.
    (Regression: ``sizes[-2] += sizes.pop()`` indexes the list before the
    pop, so two chunks raised IndexError -- e.g. the 96-cell coarsest level
    of a 384-cell grid in chunks of 64 -- and with three or more the merged
    size landed on the wrong chunk.)"""
    from tiledsm.dsm import level_chunks

    for chunk in (64, 100, 128, 256):
        for n in range(1, 700):
            sizes = level_chunks(n, chunk, 64)
            assert sum(sizes) == n, (n, chunk, sizes)
            assert all(s == chunk for s in sizes[:-1]), (n, chunk, sizes)
            if len(sizes) > 1:
                assert 64 <= sizes[-1] < chunk + 64, (n, chunk, sizes)
            else:
                assert sizes[0] == n
    assert level_chunks(128, 100, 64) == (128,)
    assert level_chunks(330, 100, 64) == (100, 100, 130)


def test_coarse_level_smaller_than_the_speckle_filter(scene_of):
    """A pyramid level with fewer cells per side than the speckle filter's
    halo (``SGVLLParams.speckle_size`` = 100) must still compute: here a
    192-cell grid with 2 levels (coarse level 96 cells), one chunk. The
    same happens to any grid under 400 cells with 3 levels (the
    ``L3-2views`` case above)."""
    scene = scene_of(2)
    grid = grid_like(scene.truth_dsm, chunk=192).subgrid(96, 288, 96, 288)
    height, _, ds, _ = _dsm(scene.views, grid, DSMParams(chunk=192, levels=2, height_range=tuple(scene.height_range)))
    assert ds.attrs["levels"] == 2
    assert np.isfinite(height).mean() > 0.8


# ------------------------------------------------------------------ real data
@pytest.mark.slow
@pytest.mark.realdata
def test_s2p_pair_is_bit_identical_in_chunks_of_128_and_512(shared_data):
    """The real Pleiades pair on s2p's DSM grid, cropped to its central
    384 x 384 cells (the full 739 x 721 grid takes over a minute at chunk
    128 on two busy cores), in chunks of 128 (3 x 3) and 512 (one):
    bit-identical heights and NaN masks."""
    imgs = [shared_data("s2p_pair", "input_pair", n) for n in ("img_01.tif", "img_02.tif")]
    ref_path = shared_data("s2p_pair", "expected_output", "pair", "dsm.tif")
    out = {}
    for chunk in (128, 512):
        full = grid_like(ref_path, chunk=chunk)
        assert full.shape == (739, 721)
        grid = full.subgrid(176, 560, 168, 552)
        height, _, _, report = _dsm(imgs, grid, DSMParams(chunk=chunk))
        out[chunk] = height
    a, b = out[128], out[512]
    assert a.shape == (384, 384)
    assert np.isfinite(a).mean() > 0.8, f"completeness {np.isfinite(a).mean():.3f}"
    np.testing.assert_array_equal(np.isfinite(a), np.isfinite(b))
    np.testing.assert_array_equal(a, b)


# ------------------------------------------------------------------ tall structure
TOWER = TowerParams(height_m=65.0, side_m=16.0)


@pytest.fixture(scope="module")
def tower_scene(tmp_path_factory):
    return make_scene(tmp_path_factory.mktemp("tower"), size=SIZE, gsd=0.5, bh=0.4, seed=3, views=2, tower=TOWER)


def _roof(scene, height: np.ndarray) -> np.ndarray:
    r0, r1, c0, c1 = scene.tower_window
    return height[r0 + 2 : r1 - 2, c0 + 2 : c1 - 2]  # the roof eroded by 2 cells


def _check_roof(scene, height: np.ndarray, report: dict, min_completeness: float = 0.9) -> None:
    roof = _roof(scene, height)
    completeness = float(np.isfinite(roof).mean())
    median = float(np.nanmedian(roof)) if np.isfinite(roof).any() else float("nan")
    detail = (
        f"roof {scene.tower.roof_height:.2f} m, DSM median {median:.2f} m, "
        f"completeness {completeness:.3f}, height range {report['height_range_m']}"
    )
    assert completeness >= min_completeness, f"hole in the roof: {detail}"
    assert abs(median - scene.tower.roof_height) <= 1.0, detail


def test_tall_tower_roof_with_default_parameters(tower_scene):
    """A 65 m tower of 16 m side on a 384 px scene, default parameters
    (height range from tie points): on the roof interior (the truth window
    eroded by 2 cells) the DSM median is within 1 m of the roof height and
    at least 90 % of the cells have a height (no hole)."""
    grid = grid_like(tower_scene.truth_dsm, chunk=SIZE)
    height, _, _, report = _dsm(tower_scene.views, grid, DSMParams(chunk=SIZE))
    _check_roof(tower_scene, height, report)


def test_tall_tower_roof_through_a_three_level_pyramid(tower_scene):
    """The same tower through 3 pyramid levels at chunks of 100: the
    coarsest level (cells 4x larger: the tower is 8 x 8 cells there, less
    than a speckle of the finest level) must keep it, and the finer levels
    must follow it up. Measured: median +0.04 m, roof-interior completeness
    0.838 (the pyramid's band blurs the roof edges; 1.0 with one level)."""
    grid = grid_like(tower_scene.truth_dsm, chunk=100)
    height, _, _, report = _dsm(tower_scene.views, grid, DSMParams(chunk=100, levels=3))
    _check_roof(tower_scene, height, report, min_completeness=0.82)


def test_tall_tower_roof_with_a_covering_height_range(tower_scene):
    """The same tower when the search range is given and covers the roof
    (the scene's guaranteed range): the matcher itself finds the roof."""
    grid = grid_like(tower_scene.truth_dsm, chunk=SIZE)
    lo, hi = tower_scene.height_range
    assert lo < tower_scene.tower.roof_height < hi
    height, _, _, report = _dsm(tower_scene.views, grid, DSMParams(chunk=SIZE, height_range=(lo, hi)))
    _check_roof(tower_scene, height, report)
