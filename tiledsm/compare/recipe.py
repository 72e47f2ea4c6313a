"""``pipeline: compare`` (and ``tiledsm compare REF OTHER``): the recipe of
a DSM comparison, one spec that is its parameters.

Each field names the command option that sets it
(:func:`tiledsm.recipes.option`), so that a bad value is reported under
the option (command) or the field path (recipe file). The core function
:func:`tiledsm.compare.compare_dsms` keeps its frozen
:class:`~tiledsm.compare.CompareParams`; :meth:`CompareRecipe.params` is
the one place that builds it from the spec.
"""

from __future__ import annotations

from typing import Literal, Optional

from pydantic import Field, field_validator

from tiledsm.recipes import ClusterSpec, StrictModel, option

__all__ = ["CompareInput", "CompareSpec", "CompareOutput", "CompareRecipe"]


class CompareInput(StrictModel):
    """The two DSMs: GeoTIFF/COG or zarr, any CRS (geographic included) and cell size."""

    ref: str = Field(..., description="reference DSM (e.g. pre-event); the comparison runs on its grid",
                     json_schema_extra=option("REF"))
    other: str = Field(..., description="DSM to compare (e.g. post-event), brought onto REF's grid",
                       json_schema_extra=option("OTHER"))


class CompareSpec(StrictModel):
    """Co-registration and statistics (see :class:`tiledsm.compare.CompareParams`)."""

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

    @field_validator("coreg")
    @classmethod
    def _known_method(cls, value: str) -> str:
        from tiledsm.compare.coreg import COREG_METHODS

        if value not in COREG_METHODS:
            raise ValueError(f"unknown co-registration method {value!r}; known: {', '.join(sorted(COREG_METHODS))}")
        return value


class CompareOutput(StrictModel):
    cog: bool = Field(True, description="write dh.tif (Cloud-Optimised GeoTIFF)")
    quicklook: bool = Field(True, description="write the PNG figures")
    report: bool = Field(True, description="write report.html")


class CompareRecipe(StrictModel):
    """``pipeline: compare``: two DSMs co-registered and differenced."""

    pipeline: Literal["compare"]
    name: str = "compare"
    input: CompareInput
    compare: CompareSpec = CompareSpec()
    output: CompareOutput = CompareOutput()
    cluster: ClusterSpec = ClusterSpec()

    def params(self):
        """The :class:`~tiledsm.compare.CompareParams` of this recipe (paths as given: absolute)."""
        from tiledsm.compare.coreg import CoregParams
        from tiledsm.compare.stage import CompareParams

        c = self.compare
        return CompareParams(
            coreg=c.coreg, deramp=c.deramp, coreg_params=CoregParams(nmad_k=c.nmad_k), stable_mask=c.stable_mask,
            max_slope_deg=c.max_slope_deg, chunks=c.chunk, cog=self.output.cog, figures=self.output.quicklook,
            report=self.output.report,
        )
