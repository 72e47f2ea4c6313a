"""Parameters of the DSM stage (:class:`DSMParams`)."""

from __future__ import annotations

from dataclasses import dataclass, field


from tiledsm.match.pyramid import SearchParams
from tiledsm.match.sgvll import SGVLLParams


@dataclass(frozen=True)
class DSMParams:
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

    resolution: float | None = None
    crs: str | None = None
    chunk: int = 512
    levels: int | None = None
    max_candidates: int = 128
    height_range: tuple[float, float] | None = None
    height_margin: float = 10.0
    refine_steps: int = 4
    sweep_step_factor: float = 2.0
    relative_correction: bool = True
    match: SGVLLParams = field(default_factory=SGVLLParams)
    search: SearchParams = field(default_factory=SearchParams)

    def __post_init__(self) -> None:
        if self.chunk < 32 or self.chunk % 2:
            # even chunks keep coarse and fine chunk corners aligned
            raise ValueError(f"DSMParams.chunk must be even and >= 32, got {self.chunk}")
        if self.levels is not None and self.levels < 1:
            raise ValueError(f"DSMParams.levels must be >= 1, got {self.levels}")
        if self.sweep_step_factor < 1:
            raise ValueError(f"DSMParams.sweep_step_factor must be >= 1, got {self.sweep_step_factor}")

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
