"""``tiledsm orient IMG... [--gcps F] [--check-points F] [--dem DEM [--geoid G]] --out DIR``:
bias-compensated RPC block adjustment on its own."""

from __future__ import annotations

import argparse
from pathlib import Path

from tiledsm.cli.run import add_cluster_arguments, add_plan_arguments

__all__ = ["add_parser"]


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "orient",
        help="bias-corrected RPCs from tie points, GCPs and a reference DEM (block adjustment)",
        description="Match multi-view tie points, adjust the RPCs' image-space bias (shift or affine A0..B2) "
        "against GCPs and/or a reference DEM, and write into --out, per image, <stem>_RPC.TXT and <stem>.tif "
        "(a copy carrying the corrected RPC tags, usable by 'tiledsm dsm'), plus orient.json, residuals.csv "
        "and residuals.png.",
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
    add_plan_arguments(p, large=False)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from contextlib import nullcontext

    from tiledsm.cli.run import cluster_config, print_warnings
    from tiledsm.cluster import compute_context
    from tiledsm.orient.stage import OrientParams, orient_images, write_orientation
    from tiledsm.orient.tracks import TrackParams
    from tiledsm.plan import plan_orient
    from tiledsm.io.lock import OutputLock

    cluster = cluster_config(args)
    plan = plan_orient(args.images, args.out, gcps=args.gcps, check_points=args.check_points, dem=args.dem,
                       geoid=args.geoid, model=args.model, tie_points=not args.no_tie_points, tile=args.tile,
                       cluster=cluster)
    print_warnings("orient", plan.warnings)
    if args.dry_run:
        print(plan.summary())
        return 0
    prepared = plan.product
    paths = {i.role: i.path for i in plan.inputs}  # absolute
    params = OrientParams(model=args.model, tie_points=not args.no_tie_points, datum=args.datum,
                          tracks=TrackParams(tile=args.tile, extractor=args.extractor))
    with OutputLock(plan.out):
        # the tie-point tiles are the only parallel part; GCP-only runs start no cluster
        with compute_context(cluster) if params.tie_points and len(prepared.images) > 1 else nullcontext():
            o = orient_images(prepared.images, paths.get("--gcps"), paths.get("--check-points"), prepared.dem,
                              params, rpcs=prepared.rpcs)
        datum_warning = [o.report["datum"]["warning"]] if "warning" in o.report["datum"] else []
        doc = write_orientation(o, plan.out, params, extra={"command": "tiledsm orient",
                                                            "warnings": plan.warnings + datum_warning,
                                                            "inputs": {
            "images": list(prepared.images), "gcps": paths.get("--gcps"),
            "check_points": paths.get("--check-points"), "dem": paths.get("--dem"), "geoid": paths.get("--geoid")}})
    _print_table(doc)
    print(f"datum: {doc['datum']['fixed_by']}")
    print_warnings("orient", datum_warning)
    return 0


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
