"""``tiledsm ortho IMG --dsm DSM.tif --out DIR``: the orthoimage of one image."""

from __future__ import annotations

import argparse

from tiledsm.cli.run import add_cluster_arguments, add_plan_arguments

__all__ = ["add_parser"]


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "ortho",
        help="orthoimage of an image (RPC or frame camera) on a DSM, occlusion-aware",
        description="Resample the image onto the DSM's ground grid (or a grid --resolution metres, dividing the "
        "DSM's cells) chunk by chunk, with cells hidden from the view set to NaN; write ortho.zarr, ortho.tif "
        "(COG), ortho.png and ortho.json into --out. The DSM must use the camera's height datum (RPC: WGS84 "
        "ellipsoidal).",
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
    add_plan_arguments(p, large=False)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from tiledsm.cli.run import cluster_config, print_warnings
    from tiledsm.ortho.stage import write_ortho_products
    from tiledsm.plan import plan_ortho
    from tiledsm.io.lock import OutputLock

    cluster = cluster_config(args)
    plan = plan_ortho(
        args.image, args.dsm, args.out, kernel=args.kernel, resolution=args.resolution, chunk=args.chunk,
        camera_file=args.camera, bounds=args.bounds, crs=args.crs, occlusion=not args.no_occlusion,
        occlusion_tolerance=args.occlusion_tolerance, cluster=cluster,
    )
    print_warnings("ortho", plan.warnings)
    if args.dry_run:
        print(plan.summary())
        return 0
    with OutputLock(plan.out):
        report = write_ortho_products(plan.product, plan.out, cluster=cluster, warnings=plan.warnings)
    print(f"{plan.out}/ortho.tif: {report['shape'][0]} x {report['shape'][1]} cells of {report['resolution_m']:g} m, "
          f"{report['valid_share']:.0%} valid ({report['attrs']['kernel']})")
    return 0
