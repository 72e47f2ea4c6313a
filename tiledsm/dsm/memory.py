"""Estimated peak memory of a DSM worker and the sizes of every pyramid level."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass


#: memory of a local dask worker process before its first large task, MiB:
#: measured on the 2-core development machine, an idle worker holds 216 MiB
#: and one that has run a small matching task (numba kernels loaded) 296 MiB,
#: of which ~28 MiB was that task's cost volumes
WORKER_BASELINE_MIB = 270

#: the most heights a cell of a finer level is sampled at, in candidates
#: of the level: a cell is sampled at the labels of every band whose ZNCC
#: window holds it. Measured 1.88 (49 labels for bands of up to 26) on the
#: level-0 task of a 2048² synthetic scene (benchmarks/cuda_kernel.py
#: --capture; tiledsm.match.sweep.sample_plan)
SAMPLE_SPAN = 2.0

#: host memory a process adds once it matches on a CUDA device, MiB:
#: measured on an H100 machine, the peak RSS of benchmarks/cuda_kernel.py grew
#: from 313 to 522 MiB at its first task matched by the 'cuda' kernel (numba's
#: CUDA context and driver; benchmarks/results/cuda_kernel.json, peak_rss_mib)
CUDA_CONTEXT_MIB = 210

MIB = 2**20
GIB = 2**30




@dataclass(frozen=True)
class LevelPlan:
    """One pyramid level of a DSM run.

    Attributes
    ----------
    level : int
        0 = full resolution.
    shape : (int, int)
        Grid cells, rows x columns.
    resolution : float
        Cell size, metres.
    chunks : int
        Number of matching tasks (the level's chunks; a last chunk smaller
        than the halo is merged into its neighbour).
    step : float
        Height step, metres.
    candidates : int
        Most candidate heights a cell searches.
    task_cells : (int, int)
        Cells of the largest matching task (chunk plus halo), rows x columns.
    window_px : int
        Pixels read from one image for the largest task (full resolution,
        before decimation), the largest over the views.
    """

    level: int
    shape: tuple[int, int]
    resolution: float
    chunks: int
    step: float
    candidates: int
    task_cells: tuple[int, int]
    window_px: int


@dataclass(frozen=True)
class MemoryEstimate:
    """Estimated peak memory of one worker (bytes), see
    :func:`estimate_worker_memory`.

    Attributes
    ----------
    total : int
        ``baseline + max(matching, reading)``.
    baseline : int
        The worker process before the task (:data:`WORKER_BASELINE_MIB`).
    cost_volumes : int
        The three cost-volume-sized buffers of a matching task.
    matching : int
        Cost volumes, per-view sample buffers and the decimated image
        windows held while matching.
    reading : int
        Reading the largest image window (the other windows held).
    device : int
        GPU memory of one task matching on a CUDA device (0 on the CPU).
    """

    total: int
    baseline: int
    cost_volumes: int
    matching: int
    reading: int
    device: int = 0

    def text(self) -> str:
        """One line: total (GiB and MiB) and parts (GiB); the GPU's share
        of a task when it matches on one."""
        gpu = f"; GPU ~{self.device / GIB:.2f} GiB per task" if self.device else ""
        return (
            f"~{self.total / GIB:.2f} GiB ({self.total / MIB:.0f} MiB) per worker (baseline {self.baseline / GIB:.2f} + "
            f"max(matching {self.matching / GIB:.2f} [cost volumes {self.cost_volumes / GIB:.2f}], "
            f"reading {self.reading / GIB:.2f})){gpu}"
        )


# --------------------------------------------------------------------------- memory
def estimate_worker_memory(
    task_cells: tuple[int, int],
    candidates: int,
    views: int = 2,
    window_px: int = 0,
    decimation: int = 1,
    itemsize: int = 2,
    baseline: int = WORKER_BASELINE_MIB * MIB,
    search_band: bool = False,
    volumes: int = 2,
    on_device: bool = False,
) -> MemoryEstimate:
    """Peak memory of a worker running one matching task.

    A task matches ``ny x nx`` cells (chunk plus halo) with ``nd``
    candidate heights each (:func:`tiledsm.match.sgvll.match_block`).
    ``k`` buffers of ``ny * nx * nd`` float32 live at once: the cost volume
    ``vol`` of ``match_block`` and the aggregated cost ``S``
    (``winner_take_all`` reads ``S`` and ``vol`` in place), ``k = 2`` with
    the fast kernel (:mod:`tiledsm.match.sweep`, which aggregates without
    copying the volume), ``k = 3`` with the reference kernel (whose
    :func:`tiledsm.match.sgm.aggregate` makes a NaN-filled copy). Besides them the
    task holds one float32 sample buffer per view (``nv * ny * nx``), each
    view's image window, decimated by ``f``, and below the coarsest level
    its search band (``h_ref, lo, hi``: ``b = 1``, else ``b = 0``). Reading
    a window of ``W`` pixels (``itemsize`` bytes each, before the volumes
    exist) briefly holds the raw masked array, its float32 masked copy and
    the NaN-filled result::

        matching = 4 k ny nx nd + 4 nv ny nx + 12 b ny nx + 4 nv W / f²
        reading  = W (itemsize + 10) + 4 nv W / f²
        peak     = baseline + max(matching, reading)

    Everything else a task allocates (the band's float64 temporaries, freed
    before the volumes exist; the projection lattice, 2-D ZNCC sums, SGM
    line buffers, the returned chunk) is a few 2-D arrays, left out. Tasks
    run one at a time per worker (one thread each).

    On a CUDA device (``on_device``, :mod:`tiledsm.match.cuda_kernel`) the
    task holds on the GPU the cost volume and the aggregated costs, its
    samples (``nv`` float32 per cell and sampled height: ``s = nd`` at the
    coarsest level, up to :data:`SAMPLE_SPAN` ``nd`` below it), the image
    windows and the per-cell arrays (``h_ref``, bands, labels: 56 bytes a
    cell)::

        device = 8 ny nx nd + 4 nv ny nx s + 4 nv W / f² + 56 ny nx

    Parameters
    ----------
    task_cells : (int, int)
        ``(ny, nx)`` cells of the task (chunk plus halo).
    candidates : int
        ``nd``, the most candidate heights of a cell.
    views : int
        ``nv``.
    window_px : int
        ``W``, full-resolution pixels of the largest image window.
    decimation : int
        ``f`` (``2**level``).
    itemsize : int
        Bytes per pixel of the images on disk.
    baseline : int
        Bytes of the worker before the task (default
        :data:`WORKER_BASELINE_MIB`).
    search_band : bool
        The task searches a band from a coarser level (``b`` above).
    volumes : int
        ``k``, cost-volume-sized buffers alive at once.
    on_device : bool
        The task matches on a CUDA device: ``device`` is filled.

    Returns
    -------
    MemoryEstimate
    """
    ny, nx = (int(v) for v in task_cells)
    cells = ny * nx
    held = 4 * views * window_px // (decimation * decimation)
    volume_bytes = int(volumes) * 4 * cells * int(candidates)
    matching = volume_bytes + 4 * views * cells + (12 * cells if search_band else 0) + held
    reading = window_px * (int(itemsize) + 10) + held
    device = 0
    if on_device:
        span = math.ceil(SAMPLE_SPAN * int(candidates)) if search_band else int(candidates)
        device = 8 * cells * int(candidates) + 4 * views * cells * span + held + 56 * cells
    return MemoryEstimate(int(baseline) + max(matching, reading), int(baseline), volume_bytes, matching, reading,
                          device)


def worker_baseline(match) -> int:
    """Bytes of a worker before its first task, for the matching
    parameters ``match`` (:class:`~tiledsm.match.sgvll.SGVLLParams`):
    :data:`WORKER_BASELINE_MIB`, plus :data:`CUDA_CONTEXT_MIB` when it
    matches on a CUDA device."""
    on_cuda = str(match.device).startswith("cuda")
    return (WORKER_BASELINE_MIB + (CUDA_CONTEXT_MIB if on_cuda else 0)) * MIB


def dsm_levels(views, grid, h_range: tuple[float, float], levels: int, params,
               itemsize: int | None = None) -> tuple[list[LevelPlan], MemoryEstimate]:
    """Sizes of every pyramid level of a DSM run and the worker memory of
    its largest task.

    Candidates per cell (see :func:`tiledsm.match.sgvll.match_block`): at
    the coarsest level the whole height range, ``ceil((hmax - hmin) / step)
    + 1``; at a finer level the band around the coarser DSM, at most
    ``2 ceil(hole_factor * refine_steps) + 1`` (its width under a coarse
    hole). The image window is that of a task at the grid centre over the
    whole height range (an upper bound for finer levels).

    ``itemsize`` (bytes per image pixel) is read from the views' files
    unless given (views of a synthetic scene not made yet).

    Returns
    -------
    (list of LevelPlan, MemoryEstimate)
        Levels from coarsest to finest, and the largest estimate over them.
    """
    import numpy as np
    import rasterio

    from tiledsm.dsm import level_geometry, level_layout
    from tiledsm.geometry.footprint import image_window

    if itemsize is None:
        itemsize = 1
        for v in views:
            with rasterio.open(v.path) as src:
                itemsize = max(itemsize, np.dtype(src.dtypes[0]).itemsize)
    span = float(h_range[1] - h_range[0])
    fine_band = 2 * math.ceil(params.search.hole_factor * params.refine_steps - 1e-9) + 1
    out: list[LevelPlan] = []
    worst: MemoryEstimate | None = None
    for level in range(levels - 1, -1, -1):
        geom = level_geometry(views, grid, level, h_range, params, levels)
        g = geom.grid
        layout = level_layout(geom, grid.chunk, params)
        chunks = layout.chunks
        task = layout.largest_task()
        full = math.ceil(span / geom.step - 1e-9) + 1
        nd = full if level == levels - 1 else min(full, fine_band)
        r0, c0 = (g.height - task[0]) // 2, (g.width - task[1]) // 2
        sub = g.subgrid(r0, r0 + task[0], c0, c0 + task[1])
        window = 0
        for v in views:
            win = image_window(v.rpc, sub, tuple(h_range), v.shape, margin=4 * geom.factor + 8)
            if win is not None:
                window = max(window, (win[1] - win[0]) * (win[3] - win[2]))
        est = estimate_worker_memory(task, nd, len(views), window, geom.factor, itemsize,
                                     baseline=worker_baseline(params.match), search_band=level != levels - 1,
                                     volumes=3 if params.match.kernel == "reference" else 2,
                                     on_device=str(params.match.device).startswith("cuda"))
        out.append(LevelPlan(level, g.shape, g.resolution, len(chunks[0]) * len(chunks[1]), geom.step, nd, task, window))
        if worst is None or est.total > worst.total:
            worst = dataclasses.replace(est, device=max(est.device, worst.device if worst else 0))
        elif est.device > worst.device:
            worst = dataclasses.replace(worst, device=est.device)
    return out, worst


