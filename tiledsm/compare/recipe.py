"""``pipeline: compare`` (and ``tiledsm compare REF OTHER``): the recipe of
a DSM comparison, whose sections are the parameters of the stage.

:class:`CompareSpec` (``compare:``, with its nested :class:`CoregFitSpec`,
``compare.coreg_fit:``) is what :func:`tiledsm.compare.compare_dsms` and
:func:`tiledsm.compare.fit_coregistration` take, and :class:`CompareOutput`
(``output:``) which products it writes: one type each, filled by the
command's options, a recipe file or Python. Each field with an option
names it (:func:`tiledsm.recipes.option`), so that a bad value is reported
under the option (command) or the field path (recipe file); the advanced
fields are recipe-only.
"""

from __future__ import annotations

from typing import Literal, Optional

from pydantic import Field, field_validator, model_validator

from tiledsm.compare.stats import SLOPE_CLASSES
from tiledsm.recipes import ClusterSpec, StrictModel, option

__all__ = ["CompareInput", "CoregFitSpec", "CompareSpec", "CompareOutput", "CompareRecipe"]


class CompareInput(StrictModel):
    """The two DSMs: GeoTIFF/COG or zarr, any CRS (geographic included) and cell size."""

    ref: str = Field(..., description="reference DSM (e.g. pre-event); the comparison runs on its grid",
                     json_schema_extra=option("REF"))
    other: str = Field(..., description="DSM to compare (e.g. post-event), brought onto REF's grid",
                       json_schema_extra=option("OTHER"))


class CoregFitSpec(StrictModel):
    """The co-registration fit (:mod:`tiledsm.compare.coreg`): Nuth & Kääb's
    iterations, the samples they use, the subpixel shift. Its outlier rule
    is ``compare.nmad_k``, its deramp ``compare.deramp``."""

    max_iterations: int = Field(10, ge=1, description="Nuth & Kääb iterations at most")
    tolerance_px: float = Field(0.005, ge=0, description="stop when the shift update is below this, pixels")
    vertical: Literal["median", "mean"] = Field(
        "median", description="statistic of the stable dh (inliers) giving the vertical bias")
    min_slope_deg: float = Field(
        1.0, ge=0, description="flattest reference slope (degrees) of the samples of the horizontal fit: "
        "flat cells carry no shift information")
    max_slope_deg: float = Field(
        70.0, le=90, description="steepest reference slope (degrees) of the samples of the horizontal fit "
        "(the statistics' stable terrain is compare.max_slope_deg)")
    aspect_bins: int = Field(72, ge=3, description="aspect sectors whose median dh / tan(slope) is fitted")
    min_bin_count: int = Field(20, ge=1, description="sectors with fewer samples are ignored")
    shift_kernel: str = Field("cubic", description="subpixel interpolation of the shifted DSM: cubic or linear")
    max_samples: int = Field(
        500_000, ge=0, description="the iterations use at most this many of the candidate cells (stable, slope in "
        "range), an evenly strided subset; 0: all of them (the exact fit). The median, NMAD and vertical bias use "
        "every stable cell")

    @field_validator("shift_kernel")
    @classmethod
    def _known_kernel(cls, value: str) -> str:
        from tiledsm.compare.shift import ShiftKernelError, kernel_taps

        try:
            kernel_taps(0.5, value)
        except ShiftKernelError as exc:
            raise ValueError(str(exc)) from None
        return value

    @model_validator(mode="after")
    def _slope_range(self):
        if not self.min_slope_deg < self.max_slope_deg:
            raise ValueError(f"need min_slope_deg < max_slope_deg, got {self.min_slope_deg} and {self.max_slope_deg}")
        return self


class CompareSpec(StrictModel):
    """Co-registration and statistics: the parameters of
    :func:`tiledsm.compare.compare_dsms`."""

    coreg: str = Field("nuth_kaab", description="co-registration method: nuth_kaab or none",
                       json_schema_extra=option("--coreg"))
    deramp: bool = Field(False, description="also remove a plane fitted on stable terrain",
                         json_schema_extra=option("--deramp"))
    stable_mask: Optional[str] = Field(None, description="GeoJSON polygons EXCLUDED from stable terrain",
                                       json_schema_extra=option("--stable-mask"))
    max_slope_deg: float = Field(70.0, gt=0, le=90, description="steeper cells (degrees) are not stable terrain",
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
    quicklook_size: int = Field(1500, ge=16, description="longest edge of the decimated arrays the figures draw, "
                                "pixels")


class CompareRecipe(StrictModel):
    """``pipeline: compare``: two DSMs co-registered and differenced."""

    pipeline: Literal["compare"]
    name: str = "compare"
    input: CompareInput
    compare: CompareSpec = CompareSpec()
    output: CompareOutput = CompareOutput()
    cluster: ClusterSpec = ClusterSpec()
