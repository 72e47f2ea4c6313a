"""Where the tasks of one pyramid level read and write: its matching
chunks, and every halo and depth around them, computed once per level
(:class:`LevelLayout`). The engine (:mod:`tiledsm.dsm.stages`) and the
plan's memory estimate (:func:`tiledsm.dsm.memory.dsm_levels`) ask it;
nothing else restates the arithmetic.

Conventions: cells of the level's grid, rows then columns; windows are
half-open ``[start, stop)``; coarse cell ``I`` covers cells ``2I, 2I+1``
of the next finer level.
"""

from __future__ import annotations

from dataclasses import dataclass

from tiledsm.dsm.params import DSMParams
from tiledsm.errors import MatchingError

__all__ = ["LevelLayout", "level_layout", "level_chunks", "min_chunk", "chunk_window"]

Window = tuple[int, int, int, int]


def _matching_halo(params: DSMParams) -> int:
    return params.halo()


def _coarse_depth(params: DSMParams) -> int:
    """Coarser cells a finer task reads around its chunk's half: the search
    band's support (:func:`~tiledsm.match.pyramid.search_halo`) plus half
    the matching halo."""
    from tiledsm.match.pyramid import search_halo

    return search_halo(params.search) + _matching_halo(params) // 2


def min_chunk(params: DSMParams) -> int:
    """Smallest chunk side a level is matched in: its halo must fit in a
    neighbour, and so must the coarser cells a task derives its search
    band from (half a chunk deep)."""
    return max(_matching_halo(params), 2 * _coarse_depth(params))


def level_chunks(n: int, chunk: int, min_size: int) -> tuple[int, ...]:
    """Chunk sizes of one axis of ``n`` cells: ``chunk`` each, the last one
    merged into its neighbour when it would be smaller than ``min_size``
    (a halo must fit in every chunk)."""
    sizes = [chunk] * (n // chunk) + ([n % chunk] if n % chunk else [])
    if len(sizes) > 1 and sizes[-1] < min_size:
        last = sizes.pop()
        sizes[-1] += last
    return tuple(sizes)


def chunk_window(chunks: tuple[int, ...], index: int, halo: int) -> Window:
    """``(start, stop, halo_start, halo_stop)`` of chunk ``index`` of an
    axis chunked as ``chunks``, the halo clipped to the axis."""
    start = sum(chunks[:index])
    stop = start + chunks[index]
    return start, stop, max(0, start - halo), min(sum(chunks), stop + halo)


@dataclass(frozen=True)
class LevelLayout:
    """The chunks of one pyramid level and every halo and depth around
    them.

    Attributes
    ----------
    level : int
        0 = full resolution.
    shape : (int, int)
        The level's cells ``(rows, cols)``.
    side : int
        Chunk side the level is matched in (the grid's chunk, raised to
        :func:`min_chunk`), cells: also the block side of its store.
    chunks : tuple of tuple of int
        Matching chunks ``(rows, cols)``: ``side`` each, a short last
        chunk merged into its neighbour (a merged chunk covers two store
        blocks).
    halo : int
        Most cells a matching task reaches beyond its chunk
        (:meth:`DSMParams.halo <tiledsm.dsm.params.DSMParams.halo>`).
    path_period : int
        Restart period of the semi-global paths, cells (0 = none).
    half_window : int
        Half the correlation window, cells.
    coarse_depth : int
        Coarser cells a task reads around its chunk's half.
    search_depth : int
        Of those, the search band's support
        (:func:`~tiledsm.match.pyramid.search_halo`).
    speckle_size : int
        The speckle filter's smallest kept component at this level, cells
        (<= 1: no filter); also the filter's halo, which makes it exact in
        any chunking.
    speckle_max_diff : float
        Metres between 4-neighbours of one component.
    """

    level: int
    shape: tuple[int, int]
    side: int
    chunks: tuple[tuple[int, ...], tuple[int, ...]]
    halo: int
    path_period: int
    half_window: int
    coarse_depth: int
    search_depth: int
    speckle_size: int
    speckle_max_diff: float

    @property
    def numblocks(self) -> tuple[int, int]:
        """Matching chunks per axis."""
        return len(self.chunks[0]), len(self.chunks[1])

    @property
    def speckle_halo(self) -> int:
        """Cells the speckle filter reads around what it filters."""
        return max(self.speckle_size, 0)

    def chunk_cells(self, i: int, j: int) -> Window:
        """``(row0, row1, col0, col1)`` of matching chunk ``(i, j)``."""
        r0, r1, _, _ = chunk_window(self.chunks[0], i, 0)
        c0, c1, _, _ = chunk_window(self.chunks[1], j, 0)
        return r0, r1, c0, c1

    def task_window(self, axis: int, index: int) -> Window:
        """``(start, stop, lo, hi)``: chunk ``index`` along ``axis`` and the
        cells ``[lo, hi)`` its matching task computes.

        A cell's aggregated cost depends only on the costs between the
        semi-global paths' restart lines around it (every ``path_period``
        cells of the whole grid), and a cost on the samples of its
        correlation window: the task reaches from the restart line at or
        before ``start`` to the one at or after ``stop``, plus half a
        window, clipped to the axis. A chunk that starts and ends on
        restart lines (chunks of 512, period 64) is matched with only the
        window's few extra cells instead of a full halo on each side, with
        the same result. Without restarts (period 0) the halo is
        :attr:`halo`.
        """
        chunks = self.chunks[axis]
        n = sum(chunks)
        start, stop, _, _ = chunk_window(chunks, index, 0)
        p = self.path_period
        if p > 0:
            lo, hi = (start // p) * p - self.half_window, -(-stop // p) * p + self.half_window
        else:
            lo, hi = start - self.halo, stop + self.halo
        lo, hi = max(0, lo), min(n, hi)
        if start - lo > self.halo or hi - stop > self.halo:
            raise MatchingError(f"internal: task window {(lo, hi)} of chunk {(start, stop)} exceeds the halo {self.halo}")
        return start, stop, lo, hi

    def largest_task(self) -> tuple[int, int]:
        """Longest extent per axis of the cells a matching task computes."""
        return tuple(
            max(hi - lo for _, _, lo, hi in (self.task_window(axis, k) for k in range(len(self.chunks[axis]))))
            for axis in (0, 1)
        )

    def coarse_window(self, i: int, j: int, coarse_shape: tuple[int, int]) -> Window:
        """``(a0, a1, b0, b1)``: the coarser level's cells (``coarse_shape``) matching task
        ``(i, j)`` searches around -- the coarse cells under its chunk
        (half of each chunk, the last one taking the rest of the coarse
        axis) grown by :attr:`coarse_depth`; may reach beyond the coarse
        grid (NaN there)."""
        out = []
        for axis, index in ((0, i), (1, j)):
            halves = [n // 2 for n in self.chunks[axis][:-1]]
            start = sum(halves[:index]) - self.coarse_depth
            size = halves[index] if index < len(halves) else coarse_shape[axis] - sum(halves)
            out += [start, start + size + 2 * self.coarse_depth]
        return tuple(out)

    def coarse_reads(self, i: int, j: int, coarser: "LevelLayout") -> Window:
        """The coarser level's cells task ``(i, j)`` reads from its store:
        :meth:`coarse_window` grown by the coarser level's speckle halo
        (the filter runs on the window read), clipped to the coarse grid."""
        a0, a1, b0, b1 = self.coarse_window(i, j, coarser.shape)
        halo = coarser.speckle_halo
        H, W = coarser.shape
        return max(0, a0 - halo), min(H, a1 + halo), max(0, b0 - halo), min(W, b1 + halo)

    def writers(self, window: Window) -> tuple[range, range]:
        """Matching chunks ``(rows, cols)`` of this level that hold some of
        the cells ``window = (row0, row1, col0, col1)``: the tasks a reader
        of those cells waits for."""
        return tuple(_overlapping(self.chunks[axis], window[2 * axis], window[2 * axis + 1]) for axis in (0, 1))


def _overlapping(chunks: tuple[int, ...], start: int, stop: int) -> range:
    """Indices of the chunks of an axis chunked ``chunks`` that hold some of
    ``[start, stop)``."""
    import bisect
    import itertools

    edges = [0, *itertools.accumulate(chunks)]
    first = max(bisect.bisect_right(edges, start) - 1, 0)
    last = min(bisect.bisect_left(edges, stop), len(chunks))
    return range(first, max(first, last))


def level_layout(geom, grid_chunk: int, params: DSMParams) -> LevelLayout:
    """The :class:`LevelLayout` of level ``geom``
    (:class:`~tiledsm.dsm.levels.LevelGeometry`) for a grid chunked
    ``grid_chunk``: a chunk smaller than the halos (:func:`min_chunk`)
    would be matched in larger ones (then rechunked to the grid's), as the
    work of a chunk grows with its halo."""
    from tiledsm.match.pyramid import search_halo

    floor = min_chunk(params)
    side = max(int(grid_chunk), floor)
    shape = tuple(int(n) for n in geom.grid.shape)
    # the same ground area at every level: a coarse cell is 4**level cells
    # (a 16 m tower is 64 cells at level 2, a speckle at level 0)
    speckle = int(params.match.speckle_size) // 4**geom.level
    return LevelLayout(
        level=int(geom.level), shape=shape, side=side, chunks=tuple(level_chunks(n, side, floor) for n in shape),
        halo=_matching_halo(params), path_period=int(params.match.path_period),
        half_window=int(params.match.window) // 2, coarse_depth=_coarse_depth(params),
        search_depth=search_halo(params.search), speckle_size=speckle,
        speckle_max_diff=float(params.match.speckle_max_diff(geom.grid.resolution, geom.step)),
    )
