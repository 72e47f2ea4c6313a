"""``tiledsm compare REF OTHER --out DIR``: co-register and difference two DSMs."""

from __future__ import annotations

import argparse
from pathlib import Path

from tiledsm.cli.run import add_cluster_arguments, add_overwrite_argument, add_plan_arguments, cluster_config

__all__ = ["add_parser", "compare_recipe", "run"]


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "compare",
        help="co-register two DSMs (Nuth & Kääb), difference them, write statistics and a report",
        description="Compare OTHER (e.g. post-event) with REF (pre-event): bring OTHER onto REF's grid, "
        "fit a horizontal shift and vertical bias on stable terrain, write dh.zarr, dh.tif, quick-looks, "
        "report.html, metrics.json, recipe.resolved.yaml and run.log into --out. dh = OTHER_corrected - REF (metres).",
    )
    p.add_argument("ref", help="reference DSM (GeoTIFF or zarr)")
    p.add_argument("other", help="DSM to compare (GeoTIFF or zarr); any CRS/resolution")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--stable-mask", default=None, help="GeoJSON polygons to EXCLUDE from stable terrain (e.g. rupture zone)")
    p.add_argument("--coreg", default="nuth_kaab", help="co-registration method: nuth_kaab (default) or none")
    p.add_argument("--deramp", action="store_true", help="also remove a plane fitted on stable terrain")
    p.add_argument("--max-slope", type=float, default=70.0, help="steeper cells (degrees) are not stable terrain")
    p.add_argument("--nmad-k", type=float, default=5.0, help="outliers: |dh - median| > K x NMAD")
    p.add_argument("--chunks", type=int, default=1024, help="tile edge in cells")
    add_cluster_arguments(p, default_scheduler="threads")
    add_overwrite_argument(p)
    add_plan_arguments(p, large=False)
    p.set_defaults(func=run)


def compare_recipe(args: argparse.Namespace):
    """The ``pipeline: compare`` recipe of the command's options, every
    path absolute; a bad value is an :class:`~tiledsm.errors.InvalidOptionError`
    naming the option."""
    from tiledsm.cli.run import absolute_path, recipe_of_options
    from tiledsm.compare.recipe import CompareRecipe

    return recipe_of_options(CompareRecipe, {
        "pipeline": "compare",
        "name": Path(args.out).name,
        "input": {"ref": absolute_path(args.ref), "other": absolute_path(args.other)},
        "compare": {"coreg": args.coreg, "deramp": args.deramp, "stable_mask": absolute_path(args.stable_mask),
                    "max_slope_deg": args.max_slope, "nmad_k": args.nmad_k, "chunk": args.chunks},
    })


def print_compare_summary(metrics: dict) -> None:
    """The shift, the vertical bias and the stable terrain's statistics, as JSON on stdout."""
    import json

    c = metrics["coregistration"]
    s = metrics["statistics"]["stable"]
    print(json.dumps({
        "coregistration": {k: c[k] for k in ("dx", "dy", "dz", "dx_px", "dy_px", "dx_m", "dy_m")},
        "stable": {k: s[k] for k in ("count", "median", "nmad", "rmse")},
    }, indent=2))


def run(args: argparse.Namespace) -> int:
    from tiledsm.cli.run import plan_and_run
    from tiledsm.plan import FieldNames
    from tiledsm.recipes import options_of
    from tiledsm.compare.recipe import CompareRecipe

    # compare's kernels release the GIL (numpy, numba nogil, GDAL): threads of this process beat a local cluster
    # of processes, which pays for starting workers and for moving blocks between them (benchmarks/compare.py
    # --schedulers cluster threads); a --cluster file (kind: local) keeps processes
    cluster = cluster_config(args)
    return plan_and_run(compare_recipe(args), args, cluster, FieldNames.of_options(options_of(CompareRecipe)), summary=print_compare_summary)
