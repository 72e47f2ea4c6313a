"""The recipe section ``orient:``: the one parameter type of the
orientation stage (``tiledsm orient``, :class:`tiledsm.orient.recipe.OrientRecipe`,
the ``orient:`` of a ``dsm`` or ``deformation`` recipe) and of the library
functions that run it (:func:`tiledsm.orient.stage.orient_images` takes an
:class:`OrientSpec`; :func:`tiledsm.orient.tracks.tie_point_tracks`,
:func:`tiledsm.orient.adjust.adjust_block`,
:func:`tiledsm.orient.structural.match_tile_structural` and
:func:`tiledsm.orient.p2l.p2l_filter` its nested models).

Example::

    orient:
      gcps: gcps.csv            # id,image,lon,lat,h,row,col (or GeoJSON)
      check_points: checks.csv  # held out of the fit, reported
      dem: srtm.tif             # reference DEM constraining tie-point heights
      geoid: egm96_15.gtx       # the DEM's heights are above this geoid
      model: affine             # shift | affine; left out: by point count
      adjust:                   # advanced (recipe only): the adjustment's weights
        dem_sigma_m: 5.0

The top-level fields are the command's options; ``tracks`` (tie-point
matching, with ``structural`` and ``p2l``) and ``adjust`` hold the
advanced parameters, set in a recipe only. This module imports nothing
heavy: a recipe model needs it, not the adjustment.

Conventions as in :mod:`tiledsm.orient.points` (GDAL pixel coordinates,
WGS84 lon/lat, ellipsoidal heights).
"""

from __future__ import annotations

from typing import Literal, Optional

from pydantic import Field, field_validator, model_validator

from tiledsm.recipes import StrictModel, option

__all__ = ["OrientSpec", "TrackParams", "StructuralParams", "P2LParams", "AdjustParams"]


def _odd_side(value: int) -> int:
    """A window side with a centre pixel: odd, at least 3."""
    if value < 3 or value % 2 == 0:
        raise ValueError(f"expected an odd integer >= 3, got {value}")
    return value


class P2LParams(StrictModel):
    """``orient.tracks.p2l`` — P2L mismatch rejection of each image pair's
    matches (:func:`tiledsm.orient.p2l.p2l_filter`)."""

    n_heights: int = Field(5, ge=2, description="heights sampled across the range to trace each epipolar curve")
    k: float = Field(3.5, gt=0, description="rejection threshold, robust standard deviations of the residual")
    # a set of near-perfect matches must not reject matches at 0.3 px
    floor_px: float = Field(0.7, ge=0, description="smallest rejection threshold, pixels")
    iterations: int = Field(6, ge=1, description="robust trend fitting passes")


class StructuralParams(StrictModel):
    """``orient.tracks.structural`` — the structural extractor
    (:func:`tiledsm.orient.structural.match_tile_structural`: Wallis,
    Förstner, NCC along the RPC curve, probability relaxation)."""

    wallis_window: int = Field(31, ge=1, description="side of the Wallis filter's local statistics window, pixels")
    target_mean: float = Field(127.0, description="Wallis target mean, grey levels")
    target_std: float = Field(50.0, description="Wallis target standard deviation, grey levels")
    contrast: float = Field(0.8, ge=0, le=1, description="Wallis contrast constant c (1: the local standard "
                            "deviation is forced to target_std)")
    brightness: float = Field(0.9, ge=0, le=1, description="Wallis brightness constant b (1: the local mean is "
                              "forced to target_mean)")
    forstner_window: int = Field(5, description="side of the structure tensor's summation window, pixels (odd)")
    min_roundness: float = Field(0.5, description="smallest Förstner roundness q in (0, 1] (0 on a straight edge, "
                                 "1 on an isotropic corner)")
    weight_factor: float = Field(1.0, description="a point's weight w must exceed this times the tile's mean w")
    nms: int = Field(9, ge=1, description="side of the non-maximum suppression neighbourhood, pixels")
    # At X-junctions and blobs the least-squares position and the w maximum coincide; at an
    # L-shaped corner (a roof corner) the maximum lies 1-2 px inside the brighter side and the
    # position on the corner, a height discontinuity where area matching follows the strongest
    # edge: 1 px drops those (two 512 px tiles of a synthetic scene: 82 % of the matches within
    # 1 px of the truth instead of 73 %); forstner_window / 2 keeps them.
    max_offset_px: float = Field(1.0, description="largest distance (per axis) between a point's least-squares "
                                 "position and its w maximum, pixels")
    points_per_tile: int = Field(150, ge=1, description="strongest interest points kept per reference tile, at most")
    template: int = Field(15, description="NCC template side, pixels (odd)")
    curve_step_px: float = Field(1.0, gt=0, description="largest spacing of the height samples' projections in "
                                 "the other image, pixels")
    # the guide's shift leaves part of the relative bias across the curve
    margin_px: float = Field(4.0, description="search across the curve, pixels: the NCC read along the curve is "
                             "the largest within this distance, a candidate the 2-D peak there")
    min_ncc: float = Field(0.6, description="smallest NCC of a candidate")
    top_k: int = Field(4, ge=1, description="candidates per point and image, at most")
    peak_separation_px: float = Field(3.0, description="smallest distance between two candidates along the "
                                      "curve, pixels")
    radius_px: float = Field(64.0, description="neighbourhood radius of the relaxation, reference pixels")
    max_neighbours: int = Field(10, description="nearest neighbours used within the radius, at most")
    compat_px: float = Field(1.5, description="parallax difference always compatible, pixels")
    max_gradient: float = Field(0.1, description="parallax difference allowed per pixel of distance (disparity "
                                "gradient limit)")
    relax_a: float = Field(0.3, description="A of the update p(a) <- p(a) (A + B q(a)), q the mean support "
                           "(the 'no match' label keeps its p)")
    relax_b: float = Field(3.0, description="B of the same update")
    iterations: int = Field(10, description="relaxation passes, at most")
    tol: float = Field(1e-3, description="stop when no probability changes by more than this")
    min_prob: float = Field(0.5, description="smallest final probability of the chosen candidate")
    # the relaxation may raise a candidate between min_ncc and this on its neighbours' support,
    # not keep it (1024 px synthetic scenes, 3 seeds: 0.6 keeps 2-3 % more matches, 85-87 % of
    # them within 1 px of the truth instead of 87-89 %)
    accept_ncc: float = Field(0.7, description="smallest NCC of a chosen candidate")
    max_window: int = Field(2048, description="longest side of a per-tile search window read in another image, "
                            "pixels; wider windows are read point by point")

    _odd = field_validator("template", "forstner_window")(_odd_side)


class TrackParams(StrictModel):
    """``orient.tracks`` — tie-point matching
    (:func:`tiledsm.orient.tracks.tie_point_tracks`; its tile side and
    extractor are ``orient.tile`` and ``orient.extractor``). The fields
    ``features_per_tile`` to ``min_std`` are the ``features`` extractor's
    (corners, NCC along the predicted segment); ``structural`` the
    structural extractor's."""

    features_per_tile: int = Field(150, ge=1, description="corner features per tile, at most (features)")
    min_distance: int = Field(15, ge=1, description="minimum distance between features, pixels (features)")
    quality: float = Field(0.01, gt=0, description="goodFeaturesToTrack quality level (features)")
    template: int = Field(15, description="NCC template side, pixels (odd; features)")
    margin_px: float = Field(4.0, ge=0, description="search margin around the predicted segment, pixels (features)")
    min_ncc: float = Field(0.8, description="smallest NCC peak accepted (features)")
    min_std: float = Field(2.0, description="smallest template standard deviation, grey levels: flat templates "
                           "are skipped (features)")
    coarse_size: int = Field(1000, ge=16, description="longest side of the overviews matched for the coarse guide, "
                             "pixels")
    height_margin_m: float = Field(15.0, ge=0, description="added on both sides of the guide's height range, metres")
    max_window: int = Field(2048, ge=1, description="longest side of a per-tile search window read in another "
                            "image, pixels; wider windows (a huge height range) are read point by point")
    p2l: P2LParams = Field(P2LParams(), description="mismatch rejection")
    structural: StructuralParams = Field(StructuralParams(), description="the structural extractor")

    _odd = field_validator("template")(_odd_side)


class AdjustParams(StrictModel):
    """``orient.adjust`` — weights and robustness of the block adjustment
    (:func:`tiledsm.orient.adjust.adjust_block`)."""

    dem_sigma_m: float = Field(3.0, gt=0, description="standard deviation of a tie-point height against the "
                               "reference DEM on flat ground, metres (SRTM: a few metres)")
    dem_robust_sigma: bool = Field(True, description="re-estimate the DEM residuals' scatter s0 after every solve "
                                   "(1.4826 x MAD, at least dem_min_sigma_m) and reject with it; false: with "
                                   "dem_sigma_m")
    dem_min_sigma_m: float = Field(0.1, gt=0, description="floor of the re-estimated s0, metres")
    dem_offset_sigma_m: float = Field(5.0, gt=0, description="prior standard deviation of the DEM's overall "
                                      "vertical offset, metres (its absolute accuracy: SRTM about 5 m)")
    # weak priors: they fix the datum of a block with nothing absolute in it
    prior_shift_px: float = Field(100.0, gt=0, description="prior standard deviation of A0/B0 around 0, pixels")
    prior_linear: float = Field(1e-3, gt=0, description="prior standard deviation of the linear terms around 0")
    loss: Literal["linear", "soft_l1", "huber", "cauchy", "arctan"] = Field(
        "soft_l1", description="scipy.optimize.least_squares loss")
    f_scale: float = Field(3.0, gt=0, description="residual where the robust loss bends, standard deviations")
    reject_k: float = Field(5.0, gt=0, description="an image measurement is rejected beyond max(min_reject_px, "
                            "reject_k x the median residual)")
    min_reject_px: float = Field(1.0, ge=0, description="smallest rejection threshold, pixels")
    dem_reject_k: float = Field(2.5, gt=0, description="a DEM height observation is dropped when its residual, "
                                "less the median, exceeds dem_reject_k x s0 (buildings, trees, DEM voids)")
    max_rounds: int = Field(6, ge=1, description="solve / reject rounds, at most")


class OrientSpec(StrictModel):
    """``orient:`` — bias-compensated orientation of images
    (:mod:`tiledsm.orient`): the section of a ``dsm`` (or ``deformation``)
    recipe that orients its images first, and the parameters of
    ``pipeline: orient`` (``tiledsm orient``, whose options the fields name)."""

    gcps: Optional[str] = Field(None, description="GCP file: CSV id,image,lon,lat,h,row,col or GeoJSON points",
                                json_schema_extra=option("--gcps"))
    check_points: Optional[str] = Field(None, description="check points (same formats), left out of the fit",
                                        json_schema_extra=option("--check-points"))
    dem: Optional[str] = Field(None, description="reference DEM (e.g. SRTM) constraining tie-point heights",
                               json_schema_extra=option("--dem"))
    geoid: Optional[str] = Field(None, description="geoid grid (.gtx) the DEM's heights refer to (SRTM: EGM96)",
                                 json_schema_extra=option("--geoid"))
    model: Optional[Literal["shift", "affine"]] = Field(
        None, description="bias model of every image; left out: chosen per image by point count",
        json_schema_extra=option("--model"))
    # the keys of tiledsm.orient.tracks.EXTRACTORS (a test keeps them equal)
    extractor: Literal["structural", "features"] = Field(
        "structural", description="tie-point matcher: structural (Wallis, Förstner, relaxation) or features",
        json_schema_extra=option("--extractor"))
    tie_points: bool = Field(True, description="match tie points (false: adjust on GCPs only)",
                             json_schema_extra=option("--no-tie-points"))
    # the keys of tiledsm.orient.datum.DATUMS (a test keeps them equal)
    datum: Literal["consensus", "mean", "priors"] = Field(
        "consensus", description="without GCPs or DEM, how the block is held (tiledsm.orient.datum)",
        json_schema_extra=option("--datum"))
    tile: int = Field(512, ge=64, description="tie-point tile side, pixels", json_schema_extra=option("--tile"))
    tie_sigma_px: float = Field(0.3, gt=0, description="standard deviation of a tie-point image measurement, pixels")
    gcp_sigma_px: float = Field(0.3, gt=0, description="standard deviation of a GCP image measurement, pixels")
    gcp_sigma_m: float = Field(0.1, gt=0, description="standard deviation of GCP ground coordinates, metres")
    refit_max_error_px: float = Field(0.01, gt=0, description="tolerance of the corrected RPC's refit (affine "
                                      "models), pixels")
    tracks: TrackParams = Field(TrackParams(), description="tie-point matching (advanced, recipe only)")
    adjust: AdjustParams = Field(AdjustParams(), description="the block adjustment's weights and robustness "
                                 "(advanced, recipe only)")

    @model_validator(mode="after")
    def _geoid_needs_dem(self):
        if self.geoid is not None and self.dem is None:
            raise ValueError("'geoid' is the reference DEM's datum: give 'dem' too")
        return self
