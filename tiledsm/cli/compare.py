"""``tiledsm compare REF OTHER --out DIR``: co-register and difference two DSMs."""

from __future__ import annotations

import argparse

from tiledsm.cli.run import add_cluster_arguments, add_plan_arguments, cluster_config

__all__ = ["add_parser", "run", "add_warnings"]


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "compare",
        help="co-register two DSMs (Nuth & Kääb), difference them, write statistics and a report",
        description="Compare OTHER (e.g. post-event) with REF (pre-event): bring OTHER onto REF's grid, "
        "fit a horizontal shift and vertical bias on stable terrain, write dh.zarr, dh.tif, quick-looks, "
        "metrics.json and report.html into --out. dh = OTHER_corrected - REF (metres).",
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
    add_plan_arguments(p, large=False)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import json

    from tiledsm.cli.run import print_warnings
    from tiledsm.cluster import compute_context
    from tiledsm.compare import CompareParams, CoregParams, compare_dsms
    from tiledsm.plan import plan_compare

    # compare's kernels release the GIL (numpy, numba nogil, GDAL): threads of this process beat a local cluster
    # of processes, which pays for starting workers and for moving blocks between them (benchmarks/compare.py
    # --schedulers cluster threads); a --cluster file (kind: local) keeps processes
    cluster = cluster_config(args)
    plan = plan_compare(args.ref, args.other, args.out, stable_mask=args.stable_mask, chunks=args.chunks,
                        cluster=cluster)
    print_warnings("compare", plan.warnings)
    if args.dry_run:
        print(plan.summary())
        return 0
    paths = {i.role: i.path for i in plan.inputs}  # absolute
    params = CompareParams(
        coreg=args.coreg,
        deramp=args.deramp,
        coreg_params=CoregParams(nmad_k=args.nmad_k),
        stable_mask=paths.get("--stable-mask"),
        max_slope_deg=args.max_slope,
        chunks=args.chunks,
    )
    with compute_context(cluster):
        result = compare_dsms(paths["REF"], paths["OTHER"], plan.out, params)
    add_warnings(plan.out / "metrics.json", plan.warnings)
    c = result.metrics["coregistration"]
    s = result.metrics["statistics"]["stable"]
    print(json.dumps({
        "out": str(result.out_dir),
        "coregistration": {k: c[k] for k in ("dx", "dy", "dz", "dx_px", "dy_px", "dx_m", "dy_m")},
        "stable": {k: s[k] for k in ("count", "median", "nmad", "rmse")},
    }, indent=2))
    return 0


def add_warnings(path, warnings) -> None:
    """Add ``warnings`` to the ``warnings`` list of a ``metrics.json`` (atomic rewrite)."""
    import json
    from pathlib import Path

    from tiledsm.io import atomic_path

    metrics = json.loads(Path(path).read_text())
    metrics["warnings"] = list(metrics.get("warnings", [])) + [w for w in warnings if w not in metrics.get("warnings", [])]
    with atomic_path(Path(path)) as tmp:
        Path(tmp).write_text(json.dumps(metrics, indent=2, default=float))
