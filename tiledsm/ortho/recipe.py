"""``pipeline: ortho`` (and ``tiledsm ortho IMAGE --dsm DSM``): the recipe
of one orthoimage, its parameters named as the command's options.

Example::

    pipeline: ortho
    input:
      image: img_01.tif        # RPC in tags or a sidecar (or a frame image listed in `camera`)
      dsm: dsm.tif             # GeoTIFF/COG or a tiledsm dsm.zarr store
    grid:
      resolution: 0.25         # metres; must divide the DSM's cell (default: the DSM's)
      chunk: 512               # ortho cells per chunk side
    ortho:
      kernel: cs               # nn | bl | cr | cs

:class:`OrthoSpec` (the ``ortho:`` section) is also the parameter type of
:func:`tiledsm.ortho.rectify.orthorectify`: the ortho grid's refinement
(``factor``) is not in it, as it follows from ``grid.resolution`` and the
DSM's cell (:func:`tiledsm.ortho.stage.resolution_factor`).

Relative paths are resolved against the recipe's folder; heights are the
camera's datum (RPC: WGS84 ellipsoidal).
"""

from __future__ import annotations

from typing import Annotated, Literal, Optional

from pydantic import AfterValidator, Field

from tiledsm.ortho.kernels import known_kernel
from tiledsm.recipes import ClusterSpec, StrictModel, option

__all__ = ["KernelName", "OrthoInput", "OrthoGrid", "OrthoSpec", "OrthoRecipe"]

#: a field naming an interpolation kernel of :data:`tiledsm.ortho.kernels.KERNELS`
#: (any case, kept as written); an unknown name is an error at the field
KernelName = Annotated[str, AfterValidator(known_kernel)]


class OrthoInput(StrictModel):
    """The image, its DSM and (frame cameras) the camera file."""

    image: str = Field(..., description="image with an RPC (tags or sidecar), or a frame image listed in 'camera'",
                       json_schema_extra=option("IMAGE"))
    dsm: str = Field(..., description="DSM: GeoTIFF/COG or a tiledsm dsm.zarr store (an image it was made from "
                     "keeps the RPC it was matched with)", json_schema_extra=option("--dsm"))
    camera: Optional[str] = Field(None, description="frame cameras: YAML block file listing the image",
                                  json_schema_extra=option("--camera"))


class OrthoGrid(StrictModel):
    """The ortho grid: the DSM's, refined and cut."""

    resolution: Optional[float] = Field(None, gt=0, description="cell size, metres (DSM cell / integer; default: the DSM's)",
                                        json_schema_extra=option("--resolution"))
    bounds: Optional[tuple[float, float, float, float]] = Field(
        None, description="xmin ymin xmax ymax, DSM CRS: restrict to this box", json_schema_extra=option("--bounds"))
    crs: Optional[str] = Field(None, description="expected CRS (must be the DSM's)", json_schema_extra=option("--crs"))
    chunk: int = Field(512, ge=16, description="chunk side, ortho cells", json_schema_extra=option("--chunk"))


class OrthoSpec(StrictModel):
    """Resampling and occlusion: the parameters of
    :func:`tiledsm.ortho.rectify.orthorectify` (the ``ortho:`` section)."""

    kernel: KernelName = Field("bl", description="interpolation kernel: nn, bl, cr (cubic a=-1), cs (cubic a=-0.5)",
                               json_schema_extra=option("--kernel"))
    occlusion: bool = Field(True, description="set cells hidden from the view to NaN",
                            json_schema_extra=option("--no-occlusion"))
    occlusion_tolerance: Optional[float] = Field(
        None, ge=0, description="metres the DSM must rise above a line of sight to hide its cell (default: one "
        "DSM cell, which absorbs DSM noise on steep slopes)", json_schema_extra=option("--occlusion-tolerance"))
    step: float = Field(0.5, gt=0, description="ray-marching step of the occlusion test, DSM cells")


class OrthoRecipe(StrictModel):
    """``pipeline: ortho`` — one image on a DSM to ``ortho.zarr``,
    ``ortho.tif``, ``ortho.png``, ``ortho.json`` and ``metrics.json``."""

    pipeline: Literal["ortho"]
    name: str = "ortho"
    input: OrthoInput
    grid: OrthoGrid = OrthoGrid()
    ortho: OrthoSpec = OrthoSpec()
    cluster: ClusterSpec = ClusterSpec()
