"""``tiledsm ortho IMG --dsm DSM.tif --out DIR``: the orthoimage of one image."""

from __future__ import annotations

import argparse
from pathlib import Path

from tiledsm.cli.run import add_cluster_arguments, add_overwrite_argument, add_plan_arguments

__all__ = ["add_parser"]


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "ortho",
        help="orthoimage of an image (RPC or frame camera) on a DSM, occlusion-aware",
        description="Resample the image onto the DSM's ground grid (or a grid --resolution metres, dividing the "
        "DSM's cells) chunk by chunk, with cells hidden from the view set to NaN; write ortho.zarr, ortho.tif "
        "(COG), ortho.png, ortho.json, metrics.json, recipe.resolved.yaml and run.log into --out. A rerun "
        "resumes the chunks an interrupted run finished. The DSM must use the camera's height datum (RPC: "
        "WGS84 ellipsoidal).",
    )
    p.add_argument("image", help="image with an RPC (tags or sidecar), or a frame image listed in --camera")
    p.add_argument("--dsm", required=True, help="DSM: GeoTIFF/COG or a tiledsm dsm.zarr store (then an image it was made from keeps the RPC it was matched with)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--kernel", default="bl", help="interpolation kernel: nn, bl, cr (cubic a=-1), cs (cubic a=-0.5)")
    p.add_argument("--resolution", type=float, default=None, help="cell size, metres (DSM cell / integer; default: the DSM's)")
    p.add_argument("--chunk", type=int, default=512, help="chunk side, ortho cells")
    p.add_argument("--camera", default=None, help="frame cameras: YAML block file listing the image (tiledsm.ortho.cameras)")
    p.add_argument("--bounds", type=float, nargs=4, default=None, metavar=("XMIN", "YMIN", "XMAX", "YMAX"),
                   help="restrict to this box (DSM CRS)")
    p.add_argument("--crs", default=None, help="expected CRS (must be the DSM's)")
    p.add_argument("--no-occlusion", action="store_true", help="do not mask cells hidden from the view")
    p.add_argument("--occlusion-tolerance", type=float, default=None, help="metres (default: one DSM cell)")
    add_cluster_arguments(p)
    add_overwrite_argument(p)
    add_plan_arguments(p, large=False)
    p.set_defaults(func=run)


def ortho_recipe(args: argparse.Namespace):
    """The ``pipeline: ortho`` recipe of the command's options, every path
    absolute; a bad value is an :class:`~tiledsm.errors.InvalidOptionError`
    naming the option."""
    from tiledsm.cli.run import absolute_path, recipe_of_options
    from tiledsm.ortho.recipe import OrthoRecipe

    grid = dict(resolution=args.resolution, bounds=args.bounds, crs=args.crs, chunk=args.chunk)
    return recipe_of_options(OrthoRecipe, {
        "pipeline": "ortho",
        "name": Path(args.out).name,
        "input": {"image": absolute_path(args.image), "dsm": absolute_path(args.dsm),
                  "camera": absolute_path(args.camera)},
        "grid": {k: v for k, v in grid.items() if v is not None},
        "ortho": {"kernel": args.kernel, "occlusion": not args.no_occlusion,
                  "occlusion_tolerance": args.occlusion_tolerance},
    })


def run(args: argparse.Namespace) -> int:
    import dataclasses

    from tiledsm.cli.run import cluster_config, plan_and_run
    from tiledsm.plan import RECIPE_NAMES

    # the stage's plan names its fields by their options itself (tiledsm.plan.core.spelling); these are the cluster's
    names = dataclasses.replace(RECIPE_NAMES, workers="--workers", scheduler="--scheduler")
    return plan_and_run(ortho_recipe(args), args, cluster_config(args), names, summary=print_report)


def print_report(metrics: dict) -> None:
    """The run's summary: the ortho's size, cell and valid share."""
    print(f"{metrics['out']}/ortho.tif: {metrics['shape'][0]} x {metrics['shape'][1]} cells of "
          f"{metrics['resolution_m']:g} m, {metrics['valid_share']:.0%} valid ({metrics['attrs']['kernel']})")
