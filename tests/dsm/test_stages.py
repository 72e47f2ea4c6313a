"""The DSM engine (:mod:`tiledsm.dsm.stages`): every level written to a
store, the same DSM as the plain graph (the oracle in ``plain_graph.py``),
a reading task waiting for the writers of what it reads and no others,
finished blocks kept on resume, a store of other inputs discarded, and a
graph built with dask's public API only.

One 384 px synthetic scene (GSD 0.5 m, B/H 0.4), computed in process with
the synchronous scheduler.
"""

from __future__ import annotations

import json
from pathlib import Path

import dask
import numpy as np
import pytest

from tiledsm.dsm import DSMParams, open_views, prepare_views
from tiledsm.dsm.engine import dsm_from_views
from tiledsm.dsm.levels import level_geometry
from tiledsm.dsm.stages import stage_reports
from tiledsm.io import BlockFiles
from tiledsm.io.grids import grid_like
from tiledsm.synth import make_scene

from plain_graph import plain_dsm


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_scene(tmp_path_factory.mktemp("scene"), size=384, gsd=0.5, bh=0.4, seed=3, views=2)


def _inputs(scene, levels: int, chunk: int):
    params = DSMParams(levels=levels, chunk=chunk)
    h_range, views, _ = prepare_views(open_views([str(v) for v in scene.views]), params)
    return views, grid_like(scene.truth_dsm, chunk=chunk), h_range, params


def _compute(ds) -> tuple[np.ndarray, np.ndarray]:
    with dask.config.set(scheduler="synchronous"):
        h, c = dask.compute(ds["height"].data, ds["confidence"].data)
    return np.asarray(h), np.asarray(c)


def _stored(path: Path) -> np.ndarray:
    store = BlockFiles.open(path)
    return store.read(0, store.shape[0], 0, store.shape[1], "height")


def _layer(graph, prefix: str) -> str:
    """The name of the one layer of ``graph`` whose name starts with ``prefix``."""
    (name,) = [n for n in graph.layers if n.startswith(prefix)]
    return name


def _waits(ds, reader: str, writer: str) -> dict[tuple[int, int], set[tuple[int, int]]]:
    """``{(i, j): {(a, b), ...}}``: the blocks of layer ``writer`` that
    block ``(i, j)`` of layer ``reader`` (keys ``(name, i, j)`` or ``(name,
    0, i, j)``) depends on, through the graph's aliases."""
    from dask.core import get_dependencies

    graph = ds.__dask_graph__()
    tasks = dict(graph)
    reader, writer = _layer(graph, reader), _layer(graph, writer)

    def reach(key) -> set:
        found = set()
        for dep in get_dependencies(tasks, key):
            if dep[0] == writer:
                found.add(dep[1:])
            elif dep[0].startswith("blocks-"):  # an alias of a token block
                found |= reach(dep)
        return found

    return {k[-2:]: reach(k) for k in tasks if isinstance(k, tuple) and k[0] == reader}


@pytest.mark.parametrize(
    "levels, chunk, chunk_counts",
    # matching chunks per level: 384 cells in 90 (the halos' floor) -> 4 x 4,
    # 192 -> 2 x 2; in 100 -> 3 x 3, 192 -> 2 x 2, 96 -> 1
    [(2, 64, (16, 4)), (3, 100, (9, 4, 1))],
    ids=["L2-chunk64", "L3-chunk100"],
)
def test_staged_levels_give_the_plain_graphs_dsm(scene, tmp_path, levels, chunk, chunk_counts):
    """With ``stage_dir`` the DSM is bit-identical to the plain graph's
    (chunks of 64, raised to the halos' floor of 90 cells, leave the
    192-cell coarse level a merged last chunk of 102 cells, whose task
    writes two store blocks), also on 4 threads; each coarse level is a
    store of raw heights. A finer task waits for the coarse tasks whose
    chunks it reads and no others (no level waits for a whole coarser
    level): without one of them, 4 threads would read blocks not yet
    written."""
    views, grid, h_range, params = _inputs(scene, levels, chunk)
    plain = _compute(plain_dsm(views, grid, h_range, params))
    ds = dsm_from_views(views, grid, h_range, params, stage_dir=tmp_path / "levels")
    assert not (tmp_path / "levels").exists(), "building the graph must not write anything"
    for level in range(1, levels):
        # every finer task waits for some coarser writers; together, for all of them
        waits = _waits(ds, f"match-L{level - 1}-", f"match-L{level}-")
        assert all(waits.values()) and len(set().union(*waits.values())) == chunk_counts[level]
    staged = _compute(ds)
    np.testing.assert_array_equal(staged[0], plain[0])
    np.testing.assert_array_equal(staged[1], plain[1])
    assert np.isfinite(plain[0]).mean() > 0.8
    with dask.config.set(scheduler="threads", num_workers=4):
        again = dask.compute(*(dsm_from_views(views, grid, h_range, params, stage_dir=tmp_path / "threads")[v].data
                               for v in ("height", "confidence")))
    np.testing.assert_array_equal(again[0], plain[0])
    np.testing.assert_array_equal(again[1], plain[1])
    stores = sorted(p.name for p in (tmp_path / "levels").iterdir())
    assert stores == [f"L{level}.blocks" for level in range(levels)]
    coarse = _stored(tmp_path / "levels" / "L1.blocks")
    assert coarse.shape == (192, 192) and np.isfinite(coarse).mean() > 0.8
    # the finest store holds the heights before the speckle filter: it removed some
    raw = _stored(tmp_path / "levels" / "L0.blocks")
    assert np.isfinite(raw).sum() > np.isfinite(staged[0]).sum()
    reports = stage_reports(tmp_path / "levels")
    assert {name: (r["chunks_total"], r["chunks_reused"]) for name, r in reports.items()} == {
        f"L{level}": (n, 0) for level, n in zip(range(levels), chunk_counts)
    }
    # candidates per cell: the coarsest level sweeps the whole range, the
    # same lattice heights in every cell, which cover `range / step` steps:
    # from range / step + 1 to range / step + 3 (exclusive) of them, as the
    # range's ends fall between lattice heights
    coarsest = level_geometry(views, grid, levels - 1, h_range, params, levels)
    steps = (h_range[1] - h_range[0]) / coarsest.step
    top = reports[f"L{levels - 1}"]
    assert top["mean_candidates_per_cell"] == int(top["mean_candidates_per_cell"])
    assert steps + 1 <= top["mean_candidates_per_cell"] < steps + 3, (top, steps)
    assert top["cells_searched"] == coarsest.grid.shape[0] * coarsest.grid.shape[1]
    # the finer levels: a band of +-refine_steps around the coarser surface
    # (wider where the coarser surface varies, or has holes)
    for level in range(levels - 1):
        band = reports[f"L{level}"]["mean_candidates_per_cell"]
        assert 2 * params.refine_steps + 1 <= band < 16, (level, band)  # measured 13.1-14.1


def test_without_a_stage_dir_the_same_engine_uses_a_folder_of_its_own(scene, tmp_path):
    """The Python API without ``stage_dir``: the same graph, its stores in
    a temporary folder that lives as long as the graph and is removed
    with it; the same DSM as with a ``stage_dir``."""
    import gc

    views, grid, h_range, params = _inputs(scene, 2, 64)
    ds = dsm_from_views(views, grid, h_range, params)
    setup = [v for k, v in dict(ds.__dask_graph__()).items() if isinstance(k, str) and k.startswith("stage-setup-L0-")]
    folder = Path(_store_folder(setup[0]))
    got = _compute(ds)
    assert sorted(p.name for p in folder.iterdir()) == ["L0.blocks", "L1.blocks"]
    staged = _compute(dsm_from_views(views, grid, h_range, params, stage_dir=tmp_path / "levels"))
    np.testing.assert_array_equal(got[0], staged[0])
    np.testing.assert_array_equal(got[1], staged[1])
    del ds, setup
    gc.collect()
    assert not folder.exists()


def _store_folder(task) -> str:
    """The folder of the store a level's setup task creates (its first argument, a BlockFiles)."""
    (store,) = [a for a in getattr(task, "args", ()) if isinstance(a, BlockFiles)]
    return str(Path(store.path).parent)


def test_a_finer_task_waits_for_the_coarse_chunks_around_its_own_only(scene, tmp_path):
    """On a 4096² grid (the graph only; nothing is computed), chunks of
    512: the coarse level has 4 x 4 tasks; a finer task waits for the
    coarse tasks under its chunk and its neighbours', the speckle filter
    of a chunk for the matched chunks around it, never a whole level."""
    from tiledsm.geometry.grid import GroundGrid

    views, small, h_range, _ = _inputs(scene, 2, 512)
    grid = GroundGrid(crs=small.crs, x0=small.x0, y0=small.y0, resolution=small.resolution, width=4096, height=4096,
                      chunk=512)
    ds = dsm_from_views(views, grid, h_range, DSMParams(levels=2, chunk=512), stage_dir=tmp_path / "levels")
    assert not (tmp_path / "levels").exists()
    fine = _waits(ds, "match-L0-", "match-L1-")
    assert len(fine) == 64 and set().union(*fine.values()) == {(a, b) for a in range(4) for b in range(4)}
    # finer chunk (i, j) lies over coarse chunk (i // 2, j // 2); its search reaches a few coarse cells beyond
    assert fine[(0, 0)] == {(0, 0)} and fine[(1, 1)] == {(0, 0), (0, 1), (1, 0), (1, 1)}
    assert fine[(3, 4)] == {(a, b) for a in (1, 2) for b in (1, 2)}  # coarse rows 768-1024, columns 1024-1280
    speckle = _waits(ds, "despeckle-L0-", "match-L0-")
    assert len(speckle) == 64 and speckle[(0, 0)] == {(0, 0), (0, 1), (1, 0), (1, 1)}
    assert speckle[(3, 4)] == {(a, b) for a in (2, 3, 4) for b in (3, 4, 5)}


def test_staged_level_keeps_its_finished_blocks_and_drops_a_stale_store(scene, tmp_path):
    """Rerunning the graph recomputes only the blocks not marked done: a
    block marked done keeps what is stored (here a planted value), a block
    marked pending is matched again. A store holding another DSM's
    fingerprint is discarded and rebuilt."""
    views, grid, h_range, params = _inputs(scene, 2, 64)
    stage = tmp_path / "levels"
    _compute(dsm_from_views(views, grid, h_range, params, stage_dir=stage))
    store = stage / "L1.blocks"
    first = _stored(store)
    blocks = BlockFiles.open(store)
    b = blocks.side  # the level's chunk side: 90 cells (the halos' floor), 192 = 90 + 90 + 12
    assert b == 90 and blocks.numblocks == (3, 3) and blocks.done().all()
    planted = np.full((b, b), 1234.0, np.float32)
    blocks.write_block(0, 0, {"height": planted})  # block (0, 0): kept as finished
    (store / "1_1.blk").unlink()  # block (1, 1): not written, so matched again
    assert not blocks.done()[1, 1]
    _compute(dsm_from_views(views, grid, h_range, params, stage_dir=stage))
    again = _stored(store)
    assert (again[0:b, 0:b] == 1234.0).all()
    np.testing.assert_array_equal(again[b : 2 * b, b : 2 * b], first[b : 2 * b, b : 2 * b])
    assert blocks.done().all()
    # L1's 2 x 2 matching chunks: the one writing block (1, 1) ran again; every L0 chunk was reused
    reports = stage_reports(stage)
    assert {name: (r["chunks_total"], r["chunks_reused"]) for name, r in reports.items()} == {"L1": (4, 3), "L0": (16, 16)}

    # another height range: another fingerprint, the stale store is rebuilt
    other = DSMParams(levels=2, chunk=64, height_range=(h_range[0] - 5.0, h_range[1] + 5.0))
    _compute(dsm_from_views(views, grid, other.height_range, other, stage_dir=stage))
    rebuilt = _stored(store)
    assert not (rebuilt[0:b, 0:b] == 1234.0).any()
    fp = json.loads(BlockFiles.open(store).attrs()["fingerprint"])
    assert fp["level"] == 1 and fp["dsm"]["height_range"] == list(other.height_range)
