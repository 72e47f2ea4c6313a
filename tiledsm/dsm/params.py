"""Parameters of the DSM stage: :class:`DSMParams`, one frozen pydantic
model holding the matching's (:class:`~tiledsm.match.sgvll.SGVLLParams`)
and the search band's (:class:`~tiledsm.match.pyramid.SearchParams`).

A recipe sets them in its ``grid`` and ``match`` sections
(:class:`tiledsm.recipes.GridSpec`, :class:`tiledsm.recipes.MatchSpec`,
whose ``params`` is the :class:`~tiledsm.match.sgvll.SGVLLParams` itself);
:meth:`DSMParams.of_recipe` validates them into the engine's model, the
parameters a recipe does not set at their defaults. Its dump
(``model_dump()``) is the ``params`` of the run's fingerprint.
"""

from __future__ import annotations

from typing import Optional

from pydantic import Field

from tiledsm.match.pyramid import SearchParams
from tiledsm.match.params import SGVLLParams
from tiledsm.recipes import ChunkSide, GridSpec, MatchSetup, MatchSpec

__all__ = ["DSMParams"]


class DSMParams(MatchSetup):
    """Parameters of the DSM stage.

    Attributes
    ----------
    resolution : float or None
        Ground cell size, metres; ``None`` takes the mean GSD of the views.
    crs : str or None
        CRS of the default grid (when no grid is given; projected, metres);
        ``None`` takes the UTM zone of the scene centre.
    chunk : int
        Chunk side of the output grid, cells.
    levels : int or None
        Pyramid levels (1 = full resolution only). ``None`` chooses: one
        level while the full-resolution sweep needs at most
        ``max_candidates`` heights, and one more level for each doubling
        beyond (measured on synthetic truth, a coarse level costs
        completeness next to buildings, so it is used only when the search
        is wide).
    max_candidates : int
        See ``levels``. 128: the real pair (136 heights) is matched in 2
        levels, faster at the same NMAD, while the demo scene (126) keeps
        one (docs: decisions/labels.md).
    height_range : (float, float) or None
        Scene height range (ellipsoidal metres); ``None`` estimates it from
        tie points.
    height_margin : float
        Metres added on both sides of the tie-point height range.
    refine_steps : int
        Height steps searched on each side of the upsampled coarser DSM at
        the finer levels.
    sweep_step_factor : float
        With two or more levels, the coarsest level sweeps the whole height
        range with steps this many times its own (about ``step_px`` pixels
        of parallax): its heights only centre the next level's band of
        ``± refine_steps`` of that level's steps, whose sub-step
        refinement they need not match. 2 halves the sweep's candidates;
        measured on ``s2p_pair`` in 2 levels (``benchmarks/blunders.py``):
        40 cells off by more than 10 m instead of 47 at the same NMAD
        (0.294 m), and the 4096² scene 1.15x faster at the same NMAD
        against its truth (``benchmarks/dsm.py``).
    relative_correction : bool
        Correct the relative pointing error of views 2.. by a translation
        estimated from tie points.
    match : SGVLLParams
        Matching parameters (window, penalties, thresholds).
    search : SearchParams
        How a coarser level's DSM becomes a finer level's search band.
    """

    resolution: Optional[float] = Field(None, gt=0, description="ground cell size, metres; None: the views' mean GSD")
    crs: Optional[str] = Field(None, description="CRS of the default grid (projected, metres); None: UTM zone of the "
                               "scene centre")
    chunk: ChunkSide = Field(512, description="chunk side of the output grid, cells (even)")
    max_candidates: int = Field(128, ge=1, description="heights a full-resolution sweep may need before levels=None "
                                "adds a level")
    refine_steps: int = Field(4, ge=0, description="height steps searched on each side of the upsampled coarser DSM")
    sweep_step_factor: float = Field(2.0, ge=1, description="the coarsest level of two or more sweeps with steps "
                                     "this many times its own")
    match: SGVLLParams = Field(SGVLLParams(), description="matching parameters")
    search: SearchParams = Field(SearchParams(), description="how a coarser level's DSM becomes a finer level's band")

    @classmethod
    def of_recipe(cls, grid: GridSpec, match: MatchSpec) -> DSMParams:
        """The parameters of a recipe's ``grid`` and ``match`` sections
        (each value already checked there, naming its field): the grid's
        cell size, CRS and chunk, the matching section's fields with its
        ``params`` as :attr:`match`; the others at their defaults."""
        return cls.model_validate({**grid.model_dump(include={"resolution", "crs", "chunk"}),
                                   **match.model_dump(exclude={"params"}), "match": match.params})

    def halo(self) -> int:
        """Most cells (even) a matching task reaches beyond its chunk
        (:meth:`tiledsm.dsm.layout.LevelLayout.task_window`): back to the previous
        restart line of the semi-global paths
        (:attr:`~tiledsm.match.sgvll.SGVLLParams.path_period`, which makes
        the aggregation exact in every chunking) plus half the correlation
        window. Chunks start on even cells, so with an even period a chunk
        edge lies at most ``period - 2`` cells past a restart line. Without
        restarts (period 0): twice the correlation window."""
        p = self.match.path_period
        reach = p - 2 + p % 2 + self.match.window // 2 if p > 0 else 2 * self.match.window
        h = max(2 * self.match.window, reach)
        return h + h % 2
