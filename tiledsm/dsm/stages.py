"""The DSM engine: every pyramid level matched into a store on disk, so
that a worker's memory does not grow with the scene, built with dask's
public array API only.

Each level is matched into a folder of block files
(:class:`~tiledsm.io.BlockFiles`, one block per matching chunk, each
written and read by its task's own thread) by one
``map_blocks`` over its chunk grid whose tasks write their chunk and
return a one-cell token (:func:`stage_level`); every later task reads the
window it needs from the store: a finer level its coarse heights, the
finest level's speckle filter its chunk plus halo (:func:`finest_from_stage`).
A reading task receives, as extra array arguments, the tokens of exactly
the tasks that write the blocks it reads (:func:`_writer_tokens`: the
token array's blocks picked with ``Array.blocks``), and of no others: no
level waits for the whole coarser level, so a finer level's first chunks
are matched while the coarser level's last ones still run, and the
speckle filter and the DSM's writes start as soon as a chunk's neighbours
are matched (on 2 workers, a thread does not idle at each level's end).
No worker holds results for its neighbours: the tokens are one byte. The
stores hold raw matched heights; the speckle filter of a level runs on the
window read, grown by the filter's own halo, which makes it exact in any
chunking (a component smaller than the halo lies inside the window), so
the DSM does not depend on the chunks (tested against a plain graph in
``tests/dsm/plain_graph.py``).

A store's blocks finished by an interrupted run are kept: the tasks of
blocks already written return at once. The store records which of its
chunks this run computed and the candidate heights of its searched cells
(:func:`stage_reports`). The level stores (``L<level>.blocks``) are
scratch: the run removes them once the DSM store is finished. Stores
carry the DSM's fingerprint; one computed from anything else is discarded
when its level is set up.
"""

from __future__ import annotations

import json
import shutil
import tempfile
import weakref
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Sequence

import dask
import dask.array as da
from dask.base import tokenize
import numpy as np

from tiledsm.dsm.layout import LevelLayout, chunk_window
from tiledsm.dsm.levels import LevelGeometry, match_task
from tiledsm.dsm.params import DSMParams
from tiledsm.dsm.views import View
from tiledsm.errors import InputFileError
from tiledsm.io import BlockFiles

__all__ = ["LEVELS_DIR", "LevelStore", "StagedLevel", "ScratchFolder", "stage_level", "finest_from_stage",
           "stage_reports"]

#: the folder of a run's level stores, beside ``dsm.zarr`` (removed once
#: the DSM store is finished)
LEVELS_DIR = "dsm.levels"


@dataclass(frozen=True)
class LevelStore:
    """Where a level's matched heights are: what its readers' tasks carry.

    Attributes
    ----------
    store : BlockFiles
        ``height`` (float32 ellipsoidal metres, NaN = none; at the finest
        level also ``confidence``), blocks of the level's chunk side, each
        with the candidate heights summed over its searched cells and
        their count.
    geom : LevelGeometry
        The level.
    layout : LevelLayout
        Its chunks, halos and depths.
    """

    store: BlockFiles
    geom: LevelGeometry
    layout: LevelLayout


@dataclass(frozen=True)
class StagedLevel:
    """A level whose matched heights a graph writes into a store.

    Attributes
    ----------
    level : LevelStore
        The store and the level.
    tokens : dask.array.Array
        ``bool`` of shape :attr:`LevelLayout.numblocks`, one cell per block
        (chunks of 1): block ``(i, j)`` is the task that writes matching
        chunk ``(i, j)`` into the store (True when this run computed it),
        after the coarser levels' tasks it reads.
    """

    level: LevelStore
    tokens: da.Array


class ScratchFolder:
    """A temporary folder for the level stores of a DSM computed without a
    ``stage_dir``: removed when the last graph that holds this object is
    gone (on the client; a copy sent to a worker is only its path)."""

    def __init__(self) -> None:
        self.path = Path(tempfile.mkdtemp(prefix="tiledsm-levels-"))
        weakref.finalize(self, shutil.rmtree, str(self.path), True)

    def __reduce__(self):
        return (Path, (str(self.path),))


def _writer_tokens(tokens: da.Array, rows: Sequence[range], cols: Sequence[range]) -> list[da.Array]:
    """Arrays of ``len(rows) x len(cols)`` one-cell blocks: block ``(i, j)``
    of them, together, are the blocks ``rows[i] x cols[j]`` of ``tokens``
    (each at least once): what a task reading the cells of those writers
    receives, so that it runs after them and after no others."""
    out = []
    for a in range(max(len(r) for r in rows)):
        by_row = tokens.blocks[[r[min(a, len(r) - 1)] for r in rows]]
        for b in range(max(len(c) for c in cols)):
            out.append(by_row.blocks[:, [c[min(b, len(c) - 1)] for c in cols]])
    return out


# ------------------------------------------------------------------ windows
def _read(store: BlockFiles, r0: int, r1: int, c0: int, c1: int, variable: str = "height") -> np.ndarray:
    return store.read(r0, r1, c0, c1, variable)


def coarse_heights(coarser: LevelStore, layout: LevelLayout, i: int, j: int) -> np.ndarray:
    """The coarse heights finer task ``(i, j)`` of ``layout`` searches
    around, read from ``coarser``'s store: its
    :meth:`~LevelLayout.coarse_window` (NaN beyond the grid), speckles
    removed.

    The filter runs on the window grown by its own halo, clipped to the
    grid (:meth:`~LevelLayout.coarse_reads`): a component smaller than that
    lies inside it, so every cell kept is the one the whole-level filter
    keeps.
    """
    from tiledsm.match.sgm import remove_speckles

    cl = coarser.layout
    a0, a1, b0, b1 = layout.coarse_window(i, j, cl.shape)
    r0, r1, c0, c1 = layout.coarse_reads(i, j, cl)
    H, W = cl.shape
    h = _read(coarser.store, r0, r1, c0, c1)
    if cl.speckle_size > 1:
        h = remove_speckles(h, cl.speckle_max_diff, cl.speckle_size)
    out = np.full((a1 - a0, b1 - b0), np.nan, np.float32)
    y0, y1, x0, x1 = max(a0, 0), min(a1, H), max(b0, 0), min(b1, W)
    out[y0 - a0 : y1 - a0, x0 - b0 : x1 - b0] = h[y0 - r0 : y1 - r0, x0 - c0 : x1 - c0]
    return out


# ------------------------------------------------------------------ tasks
def _setup(store: BlockFiles, fingerprint: str, tasks: tuple[int, int], keep=None) -> np.ndarray:
    """Create the level's store, or keep it (resume) when it holds the same
    fingerprint; a store of anything else is discarded. No task of the
    ``tasks`` chunks is marked computed yet. ``keep``: an object the graph
    must hold while it exists (a :class:`ScratchFolder`)."""
    store.prepare({"fingerprint": fingerprint, "tasks": list(tasks)})
    return np.ones((1, 1), bool)


def _staged_task(*_ready, block_id, coarser, level, views, h_range, params) -> np.ndarray:
    """Match chunk ``block_id`` of ``level`` and write it into its store,
    unless an earlier run did; a ``(1, 1)`` token: whether it was computed.
    ``_ready``: the level's setup, and the coarser tasks it reads (at the
    coarsest level a block index; their values unused)."""
    store, layout = level.store, level.layout
    i, j = block_id
    r0, r1, c0, c1 = layout.chunk_cells(i, j)
    blocks = store.blocks_under(r0, r1, c0, c1)
    if store.blocks_done(blocks):
        return np.zeros((1, 1), bool)
    coarse = None if coarser is None else coarse_heights(coarser, layout, i, j)
    details: dict = {}
    res = match_task(coarse, views, level.geom, layout, h_range, params, i, j, details=details)
    for bi, bj in blocks:
        w0, w1, v0, v1 = store.block_window(bi, bj)
        cand = details["candidates"][w0 - r0 : w1 - r0, v0 - c0 : v1 - c0]
        part = res[:, w0 - r0 : w1 - r0, v0 - c0 : v1 - c0]
        store.write_block(bi, bj, dict(zip(store.variables, part)), counts=(int(cand.sum()), int((cand > 0).sum())))
    store.mark_computed(i, j)
    return np.ones((1, 1), bool)


def _despeckled_task(*_ready, block_id, level, grid_chunks) -> np.ndarray:
    """Heights and confidence of grid chunk ``block_id[-2:]`` of the finest
    level, read with the speckle filter's halo from its store and filtered
    (``_ready``: the matching tasks that wrote them)."""
    from tiledsm.match.sgm import remove_speckles

    layout = level.layout
    size = layout.speckle_halo
    i, j = block_id[-2:]
    r0, r1, hr0, hr1 = chunk_window(grid_chunks[0], i, size)
    c0, c1, hc0, hc1 = chunk_window(grid_chunks[1], j, size)
    height = _read(level.store, hr0, hr1, hc0, hc1)
    if layout.speckle_size > 1:
        height = remove_speckles(height, layout.speckle_max_diff, layout.speckle_size)
    # the filter leaves the confidence as it is: read without the halo
    rest = [_read(level.store, r0, r1, c0, c1, v) for v in level.store.variables[1:]]
    return np.stack([height[r0 - hr0 : r1 - hr0, c0 - hc0 : c1 - hc0], *rest])


# ------------------------------------------------------------------ graphs
def stage_level(
    views: Sequence[View],
    geom: LevelGeometry,
    layout: LevelLayout,
    h_range: tuple[float, float],
    params: DSMParams,
    coarser: StagedLevel | None,
    stage_dir: Path,
    fingerprint: str,
    keep: ScratchFolder | None = None,
) -> StagedLevel:
    """The graph that matches level ``geom`` in ``layout``'s chunks into
    ``stage_dir/L<level>.blocks`` (searching around ``coarser``'s stored
    heights, or the whole height range at the coarsest level): heights at
    a coarse level, heights and confidence at the finest. ``keep`` rides
    along in the level's setup task (:class:`ScratchFolder`)."""
    side = layout.side
    variables = ("height", "confidence") if geom.level == 0 else ("height",)
    store = BlockFiles(Path(stage_dir) / f"L{geom.level}.blocks", variables, layout.shape, side)
    level = LevelStore(store, geom, layout)
    fp = json.dumps({"dsm": json.loads(fingerprint), "level": geom.level}, sort_keys=True)
    # one DSM's tasks apart from another's (two epochs may share a graph)
    token = tokenize(fp, store.path)
    setup = da.from_delayed(
        dask.delayed(_setup)(store, fp, layout.numblocks, keep,
                             dask_key_name=f"stage-setup-L{geom.level}-{token}"),
        shape=(1, 1), dtype=bool, meta=np.empty((0, 0), bool),
    )
    if coarser is None:
        # the coarsest level reads nothing: a block-index array gives its tasks their grid
        reads = [da.zeros(layout.numblocks, chunks=1, dtype=bool)]
    else:
        cl = coarser.level.layout
        # the coarser tasks that write the coarse cells each task reads (rows by i, columns by j)
        rows = [cl.writers(layout.coarse_reads(i, 0, cl))[0] for i in range(layout.numblocks[0])]
        cols = [cl.writers(layout.coarse_reads(0, j, cl))[1] for j in range(layout.numblocks[1])]
        reads = _writer_tokens(coarser.tokens, rows, cols)
    fn = partial(_staged_task, coarser=None if coarser is None else coarser.level, level=level, views=list(views),
                 h_range=tuple(h_range), params=params)
    tokens = da.map_blocks(fn, setup, *reads, dtype=bool, meta=np.empty((0, 0), bool),
                           name=f"match-L{geom.level}-{token}")
    return StagedLevel(level, tokens)


def finest_from_stage(staged: StagedLevel, grid_chunks: tuple[tuple[int, ...], tuple[int, ...]]) -> da.Array:
    """Lazy ``(2, H, W)`` heights and confidence of the finest level, chunked
    ``grid_chunks`` (the grid's), from its store: each task reads its chunk
    plus the speckle filter's halo once the tasks writing them are done,
    and filters it."""
    layout = staged.level.layout
    halo = layout.speckle_halo
    rows = [layout.writers((*chunk_window(grid_chunks[0], i, halo)[2:], 0, 1))[0] for i in range(len(grid_chunks[0]))]
    cols = [layout.writers((0, 1, *chunk_window(grid_chunks[1], j, halo)[2:]))[1] for j in range(len(grid_chunks[1]))]
    reads = _writer_tokens(staged.tokens, rows, cols)
    name = staged.tokens.name.replace("match-", "despeckle-", 1)
    fn = partial(_despeckled_task, level=staged.level, grid_chunks=grid_chunks)
    return da.map_blocks(fn, *reads, chunks=((2,), *grid_chunks), new_axis=[0], dtype=np.float32,
                         meta=np.empty((0, 0, 0), np.float32), name=name)


def stage_reports(stage_dir: Path) -> dict[str, dict]:
    """``{"L<level>": {"chunks_total", "chunks_reused", "cells_searched",
    "mean_candidates_per_cell"}}`` of the level stores in ``stage_dir``
    once a run has matched them: what it computed, what it took from an
    earlier run, and how many candidate heights a searched cell had on
    average (the cost of matching follows it)."""
    out = {}
    for path in sorted(Path(stage_dir).glob("L*.blocks")):
        try:
            store = BlockFiles.open(path)
        except InputFileError:  # not a level store of ours
            continue
        attrs = store.attrs() or {}
        if "tasks" not in attrs:
            continue
        total = int(np.prod(attrs["tasks"]))
        n, cells = (int(v) for v in store.counts())
        out[path.name.split(".")[0]] = {
            "chunks_total": total, "chunks_reused": total - store.computed(),
            "cells_searched": cells, "mean_candidates_per_cell": n / cells if cells else None,
        }
    return out
