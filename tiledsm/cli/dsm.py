"""``tiledsm dsm IMG1 IMG2 [IMG3 ...] --out DIR``: the DSM stage on its own."""

from __future__ import annotations

import argparse
from pathlib import Path

from tiledsm.cli.run import add_cluster_arguments, add_overwrite_argument, cluster_config

__all__ = ["add_parser"]


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "dsm",
        help="DSM from two or more images with RPCs (object-space semi-global matching)",
        description="Match the images in object space chunk by chunk on a ground grid and write "
        "dsm.zarr, dsm.tif (COG), dsm.png and metrics.json into --out. Heights are WGS84 ellipsoidal.",
    )
    p.add_argument("images", nargs="+", help="two or more images with RPCs (tags or sidecars)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--like", default=None, help="align the output to this raster's grid")
    p.add_argument("--crs", default=None, help="output CRS (default: UTM zone of the scene centre)")
    p.add_argument("--resolution", type=float, default=None, help="cell size, metres (default: GSD)")
    p.add_argument("--bounds", type=float, nargs=4, default=None, metavar=("XMIN", "YMIN", "XMAX", "YMAX"))
    p.add_argument("--chunk", type=int, default=512, help="chunk side, cells")
    p.add_argument("--levels", type=int, default=None, help="pyramid levels (default: from the height range)")
    p.add_argument("--height-range", type=float, nargs=2, default=None, metavar=("HMIN", "HMAX"), help="ellipsoidal metres; default: from tie points")
    p.add_argument("--reference", default=None, help="reference DSM for metrics (same vertical datum as the output)")
    p.add_argument("--geoid", default=None, help="geoid grid (e.g. egm96_15.gtx): write heights above the geoid instead of the WGS84 ellipsoid")
    add_cluster_arguments(p)
    add_overwrite_argument(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from tiledsm.cli.run import _print_summary
    from tiledsm.pipelines import run_recipe
    from tiledsm.recipes import DSMRecipe

    if len(args.images) < 2:
        raise SystemExit("tiledsm dsm: error: at least two images are needed")
    recipe = DSMRecipe.model_validate(
        {
            "pipeline": "dsm",
            "name": Path(args.out).name,
            "input": {"images": [str(Path(p).resolve()) for p in args.images], "reference": args.reference},
            "grid": {
                k: v
                for k, v in dict(like=args.like, crs=args.crs, resolution=args.resolution, bounds=args.bounds, chunk=args.chunk).items()
                if v is not None
            },
            "match": {"levels": args.levels, "height_range": args.height_range},
            "output": {"geoid": str(Path(args.geoid).resolve()) if args.geoid else None},
        }
    )
    metrics = run_recipe(recipe, args.out, cluster_config(args), overwrite=args.overwrite)
    _print_summary(metrics)
    return 0
