"""Pyramid levels kept on disk between stages, so that a worker's memory
does not grow with the scene.

In the plain graph (:func:`tiledsm.dsm.levels.level_array`) a finer level's
tasks depend on the coarser level's results through an overlap
(``coarse_blocks``), and the speckle filter on its level's matched chunks
through another: dask keeps every result in a worker's memory until the
last task that needs it has run, and on a large grid that frontier grows
with the grid (an 8192² scene: ~150 MiB per worker on top of its largest
task, ~290 MiB at times). Here each level is matched into a resumable zarr
store (:class:`~tiledsm.io.ChunkStore`, one block per matching chunk), its
tasks return only a token, and every later task reads the window it
needs from the store: a finer level its coarse heights, the finest level's speckle
filter its chunk plus halo. A reading task depends on the tasks that
write the blocks it reads, and on no others: no level waits for the
whole coarser level, so a finer level's first chunks are matched while
the coarser level's last ones still run, and the speckle filter and the
DSM's writes start as soon as a chunk's neighbours are matched (on 2
workers, a thread no longer idles at each level's end). The stores hold
raw matched heights; the
speckle filter of a coarse level runs on the window read (grown by the
filter's own halo), which is exact for the same reason the filter is exact
in any chunking (:func:`~tiledsm.dsm.levels.despeckle`), so the DSM is
bit-identical to the plain graph's (tested).

A store's blocks finished by an interrupted run are kept: the tasks of
blocks already marked done return at once. The store records which of its
chunks this run computed and the candidate heights of its searched cells
(:func:`stage_reports`). The level stores stay partial (``L<level>.zarr.partial``):
nothing marks a level finished, as its readers may still run, and the run
removes them once the DSM store is finished. Stores carry the DSM's
fingerprint (``stage_fingerprint``); one computed from anything else is
discarded when its level is set up.
"""

from __future__ import annotations

import bisect
import functools
import itertools

import json
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import Sequence

import dask.array as da
import numpy as np
from dask.highlevelgraph import HighLevelGraph

from tiledsm.dsm.levels import LevelGeometry, coarse_chunks, coarse_depth, match_task, min_chunk, speckle_rule
from tiledsm.dsm.params import DSMParams
from tiledsm.dsm.views import View
from tiledsm.io import ChunkStore

__all__ = ["LEVELS_DIR", "LevelStore", "StagedLevel", "stage_level", "finest_from_stage", "coarse_window", "stage_reports"]

#: the folder of a run's coarse level stores, beside ``dsm.zarr`` (removed
#: once the DSM store is finished)
LEVELS_DIR = "dsm.levels"
_FP_ATTR = "stage_fingerprint"
#: per-block candidate counts (sum over the searched cells, and the cells);
#: per matching chunk, whether this run computed it (``computed``)
_COUNTS = "_counts"
_CANDIDATES = (("candidates", "int64"), ("cells", "int64"))
_COMPUTED = "computed"


@dataclass(frozen=True)
class LevelStore:
    """Where a level's matched heights are: what its readers' tasks carry.

    Attributes
    ----------
    store : ChunkStore
        ``height`` (float32 ellipsoidal metres, NaN = none; at the finest
        level also ``confidence``), blocks of the level's chunk side.
    geom : LevelGeometry
        The level.
    """

    store: ChunkStore
    geom: LevelGeometry


@dataclass(frozen=True)
class StagedLevel:
    """A level whose matched heights a graph writes into a store.

    Attributes
    ----------
    level : LevelStore
        The store and the level.
    chunks : tuple of tuple of int
        The level's matching chunks ``(rows, cols)``.
    name : str
        Its matching tasks' layer: task ``(name, i, j)`` writes the blocks
        of chunk ``(i, j)``.
    graph : HighLevelGraph
        The tasks of the level (coarser levels included); never given to
        a task, which carries ``level`` only.
    """

    level: LevelStore
    chunks: tuple[tuple[int, ...], tuple[int, ...]]
    name: str
    graph: HighLevelGraph

    def writers(self, r0: int, r1: int, c0: int, c1: int) -> list[tuple[str, int, int]]:
        """Keys of the matching tasks whose chunks hold level cells
        ``[r0:r1, c0:c1]``: what a task reading them must wait for."""
        rows = _overlapping(self.chunks[0], r0, r1)
        cols = _overlapping(self.chunks[1], c0, c1)
        return [(self.name, a, b) for a in rows for b in cols]


@functools.lru_cache(maxsize=8)
def _edges(chunks: tuple[int, ...]) -> list[int]:
    """Where the chunks of an axis start, and its end."""
    return [0, *itertools.accumulate(chunks)]


def _overlapping(chunks: tuple[int, ...], start: int, stop: int) -> list[int]:
    """Indices of the chunks of an axis chunked ``chunks`` that hold some of
    ``[start, stop)``."""
    # a binary search, not a scan: a grid of n chunks a side asks this 2 n² times while its graph is built
    # (a scan took 102 s of the plan of a 402 x 386-chunk grid, issue 37)
    edges = _edges(chunks)
    first = max(bisect.bisect_right(edges, start) - 1, 0)
    last = min(bisect.bisect_left(edges, stop), len(chunks))
    return [k for k in range(first, last) if edges[k + 1] > start and edges[k] < stop]


# ------------------------------------------------------------------ windows
def _read(store: ChunkStore, r0: int, r1: int, c0: int, c1: int, variable: str = "height") -> np.ndarray:
    import zarr

    return np.asarray(zarr.open_array(store=str(store.live_path), path=variable, mode="r")[r0:r1, c0:c1])


def coarse_window(
    staged: LevelStore, chunks: tuple[tuple[int, ...], tuple[int, ...]], i: int, j: int, params: DSMParams
) -> np.ndarray:
    """The coarse heights finer task ``(i, j)`` of ``chunks`` searches
    around, read from ``staged``'s store: its chunk's coarse cells grown by
    :func:`~tiledsm.dsm.levels.coarse_depth` (NaN beyond the grid), speckles
    removed as the plain graph removes them.

    The filter runs on the window grown by its own halo (the speckle size,
    clipped to the grid): a component smaller than that lies inside it, so
    every cell kept is the one the whole-level filter keeps.
    """
    from tiledsm.match.sgm import remove_speckles

    (a0, a1, b0, b1), (r0, r1, c0, c1) = _coarse_extent(staged, chunks, i, j, params)
    H, W = staged.store.shape
    size, max_diff = speckle_rule(staged.geom, params)
    h = _read(staged.store, r0, r1, c0, c1)
    if size > 1:
        h = remove_speckles(h, max_diff, size)
    out = np.full((a1 - a0, b1 - b0), np.nan, np.float32)
    y0, y1, x0, x1 = max(a0, 0), min(a1, H), max(b0, 0), min(b1, W)
    out[y0 - a0 : y1 - a0, x0 - b0 : x1 - b0] = h[y0 - r0 : y1 - r0, x0 - c0 : x1 - c0]
    return out


def _coarse_extent(staged: LevelStore, chunks, i: int, j: int, params: DSMParams):
    """``((a0, a1, b0, b1), (r0, r1, c0, c1))``: the coarse window of finer
    task ``(i, j)`` (:func:`coarse_window`; may reach beyond the grid) and
    the coarse cells read for it (grown by the speckle filter's halo,
    clipped to the grid)."""
    depth = coarse_depth(params)
    H, W = staged.store.shape
    # as coarse_blocks: the coarse cells under the finer chunk, grown by depth
    rows, cols = coarse_chunks(chunks, (H, W))
    a0, b0 = sum(rows[:i]) - depth, sum(cols[:j]) - depth
    a1, b1 = a0 + rows[i] + 2 * depth, b0 + cols[j] + 2 * depth
    halo = max(speckle_rule(staged.geom, params)[0], 0)
    return (a0, a1, b0, b1), (max(0, a0 - halo), min(H, a1 + halo), max(0, b0 - halo), min(W, b1 + halo))


# ------------------------------------------------------------------ tasks
def _setup(store: ChunkStore, fingerprint: str, geom: LevelGeometry, tasks: tuple[int, int]) -> bool:
    """Create the level's store, or keep it (resume) when it holds the same
    fingerprint; a store of anything else is discarded. The marks of the
    ``tasks`` chunks this run computes start at 0."""
    import zarr

    from tiledsm.io import create_store
    from tiledsm.io.atomic import remove_path

    for path in (Path(store.path), store.partial_path):
        if path.exists():
            try:
                stored = zarr.open_group(str(path), mode="r").attrs.get(_FP_ATTR)
            except Exception:  # unreadable: not ours to keep
                stored = None
            if stored != fingerprint:
                remove_path(path)
    template = replace(geom.grid, chunk=store.chunk[0])
    create_store(store.path, template, {v: "float32" for v in store.variables}, attrs={_FP_ATTR: fingerprint})
    # per block: the candidate heights summed over its searched cells, and their count
    group = zarr.open_group(str(store.live_path), mode="a")
    counts = group.require_group(_COUNTS)
    for name, dtype in _CANDIDATES:
        if name not in counts:
            counts.create_array(name, shape=store.numblocks, chunks=(1, 1), dtype=dtype, fill_value=0)
    # one zarr chunk per task: tasks mark theirs concurrently
    counts.create_array(_COMPUTED, shape=tasks, chunks=(1, 1), dtype="uint8", fill_value=0, overwrite=True)
    return True


def _blocks(store: ChunkStore, r0: int, r1: int, c0: int, c1: int) -> list[tuple[int, int]]:
    cy, cx = store.chunk
    return [(bi, bj) for bi in range(r0 // cy, -(-r1 // cy)) for bj in range(c0 // cx, -(-c1 // cx))]


def _staged_task(i, j, *_ready, staged_in, store, views, geom, chunks, h_range, params) -> bool:
    """Match chunk ``(i, j)`` of a level and write it into ``store``,
    unless an earlier run did; return whether it was computed. ``_ready``:
    the level's setup and the coarser tasks it reads (their values unused)."""
    from tiledsm.dsm.levels import chunk_window

    r0, r1, _, _ = chunk_window(chunks[0], i, 0)
    c0, c1, _, _ = chunk_window(chunks[1], j, 0)
    blocks = _blocks(store, r0, r1, c0, c1)
    if store.blocks_done(blocks):
        return False
    import zarr

    coarse = None if staged_in is None else coarse_window(staged_in, chunks, i, j, params)
    details: dict = {}
    res = match_task(coarse, views, geom, chunks, h_range, params, staged_in is None, block_id=(i, j), details=details)
    where = str(store.live_path)
    for bi, bj in blocks:
        w0, w1, v0, v1 = store.block_window(bi, bj)
        cand = details["candidates"][w0 - r0 : w1 - r0, v0 - c0 : v1 - c0]
        # before the block is marked done (write_block), so a done block has its counts
        zarr.open_array(store=where, path=f"{_COUNTS}/candidates", mode="r+")[bi, bj] = int(cand.sum())
        zarr.open_array(store=where, path=f"{_COUNTS}/cells", mode="r+")[bi, bj] = int((cand > 0).sum())
        part = res[:, w0 - r0 : w1 - r0, v0 - c0 : v1 - c0]
        store.write_block(bi, bj, dict(zip(store.variables, part)))
    zarr.open_array(store=where, path=f"{_COUNTS}/{_COMPUTED}", mode="r+")[i, j] = 1
    return True


def _despeckled_task(i, j, *_ready, staged, chunks, max_diff, size) -> np.ndarray:
    """Heights and confidence of grid chunk ``(i, j)`` of the finest level,
    read with the speckle filter's halo from its store and filtered
    (``_ready``: the matching tasks that wrote them)."""
    from tiledsm.dsm.levels import chunk_window
    from tiledsm.match.sgm import remove_speckles

    r0, r1, hr0, hr1 = chunk_window(chunks[0], i, size)
    c0, c1, hc0, hc1 = chunk_window(chunks[1], j, size)
    height = _read(staged.store, hr0, hr1, hc0, hc1)
    if size > 1:
        height = remove_speckles(height, max_diff, size)
    # the filter leaves the confidence as it is (despeckle_heights): read without the halo
    rest = [_read(staged.store, r0, r1, c0, c1, v) for v in staged.store.variables[1:]]
    return np.stack([height[r0 - hr0 : r1 - hr0, c0 - hc0 : c1 - hc0], *rest])


# ------------------------------------------------------------------ graphs
def stage_level(
    views: Sequence[View],
    geom: LevelGeometry,
    chunks: tuple[tuple[int, ...], tuple[int, ...]],
    h_range: tuple[float, float],
    params: DSMParams,
    coarser: StagedLevel | None,
    stage_dir: Path,
    fingerprint: str,
) -> StagedLevel:
    """The graph that matches level ``geom`` in ``chunks`` into
    ``stage_dir/L<level>.zarr`` (searching around ``coarser``'s stored
    heights, or the whole height range at the coarsest level): heights at
    a coarse level, heights and confidence at the finest."""
    # the side of the level's chunks (:func:`~tiledsm.dsm.levels.level_layout`):
    # a merged last chunk covers two store blocks
    side = max(int(geom.grid.chunk), min_chunk(params))
    variables = ("height", "confidence") if geom.level == 0 else ("height",)
    store = ChunkStore(str(Path(stage_dir) / f"L{geom.level}.zarr"), variables, tuple(geom.grid.shape), (side, side))
    fp = json.dumps({"dsm": json.loads(fingerprint), "level": geom.level}, sort_keys=True)
    # fixed names, as the plain graph's ``match-L<level>`` (one DSM per graph)
    setup_key, name = f"stage-setup-L{geom.level}", f"match-L{geom.level}"
    fn = partial(
        _staged_task, staged_in=None if coarser is None else coarser.level, store=store, views=list(views), geom=geom,
        chunks=chunks, h_range=tuple(h_range), params=params,
    )
    tasks = {}
    for i in range(len(chunks[0])):
        for j in range(len(chunks[1])):
            # the coarser tasks that write the coarse cells this task reads
            reads = [] if coarser is None else coarser.writers(*_coarse_extent(coarser.level, chunks, i, j, params)[1])
            tasks[(name, i, j)] = (fn, i, j, setup_key, *reads)
    layers = {setup_key: {setup_key: (_setup, store, fp, geom, tuple(map(len, chunks)))}, name: tasks}
    deps = {setup_key: set(), name: {setup_key} | ({coarser.name} if coarser else set())}
    graph = HighLevelGraph(layers, deps)
    if coarser is not None:
        graph = HighLevelGraph.merge(coarser.graph, graph)
    return StagedLevel(LevelStore(store, geom), tuple(map(tuple, chunks)), name, graph)


def finest_from_stage(staged: StagedLevel, chunks: tuple[tuple[int, ...], tuple[int, ...]], params: DSMParams) -> da.Array:
    """Lazy ``(2, H, W)`` heights and confidence of the finest level, chunked
    ``chunks`` (the grid's), from its store once complete: each task reads
    its chunk plus the speckle filter's halo and filters it (as
    :func:`~tiledsm.dsm.levels.despeckle`)."""
    from tiledsm.dsm.levels import chunk_window

    size, max_diff = speckle_rule(staged.level.geom, params)
    name = f"despeckle-L{staged.level.geom.level}"
    fn = partial(_despeckled_task, staged=staged.level, chunks=chunks, max_diff=max_diff, size=max(size, 0))
    layer = {}
    for i in range(len(chunks[0])):
        for j in range(len(chunks[1])):
            _, _, r0, r1 = chunk_window(chunks[0], i, max(size, 0))
            _, _, c0, c1 = chunk_window(chunks[1], j, max(size, 0))
            layer[(name, 0, i, j)] = (fn, i, j, *staged.writers(r0, r1, c0, c1))
    graph = HighLevelGraph.merge(staged.graph, HighLevelGraph({name: layer}, {name: {staged.name}}))
    return da.Array(graph, name, ((2,), *chunks), dtype=np.float32, meta=np.empty((0, 0, 0), np.float32))


def stage_reports(stage_dir: Path) -> dict[str, dict]:
    """``{"L<level>": {"chunks_total", "chunks_reused", "cells_searched",
    "mean_candidates_per_cell"}}`` of the level stores in ``stage_dir``
    once a run has matched them: what it computed, what it took from an
    earlier run, and how many candidate heights a searched cell had on
    average (the cost of matching follows it)."""
    import zarr

    out = {}
    for path in sorted(Path(stage_dir).glob("L*.zarr*")):
        where = f"{_COUNTS}/"
        try:
            computed = np.asarray(zarr.open_array(store=str(path), path=where + _COMPUTED, mode="r")[...])
            n, cells = (int(np.asarray(zarr.open_array(store=str(path), path=where + k, mode="r")[...]).sum())
                        for k, _ in _CANDIDATES)
        except Exception:  # not a level store of ours
            continue
        out[path.name.split(".")[0]] = {
            "chunks_total": int(computed.size), "chunks_reused": int(computed.size - computed.sum()),
            "cells_searched": cells, "mean_candidates_per_cell": n / cells if cells else None,
        }
    return out
