"""``tiledsm synth OUT ...`` and ``tiledsm degrade IN OUT ...``."""

from __future__ import annotations

import argparse
import json

__all__ = ["add_parser", "run", "run_degrade"]


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "synth",
        help="make a synthetic stereo scene with known truth (views with RPCs, truth DSM)",
        description="Render 2 or 3 pushbroom views (uint16 GeoTIFFs with RPC tags) of a synthetic world "
        "(fractal relief, buildings, trees, natural texture) with occlusion, PSF and noise, and write the "
        "truth DSM (UTM, ellipsoidal heights) and scene.json. With --event, also the post-event scene and "
        "the displacement truth (dh, dx, dy, dz). With --tower, one tall flat-roofed tower at the scene centre "
        "(footprint and roof height in scene.json).",
    )
    p.add_argument("out", help="output folder")
    p.add_argument("--size", type=int, default=1024, help="image size in pixels (default 1024)")
    p.add_argument("--gsd", type=float, default=0.5, help="ground sample distance, metres (default 0.5)")
    p.add_argument("--bh", type=float, default=0.4, help="base-to-height ratio of view_0/view_1 (default 0.4)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--views", type=int, choices=(2, 3), default=2, help="number of views (default 2)")
    p.add_argument("--event", action="store_true", help="also write the post-event scene and displacement truth")
    p.add_argument("--still", choices=("none", "left"), default="none",
                   help="with --event: 'left' keeps the block left of the fault still (the right one moves by the "
                   "full slip and throw and carries the uplift); 'none' moves both by half (default)")
    p.add_argument("--chunk", type=int, default=512, help="tile edge for the dask computation (default 512)")
    p.add_argument("--psf-sigma", type=float, default=None, help="Gaussian PSF sigma, pixels (default 0.5)")
    p.add_argument("--noise", type=float, default=None, help="noise standard deviation, DN (default 3)")
    p.add_argument("--tower", type=float, default=None, metavar="HEIGHT",
                   help="add one flat-roofed tower HEIGHT metres tall at the scene centre (default: none)")
    p.add_argument("--tower-side", type=float, default=16.0, metavar="METRES",
                   help="side of the tower's square footprint, metres (default 16)")
    p.add_argument("--workers", type=int, default=None, help="dask threads (default: one per core)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=run)

    d = subparsers.add_parser(
        "degrade",
        help="make a low-resolution version of an image (bicubic or Gaussian) with its RPC regenerated",
        description="Downsample IN by --scale with antialiased bicubic or Gaussian blur + decimation, add "
        "optional noise, and write OUT with the exactly rescaled RPC (and geotransform, if any).",
    )
    d.add_argument("input", help="input GeoTIFF (RPC tags and/or CRS)")
    d.add_argument("output", help="output GeoTIFF")
    d.add_argument("--scale", type=float, default=2.0, help="downsampling factor (default 2)")
    d.add_argument("--method", choices=("bicubic", "gaussian"), default="bicubic", help="kernel (default bicubic)")
    d.add_argument("--sigma", type=float, default=None, help="Gaussian sigma in input pixels (default scale/2)")
    d.add_argument("--noise", type=float, default=0.0, help="additive noise standard deviation, DN (default 0)")
    d.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    d.set_defaults(func=run_degrade)


def run(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from pathlib import Path

    from tiledsm.errors import InvalidOptionError
    from tiledsm.synth import RadiometryParams, TowerParams, make_scene

    if args.size < 16:
        raise InvalidOptionError(f"--size: need at least 16 pixels, got {args.size}")
    if not args.gsd > 0:
        raise InvalidOptionError(f"--gsd: must be positive, got {args.gsd}")
    if Path(args.out).exists() and not Path(args.out).is_dir():
        raise InvalidOptionError(f"{Path(args.out).resolve()}: OUT is a file, expected a folder")
    rad = RadiometryParams()
    if args.psf_sigma is not None:
        rad = replace(rad, psf_sigma=args.psf_sigma)
    if args.noise is not None:
        rad = replace(rad, noise=args.noise)
    tower = None if args.tower is None else TowerParams(height_m=args.tower, side_m=args.tower_side)
    event_params = None
    if args.event:
        from tiledsm.synth import EventParams

        event_params = EventParams.for_extent(args.size * args.gsd, still=args.still)
    info = make_scene(args.out, size=args.size, gsd=args.gsd, bh=args.bh, seed=args.seed, views=args.views,
                      event=args.event, chunk=args.chunk, radiometry=rad, tower=tower, workers=args.workers,
                      event_params=event_params)
    summary = {
        "out": str(info.out_dir),
        "views": [str(p) for p in info.views],
        "truth_dsm": str(info.truth_dsm),
        "crs": info.grid.crs,
        "bh_measured": round(info.bh, 4),
        "bh_pairs": {k: round(v, 4) for k, v in info.bh_pairs.items()},
        "rpc_fit_max_px": [float(f"{v:.3g}") for v in info.fit_residual_px],
        "height_range_m": [round(v, 2) for v in info.height_range],
        "seconds": round(info.timings_s.get("total", float("nan")), 2),
    }
    if info.tower is not None:
        summary["tower"] = {"window_rows_cols": list(info.tower.window),
                            "roof_height_m": round(info.tower.roof_height, 3)}
    if info.event is not None:
        summary["event"] = {k: str(v) for k, v in info.event.items() if k not in ("params", "post_views")}
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        for k, v in summary.items():
            print(f"{k:16s} {v}")
    return 0


def run_degrade(args: argparse.Namespace) -> int:
    from tiledsm.synth import degrade

    out = degrade(args.input, args.output, scale=args.scale, method=args.method, sigma=args.sigma,
                  noise=args.noise, seed=args.seed)
    print(out)
    return 0
