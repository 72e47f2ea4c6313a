"""``pipeline: compare`` (and ``tiledsm compare REF OTHER``): the recipe of
a DSM comparison, whose sections are the parameters of the stage.

:class:`CompareSpec` (``compare:``, the fit's parameters nested in it as
:class:`~tiledsm.compare.coreg.CoregFitSpec`, ``compare.coreg_fit:``) is
what :func:`tiledsm.compare.compare_dsms` and
:func:`tiledsm.compare.fit_coregistration` take, and :class:`CompareOutput`
(``output:``) says which products it writes: one type each, filled by the
command's options, a recipe file or Python. Each field with an option
names it (:func:`tiledsm.recipes.option`), so that a bad value is reported
under the option (command) or the field path (recipe file); the advanced
fields are recipe-only.
"""

from __future__ import annotations

from typing import Literal, Optional

from pydantic import Field, field_validator

from tiledsm.compare.coreg import CoregFitSpec
from tiledsm.compare.stats import SLOPE_CLASSES
from tiledsm.recipes import ClusterSpec, StrictModel, option

__all__ = ["CompareInput", "CompareSpec", "CompareOutput", "CompareRecipe"]


class CompareInput(StrictModel):
    """The two DSMs: GeoTIFF/COG or zarr, any CRS (geographic included) and cell size."""

    ref: str = Field(..., description="reference DSM (e.g. pre-event); the comparison runs on its grid",
                     json_schema_extra=option("REF"))
    other: str = Field(..., description="DSM to compare (e.g. post-event), brought onto REF's grid",
                       json_schema_extra=option("OTHER"))


class CompareSpec(StrictModel):
    """Co-registration and statistics: the parameters of
    :func:`tiledsm.compare.compare_dsms`."""

    coreg: str = Field("nuth_kaab", description="co-registration method: nuth_kaab or none",
                       json_schema_extra=option("--coreg"))
    deramp: bool = Field(False, description="also remove a plane fitted on stable terrain",
                         json_schema_extra=option("--deramp"))
    stable_mask: Optional[str] = Field(None, description="GeoJSON polygons EXCLUDED from stable terrain",
                                       json_schema_extra=option("--stable-mask"))
    max_slope_deg: float = Field(70.0, gt=0, le=90, description="steeper cells (degrees) are not stable terrain "
                                 "in the statistics (the fit's samples: coreg_fit.max_slope_deg)",
                                 json_schema_extra=option("--max-slope"))
    nmad_k: float = Field(5.0, gt=0, description="outliers: |dh - median| > nmad_k x NMAD",
                          json_schema_extra=option("--nmad-k"))
    chunk: int = Field(1024, ge=16, description="chunk side of the comparison grid, cells",
                       json_schema_extra=option("--chunks"))
    coreg_fit: CoregFitSpec = CoregFitSpec()
    resampling: str = Field("bilinear", description="resampling of OTHER onto REF's grid when they differ "
                            "(a rasterio Resampling name)")
    slope_classes: tuple[float, ...] = Field(
        SLOPE_CLASSES, min_length=1, description="lower bounds of the slope classes of the statistics, percent, "
        "increasing from 0")
    max_fit_pixels: int = Field(
        4_000_000, ge=1, description="at most this many cells are loaded for the fit, cells; a larger grid is "
        "sampled with fit_window-sized windows on a regular lattice")
    fit_window: int = Field(512, ge=3, description="edge of those windows, cells")
    hist_bins: int = Field(65536, ge=16, description="bins of the histogram giving the median and NMAD")

    @field_validator("coreg")
    @classmethod
    def _known_method(cls, value: str) -> str:
        from tiledsm.compare.coreg import COREG_METHODS

        if value not in COREG_METHODS:
            raise ValueError(f"unknown co-registration method {value!r}; known: {', '.join(sorted(COREG_METHODS))}")
        return value

    @field_validator("resampling")
    @classmethod
    def _known_resampling(cls, value: str) -> str:
        from rasterio.enums import Resampling

        if value not in Resampling.__members__:
            raise ValueError(f"unknown resampling {value!r}; one of {', '.join(Resampling.__members__)}")
        return value

    @field_validator("slope_classes")
    @classmethod
    def _increasing_from_zero(cls, value: tuple[float, ...]) -> tuple[float, ...]:
        if list(value) != sorted(value) or value[0] != 0:
            raise ValueError(f"{list(value)} must be increasing from 0")
        return value


class CompareOutput(StrictModel):
    """The products :func:`tiledsm.compare.compare_dsms` writes besides ``dh.zarr`` and ``metrics.json``."""

    cog: bool = Field(True, description="write dh.tif (Cloud-Optimised GeoTIFF)")
    quicklook: bool = Field(True, description="write the PNG figures")
    report: bool = Field(True, description="write report.html")
    # the dh map is drawn 880 px wide (8 in at 110 dpi): a finer array adds memory, not detail
    # (drawing a 1366 px array of a 4096² grid raised the client's peak by 0.2 GiB)
    quicklook_size: int = Field(1024, ge=16, description="longest edge of the decimated arrays the figures draw, "
                                "pixels (as the DSM's quick-look)")


class CompareRecipe(StrictModel):
    """``pipeline: compare``: two DSMs co-registered and differenced."""

    pipeline: Literal["compare"]
    name: str = "compare"
    input: CompareInput
    compare: CompareSpec = CompareSpec()
    output: CompareOutput = CompareOutput()
    cluster: ClusterSpec = ClusterSpec()
