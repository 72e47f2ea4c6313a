"""``tiledsm orient IMG... [--gcps F] [--check-points F] [--dem DEM [--geoid G]] --out DIR``:
bias-compensated RPC block adjustment on its own."""

from __future__ import annotations

import argparse
from pathlib import Path

from tiledsm.cli.run import add_cluster_arguments, add_overwrite_argument, add_plan_arguments

__all__ = ["add_parser"]


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "orient",
        help="bias-corrected RPCs from tie points, GCPs and a reference DEM (block adjustment)",
        description="Match multi-view tie points, adjust the RPCs' image-space bias (shift or affine A0..B2) "
        "against GCPs and/or a reference DEM, and write into --out, per image, <stem>_RPC.TXT and <stem>.tif "
        "(a copy carrying the corrected RPC tags, usable by 'tiledsm dsm'), plus orient.json, residuals.csv, "
        "residuals.png, metrics.json, recipe.resolved.yaml and run.log.",
    )
    p.add_argument("images", nargs="+", help="images with RPCs (tags or sidecars); the first is the tie-point reference")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--gcps", default=None, help="GCP file: CSV id,image,lon,lat,h,row,col or GeoJSON points")
    p.add_argument("--check-points", default=None, help="check points (same format), left out of the fit")
    p.add_argument("--dem", default=None, help="reference DEM constraining tie-point heights (e.g. SRTM)")
    p.add_argument("--geoid", default=None, help="geoid grid of the DEM's heights (e.g. egm96_15.gtx); "
                   "default: the DEM is WGS84-ellipsoidal")
    p.add_argument("--model", choices=("shift", "affine"), default=None,
                   help="bias model of every image (default: per image by point count)")
    p.add_argument("--no-tie-points", action="store_true", help="adjust on GCPs only")
    p.add_argument("--datum", choices=("consensus", "mean", "priors"), default="consensus",
                   help="without GCPs or DEM, how the block is held: consensus (default: the views that agree keep "
                   "their RPCs, one that disagrees takes the correction), mean (the views' mean correction at zero) "
                   "or priors (least squares of all terms)")
    p.add_argument("--tile", type=int, default=512, help="tie-point tile side, pixels")
    p.add_argument("--extractor", choices=("structural", "features"), default="structural",
                   help="tie-point matcher: structural (Wallis, Förstner points, NCC along the RPC curve, "
                   "probability relaxation) or features (corners, NCC)")
    add_cluster_arguments(p)
    add_overwrite_argument(p)
    add_plan_arguments(p, large=False)
    p.set_defaults(func=run)


def orient_recipe(args: argparse.Namespace):
    """The ``pipeline: orient`` recipe of the command's options, every path
    absolute; a bad value is an :class:`~tiledsm.errors.InvalidOptionError`
    naming the option."""
    from tiledsm.cli.run import absolute_path, recipe_of_options
    from tiledsm.orient.recipe import OrientRecipe

    return recipe_of_options(OrientRecipe, {
        "pipeline": "orient",
        "name": Path(args.out).name,
        "images": [absolute_path(p) for p in args.images],
        "orient": {"gcps": absolute_path(args.gcps), "check_points": absolute_path(args.check_points),
                   "dem": absolute_path(args.dem), "geoid": absolute_path(args.geoid), "model": args.model,
                   "tie_points": not args.no_tie_points, "datum": args.datum, "tile": args.tile,
                   "extractor": args.extractor},
    })


def run(args: argparse.Namespace) -> int:
    import dataclasses

    from tiledsm.cli.run import cluster_config, plan_and_run
    from tiledsm.plan import RECIPE_NAMES

    # the stage's plan names its fields by their options itself (tiledsm.plan.core.spelling); these are the cluster's
    names = dataclasses.replace(RECIPE_NAMES, workers="--workers", scheduler="--scheduler")
    return plan_and_run(orient_recipe(args), args, cluster_config(args), names, summary=_print_table)


def _fmt(v) -> str:
    return "-" if v is None else f"{v:.3f}"


def _print_table(doc: dict) -> None:
    print(f"{'image':<28} {'model':<7} {'A0':>8} {'B0':>8} {'GCP px before/after':>22} {'check px before/after':>24}")
    for d in doc["images"]:
        t = d["terms"]
        print(f"{Path(d['image']).name:<28} {d['model']:<7} {t['A0']:>8.3f} {t['B0']:>8.3f} "
              f"{_fmt(d['gcp_rms_px']['before']):>10} / {_fmt(d['gcp_rms_px']['after']):<9} "
              f"{_fmt(d['check_rms_px']['before']):>11} / {_fmt(d['check_rms_px']['after']):<9}")
    tie = doc["tie_relative_rms_px"]
    print(f"tie points: {doc['n_tracks']} tracks, relative RMS {_fmt(tie['before'])} -> {_fmt(tie['after'])} px; "
          f"rejected measurements: {doc['n_rejected']}"
          + (f"; rejected GCPs: {', '.join(doc['rejected_gcps'])}" if doc["rejected_gcps"] else ""))
    print(f"datum: {doc['datum']['fixed_by']}")
