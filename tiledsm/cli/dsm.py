"""``tiledsm dsm IMG1 IMG2 [IMG3 ...] --out DIR``: the DSM stage on its own."""

from __future__ import annotations

import argparse
from pathlib import Path

from tiledsm.cli.run import add_cluster_arguments, add_overwrite_argument, add_plan_arguments, cluster_config

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
    p.add_argument("--chunk", type=int, default=None,
                   help="chunk side, cells (default 512, or smaller when a worker's memory needs it)")
    p.add_argument("--levels", type=int, default=None, help="pyramid levels (default: from the height range)")
    p.add_argument("--height-range", type=float, nargs=2, default=None, metavar=("HMIN", "HMAX"), help="ellipsoidal metres; default: from tie points")
    p.add_argument("--reference", default=None, help="reference DSM for metrics (same vertical datum as the output)")
    p.add_argument("--device", default="cpu",
                   help="where matching runs: cpu (the compiled kernel, default) or a CUDA GPU, cuda or cuda:N "
                        "(the same matching as compiled CUDA kernels on that GPU, the same heights); several: "
                        "cuda:0,1 or cuda:all (each worker thread keeps one GPU, in turn)")
    p.add_argument("--geoid", default=None, help="geoid grid (e.g. egm96_15.gtx): write heights above the geoid instead of the WGS84 ellipsoid")
    add_cluster_arguments(p, default_scheduler="threads")
    add_overwrite_argument(p)
    add_plan_arguments(p)
    p.set_defaults(func=run)


def dsm_recipe(args: argparse.Namespace):
    """The ``pipeline: dsm`` recipe of the command's options, every path
    absolute; a bad value is an :class:`~tiledsm.errors.InvalidOptionError`
    naming the option."""
    from tiledsm.cli.run import absolute_path, recipe_of_options
    from tiledsm.errors import InvalidOptionError
    from tiledsm.workflows.dsm import DSMRecipe

    if len(args.images) < 2:
        raise InvalidOptionError(f"IMAGES: at least two images are needed, got {len(args.images)}")
    grid = dict(like=absolute_path(args.like), crs=args.crs, resolution=args.resolution, bounds=args.bounds, chunk=args.chunk)
    return recipe_of_options(DSMRecipe, {
        "pipeline": "dsm",
        "name": Path(args.out).name,
        "input": {"images": [absolute_path(p) for p in args.images], "reference": absolute_path(args.reference)},
        "grid": {k: v for k, v in grid.items() if v is not None},
        "match": {"levels": args.levels, "height_range": args.height_range,
                  "params": {} if args.device == "cpu" else {"kernel": "cuda", "device": args.device}},
        "output": {"geoid": absolute_path(args.geoid)},
    })


def run(args: argparse.Namespace) -> int:
    from tiledsm.cli.run import plan_and_run
    from tiledsm.plan import FieldNames
    from tiledsm.recipes import options_of
    from tiledsm.workflows.dsm import DSMRecipe

    # the matching kernels are nogil numba, reads are GDAL: threads of this process beat a local cluster of
    # processes, which pays for starting workers and for moving images and level stores between them (s2p_pair
    # on its grid, 2 workers: 9.2 s instead of 12.9 s; benchmarks/dsm.py --schedulers threads cluster)
    cluster = cluster_config(args)
    return plan_and_run(dsm_recipe(args), args, cluster, FieldNames.of_options(options_of(DSMRecipe)))
