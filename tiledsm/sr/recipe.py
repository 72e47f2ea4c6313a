"""``pipeline: sr`` (and ``tiledsm sr IMAGE OUT``): the recipe of
super-resolving one image with its camera, one spec that is its parameters.

Each field names the command option that sets it
(:func:`tiledsm.recipes.option`), so that a bad value is reported under
the option (command) or the field path (recipe file). The run folder
receives ``sr.tif`` (GeoTIFF with the RPC scaled, ``output.format: tif``)
or ``sr.zarr``, beside ``metrics.json``, ``recipe.resolved.yaml`` and
``run.log``.
"""

from __future__ import annotations

from typing import Literal, Optional, Union

from pydantic import Field, field_validator

from tiledsm.recipes import ClusterSpec, StrictModel, option

__all__ = ["SRInput", "SRSpec", "SROutput", "SRRecipe", "product_name"]


class SRInput(StrictModel):
    image: str = Field(..., description="image with an RPC (tags or sidecar)", json_schema_extra=option("IMAGE"))


class SRSpec(StrictModel):
    """The network and how the image is fed to it (see :func:`tiledsm.sr.infer.super_resolve`)."""

    model: str = Field("srmd_official", description="SR network of the registry (tiledsm.sr.registry.MODELS)",
                       json_schema_extra=option("--model"))
    scale: int = Field(2, ge=2, description="upscaling factor", json_schema_extra=option("--scale"))
    weights: Optional[str] = Field(None, description="weights file (default: the shipped weights of model at scale)",
                                   json_schema_extra=option("--weights"))
    blur_sigma: Optional[Union[float, Literal["bicubic"]]] = Field(
        None, description="SRMD: Gaussian blur sigma of the LR image, HR pixels, or 'bicubic'",
        json_schema_extra=option("--blur-sigma"))
    noise: Optional[float] = Field(None, ge=0, description="SRMD: noise standard deviation, digital numbers",
                                   json_schema_extra=option("--noise"))
    bit_depth: Optional[int] = Field(None, ge=1, le=32, description="sensor bit depth (default: from the data)",
                                     json_schema_extra=option("--bit-depth"))
    normalisation: Literal["stretch", "full_scale"] = Field(
        "stretch", description="value mapped to 1: the 99.9th percentile, or 2**bit_depth - 1",
        json_schema_extra=option("--normalisation"))
    chunk: int = Field(512, ge=16, description="tile side, input pixels", json_schema_extra=option("--chunk"))
    device: Literal["cpu", "cuda"] = Field("cpu", description="torch device", json_schema_extra=option("--device"))

    @field_validator("model")
    @classmethod
    def _registered(cls, value: str) -> str:
        from tiledsm.sr.registry import MODELS  # imports torch: only when an sr recipe is validated

        if value not in MODELS:
            raise ValueError(f"unknown model {value!r}; known: {', '.join(MODELS.names())}")
        return value


class SROutput(StrictModel):
    format: Literal["tif", "zarr"] = Field("tif", description="sr.tif (GeoTIFF + RPC tags) or sr.zarr",
                                           json_schema_extra=option("--format"))


class SRRecipe(StrictModel):
    """``pipeline: sr``: one image super-resolved, its RPC regenerated."""

    pipeline: Literal["sr"]
    name: str = "sr"
    input: SRInput
    sr: SRSpec = SRSpec()
    output: SROutput = SROutput()
    cluster: ClusterSpec = ClusterSpec()


def product_name(recipe: SRRecipe) -> str:
    """The product's name in the run folder: ``sr.tif`` or ``sr.zarr``."""
    return f"sr.{recipe.output.format}"
