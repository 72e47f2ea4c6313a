"""``pipeline: orient`` (and ``tiledsm orient IMG...``): images to
bias-corrected RPCs; the parameters are the ``orient:`` section every
recipe shares (:class:`tiledsm.orient.spec.OrientSpec`).

Example::

    pipeline: orient
    images: [left.tif, right.tif]
    orient:
      gcps: gcps.csv
      dem: N44E005.hgt
      geoid: egm96_15.gtx
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from tiledsm.orient.spec import OrientSpec
from tiledsm.recipes import ClusterSpec, StrictModel, option

__all__ = ["OrientRecipe"]


class OrientRecipe(StrictModel):
    """``pipeline: orient`` — images to bias-corrected RPCs: per image
    ``<stem>_RPC.TXT`` and ``<stem>.tif``, with ``orient.json``,
    ``residuals.csv``, ``residuals.png`` and ``metrics.json``."""

    pipeline: Literal["orient"]
    name: str = "orient"
    images: list[str] = Field(..., min_length=1, description="images with RPCs (tags or sidecars); the first is the "
                              "tie-point reference", json_schema_extra=option("IMAGES"))
    # the section's own check (a geoid needs a DEM) is --geoid's
    orient: OrientSpec = Field(OrientSpec(), json_schema_extra=option("--geoid"))
    cluster: ClusterSpec = ClusterSpec()
