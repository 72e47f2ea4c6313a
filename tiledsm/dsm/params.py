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
        beyond.
    max_candidates : int
        See ``levels``. 128 (was 192): ``s2p_pair`` (134 candidates) now
        takes 2 levels and, with absolute labels and ``refine_steps`` 3,
        matches in 5.5 s instead of 8.7 s (2 worker processes), NMAD 0.302
        m either way, cells off by > 10 m 0.0082 % (full overlap),
        completeness 95.6 % (95.1). Not 96: the 4096² synthetic scene then
        takes 3 levels (45.8 s instead of 64.4 s on 2 threads, same
        accuracy), but the 768 px demo scene (126 candidates) takes 2 and
        loses 1.9 points of completeness on visible ground (97.2 -> 95.3
        %): a coarse level smears its building edges (README, "The DSM
        stage").
    height_range : (float, float) or None
        Scene height range (ellipsoidal metres); ``None`` estimates it from
        tie points.
    height_margin : float
        Metres added on both sides of the tie-point height range.
    refine_steps : int
        Height steps searched on each side of the upsampled coarser DSM at
        the finer levels (``SearchParams.hole_factor`` times more under a
        coarse hole). On ``s2p_pair`` at 2 levels (full overlap, against
        s2p's DSM, ``hole_factor`` 3): 3 / 4 / 6 steps gave cells off by >
        10 m 0.0095 / 0.0103 / 0.0145 %, RMSE 0.445 / 0.464 / 0.482 m, NMAD
        0.294 / 0.295 / 0.295 m, completeness 95.8 / 96.1 / 96.2 %: a wider
        band lets more mismatches in next to holes (4 steps with
        ``hole_factor`` 4: still 0.0103 %). It costs completeness on the
        synthetic scenes' building edges: 4096², 2 levels, 84.9 % with 4
        steps, 83.4 % with 3.
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
    refine_steps: int = 3
    relative_correction: bool = True
    match: SGVLLParams = field(default_factory=SGVLLParams)
    search: SearchParams = field(default_factory=SearchParams)

    def __post_init__(self) -> None:
        if self.chunk < 32 or self.chunk % 2:
            # even chunks keep coarse and fine chunk corners aligned
            raise ValueError(f"DSMParams.chunk must be even and >= 32, got {self.chunk}")
        if self.levels is not None and self.levels < 1:
            raise ValueError(f"DSMParams.levels must be >= 1, got {self.levels}")

    def halo(self) -> int:
        """Halo in cells (even) of a matching task: the semi-global paths'
        restart period (:attr:`~tiledsm.match.sgvll.SGVLLParams.path_period`,
        which makes the aggregation exact in every chunking), and at least
        twice the correlation window."""
        h = max(2 * self.match.window, self.match.path_period)
        return h + h % 2
