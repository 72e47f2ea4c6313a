"""``tiledsm displace PRE POST --out DIR``: the displacement field of two orthoimages."""

from __future__ import annotations

import argparse
from pathlib import Path

from tiledsm.cli.run import add_cluster_arguments, add_overwrite_argument, add_plan_arguments, cluster_config

__all__ = ["add_parser", "displace_recipe"]


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "displace",
        help="horizontal displacement (dE, dN) between two orthoimages, with sigma, by sub-pixel correlation",
        description="Correlate POST against PRE (two orthoimages, any projected CRS, cell size or origin: both are "
        "read onto PRE's pixel lattice, or --like/--resolution, POST warped bicubic) and write displacement.zarr, "
        "dE.tif, dN.tif, sigma_dE.tif, sigma_dN.tif, displacement.png, profiles.png (with --fault-trace), "
        "metrics.json, recipe.resolved.yaml and run.log into --out. dE/dN: metres east/north that the ground moved "
        "from PRE to POST; NaN where unknown (status layer says why).",
    )
    p.add_argument("pre", help="pre-event orthoimage (GeoTIFF/COG, or a tiledsm ortho .zarr); with --dsm-pre, an "
                   "image with its camera")
    p.add_argument("post", help="post-event orthoimage (any projected CRS, cell size or origin); with --dsm-post, an "
                   "image with its camera")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--dsm-pre", default=None, help="PRE is an image with its camera (RPC tags or sidecar): "
                   "orthorectify it on this DSM first (GeoTIFF or a tiledsm dsm.zarr)")
    p.add_argument("--dsm-post", default=None, help="POST is an image with its camera: orthorectify it on this DSM first")
    p.add_argument("--kernel", default="cs", help="ortho interpolation kernel with --dsm-pre/--dsm-post: nn, bl, cr, "
                   "cs (default)")
    p.add_argument("--window", type=int, default=32, help="correlation window side, pixels (even; default 32)")
    p.add_argument("--step", type=int, default=8, help="spacing of the displacement cells, pixels (even, <= window; "
                   "default 8)")
    p.add_argument("--search", type=int, default=8,
                   help="search, pixels per axis: around zero, or at the coarsest level of the pyramid that "
                   "--max-displacement asks for (default 8)")
    p.add_argument("--max-displacement", type=float, default=None, metavar="METRES",
                   help="largest displacement expected, metres: beyond --search pixels the correlation runs coarse "
                   "to fine (default: --search pixels)")
    p.add_argument("--refine-search", type=int, default=4,
                   help="with a pyramid, search around each coarse candidate at full resolution, pixels (default 4)")
    p.add_argument("--stable-mask", default=None,
                   help="GeoJSON polygons EXCLUDED from stable terrain (the moving ground): the rest fixes the frame "
                   "(a plane removed per component) and calibrates sigma")
    p.add_argument("--fault-trace", type=float, nargs=4, default=None, metavar=("LON0", "LAT0", "LON1", "LAT1"),
                   help="fault trace, two WGS84 points: offsets (right side minus left, looking from the first "
                   "point) and profiles across it, and where the field's step lies")
    p.add_argument("--stripes", action="store_true", help="also remove along-row stripes (attitude jitter) on stable "
                   "terrain (needs --stable-mask)")
    p.add_argument("--no-plane", action="store_true", help="remove only the median of stable terrain, not a plane")
    p.add_argument("--min-quality", type=float, default=0.5, help="phase coherence under which a cell is NaN")
    p.add_argument("--min-peak", type=float, default=0.15, help="correlation peak under which a cell is NaN")
    p.add_argument("--min-texture", type=float, default=1.0, help="std of the PRE window (DN) under which a cell is NaN")
    p.add_argument("--like", default=None, help="measure on this raster's lattice (CRS, cell size, origin)")
    p.add_argument("--resolution", type=float, default=None, help="cell size, metres, in PRE's CRS and origin")
    p.add_argument("--chunk", type=int, default=1024, help="ortho pixels per chunk side (default 1024)")
    p.add_argument("--no-cog", action="store_true", help="do not write the COGs")
    p.add_argument("--no-quicklook", action="store_true", help="do not draw the PNGs")
    add_cluster_arguments(p, default_scheduler="threads")
    add_overwrite_argument(p)
    add_plan_arguments(p, large=False)
    p.set_defaults(func=run)


def displace_recipe(args: argparse.Namespace):
    """The ``pipeline: displace`` recipe of the command's options, every
    path absolute; a bad value is an :class:`~tiledsm.errors.InvalidOptionError`
    naming the option."""
    from tiledsm.cli.run import absolute_path, recipe_of_options
    from tiledsm.errors import InvalidOptionError
    from tiledsm.workflows.displace import DisplaceRecipe

    if args.stripes and not args.stable_mask:
        raise InvalidOptionError("--stripes: needs --stable-mask (stripes are fitted on stable terrain)")
    ft = args.fault_trace
    displacement = {"window": args.window, "step": args.step, "search": args.search,
                    "max_displacement": args.max_displacement, "refine_search": args.refine_search,
                    "min_quality": args.min_quality, "min_peak": args.min_peak, "min_texture": args.min_texture,
                    "plane": not args.no_plane, "stripes": "rows" if args.stripes else None}
    grid = {"like": absolute_path(args.like), "resolution": args.resolution, "chunk": args.chunk}
    return recipe_of_options(DisplaceRecipe, {
        "pipeline": "displace",
        "name": Path(args.out).name,
        "input": {"pre": absolute_path(args.pre), "post": absolute_path(args.post),
                  "dsm_pre": absolute_path(args.dsm_pre), "dsm_post": absolute_path(args.dsm_post),
                  "kernel": args.kernel},
        "grid": {k: v for k, v in grid.items() if v is not None},
        "displacement": displacement,
        "stable_mask": absolute_path(args.stable_mask),
        "fault_trace": None if ft is None else [(ft[0], ft[1]), (ft[2], ft[3])],
        "output": {"cog": not args.no_cog, "quicklook": not args.no_quicklook},
    })


def run(args: argparse.Namespace) -> int:
    import json

    from tiledsm.cli.run import print_warnings
    from tiledsm.pipelines import run_recipe
    from tiledsm.workflows.displace import plan_displace

    # the correlation's kernels are numpy FFTs and nogil numba, reads are GDAL: threads of this process
    cluster = cluster_config(args)
    recipe = displace_recipe(args)
    from tiledsm.recipes import options_of
    from tiledsm.workflows.displace import DisplaceRecipe, FIELD_NAMES

    names = {f: o for f, o in options_of(DisplaceRecipe).items() if f in FIELD_NAMES}
    plan = plan_displace(recipe, args.out, cluster, overwrite=args.overwrite, names=names)
    print_warnings("displace", plan.warnings)
    if args.dry_run:
        print(plan.summary())
        return 0
    m = run_recipe(recipe, plan.out, cluster, overwrite=args.overwrite, plan=plan)
    summary = {"out": str(plan.out), "grid": m["grid"]["text"], "valid_share": round(m["valid_share"], 4),
               "status_share": {k: round(v, 4) for k, v in m["status_share"].items()}}
    if "fault" in m:
        summary["fault_offsets_m"] = {k: {"offset": round(v["offset"], 4), "error": round(v["error"], 4)}
                                      for k, v in m["fault"]["offsets"].items()}
    print(json.dumps(summary, indent=2))
    return 0
