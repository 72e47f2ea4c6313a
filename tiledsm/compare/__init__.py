"""Pre/post DSM comparison: common grid, co-registration, dh, statistics, report.

Public surface::

    from tiledsm.compare import CompareSpec, compare_dsms
    result = compare_dsms("pre.tif", "post.tif", "out/", CompareSpec(stable_mask="rupture.geojson"))
    result.coregistration.dx_px, result.metrics["statistics"]["stable"]["nmad"]

The parameters are the recipe's sections (:mod:`~tiledsm.compare.recipe`):
:class:`CompareSpec` (``compare:``, its fit in :class:`CoregFitSpec`,
``compare.coreg_fit:``) and :class:`CompareOutput` (``output:``).

Modules: :mod:`~tiledsm.compare.align` (common grid), :mod:`~tiledsm.compare.coreg`
(Nuth & Kääb, registry), :mod:`~tiledsm.compare.recipe` (parameters), :mod:`~tiledsm.compare.stable` (stable terrain),
:mod:`~tiledsm.compare.stats`, :mod:`~tiledsm.compare.terrain`,
:mod:`~tiledsm.compare.report`, :mod:`~tiledsm.compare.stage`.
"""

from tiledsm.compare.align import AlignedPair, align_dsms, open_dsm
from tiledsm.compare.coreg import (
    COREG_METHODS,
    CoregistrationError,
    Coregistration,
    CoregFitSpec,
    NoStableTerrainError,
    register_coreg,
)
from tiledsm.compare.recipe import CompareOutput, CompareSpec
from tiledsm.compare.stage import CompareResult, compare_dsms, difference_lazy, fit_coregistration
from tiledsm.compare.stats import difference_statistics

__all__ = [
    "AlignedPair",
    "align_dsms",
    "open_dsm",
    "COREG_METHODS",
    "CoregistrationError",
    "Coregistration",
    "CoregFitSpec",
    "NoStableTerrainError",
    "register_coreg",
    "CompareSpec",
    "CompareOutput",
    "CompareResult",
    "compare_dsms",
    "difference_lazy",
    "fit_coregistration",
    "difference_statistics",
]
