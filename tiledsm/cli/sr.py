"""``tiledsm sr IN OUT`` (super-resolve an image, RPC regenerated) and
``tiledsm train-sr`` (train an SR network on offline images)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from tiledsm.cli.run import add_cluster_arguments, add_plan_arguments, cluster_config

__all__ = ["add_parser", "run_sr", "run_train", "write_sr"]


def _blur_sigma(text: str) -> float | str:
    """``--blur-sigma``: a sigma in HR pixels, or ``bicubic``."""
    if text == "bicubic":
        return text
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a sigma in HR pixels or 'bicubic', got {text!r}") from None


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "sr",
        help="super-resolve an image (bicubic, SRCNN, VDSR, SRMD) and regenerate its RPC",
        description="Super-resolve IN tile by tile (halo = the model's receptive field) and write OUT: "
        "a GeoTIFF with RPC tags (.tif) or a zarr store (.zarr). The RPC of OUT is the RPC of IN scaled "
        "by --scale; nodata stays nodata.",
    )
    p.add_argument("input", help="image with an RPC (tags or sidecar)")
    p.add_argument("output", help="output .tif (GeoTIFF + RPC tags) or .zarr")
    p.add_argument("--model", default="srmd_official", choices=["bicubic", "srcnn", "srcnn_residual", "vdsr", "srmd", "srmd_official"],
                   help="SR network (default: the published SRMD weights, the best on held-out images; "
                        "srcnn is about 10x faster)")
    p.add_argument("--scale", type=int, default=2)
    p.add_argument("--weights", default=None, help="weights file (default: the shipped weights of --model at --scale)")
    p.add_argument("--blur-sigma", type=_blur_sigma, default=None,
                   help="SRMD: Gaussian blur sigma of the LR image, HR pixels, or 'bicubic' (LR made by bicubic downsampling)")
    p.add_argument("--noise", type=float, default=None, help="SRMD: noise standard deviation, digital numbers")
    p.add_argument("--bit-depth", type=int, default=None, help="sensor bit depth (default: smallest of 8/10/11/12/14/16 covering the data)")
    p.add_argument("--normalisation", default="stretch", choices=["stretch", "full_scale"],
                   help="value mapped to 1 before the network: the image's 99.9th percentile (default; the networks "
                        "were trained on full-range images) or the full scale 2**bit-depth - 1")
    p.add_argument("--chunk", type=int, default=512, help="tile side, input pixels")
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"], help="torch device (cuda only when available)")
    p.add_argument("--overwrite", action="store_true", help="replace OUTPUT when it exists (default: refuse)")
    add_cluster_arguments(p)
    add_plan_arguments(p, large=False)
    p.set_defaults(func=run_sr)

    t = subparsers.add_parser(
        "train-sr",
        help="train an SR network (weights + card) on offline images",
        description="Train on random patches of scikit-image's bundled images, images in the recipe's "
        "data_dirs (or --data-dir) and synthetic renders; writes the weights file and a markdown card with the held-out PSNR.",
    )
    t.add_argument("--recipe", default=None, help="YAML with TrainConfig fields (recipes/train_sr.yaml); flags override it")
    t.add_argument("--model", default=None, choices=["srcnn", "srcnn_residual", "vdsr", "srmd"])
    t.add_argument("--scale", type=int, default=None)
    t.add_argument("--out", default=None, help="weights file (.pt); card written beside it (.md)")
    t.add_argument("--steps", type=int, default=None)
    t.add_argument("--max-seconds", type=float, default=None)
    t.add_argument("--data-dir", action="append", default=None, help="image folder (repeatable; replaces the recipe's data_dirs)")
    t.add_argument("--threads", type=int, default=None, help="torch threads")
    t.add_argument("--ship", action="store_true",
                   help="allow --out inside the package's shipped weights folder (replace the shipped weights)")
    t.set_defaults(func=run_train)


def run_sr(args: argparse.Namespace) -> int:
    from tiledsm.cli.run import print_warnings
    from tiledsm.plan import plan_sr
    from tiledsm.sr.registry import SRError

    cluster = cluster_config(args)
    if args.device == "cuda":
        import torch

        if not torch.cuda.is_available():
            raise SRError("--device cuda: no CUDA device is available (use --device cpu)")
    plan = plan_sr(args.input, args.output, model=args.model, scale=args.scale, weights=args.weights,
                   chunk=args.chunk, cluster=cluster, overwrite=args.overwrite, device=args.device, blur_sigma=args.blur_sigma,
                   noise=args.noise, bit_depth=args.bit_depth, normalisation=args.normalisation)
    print_warnings("sr", plan.warnings)
    if plan.product.attrs.get("sr_scheme"):
        print(f"tiledsm sr: {args.model} has no native x{args.scale} weights: its {plan.product.attrs['sr_scheme']}",
              file=sys.stderr)
    if args.dry_run:
        print(plan.summary())
        return 0
    return write_sr(plan.product, plan.out, args.scale, cluster)


def write_sr(hr, out: Path, scale: int, cluster) -> int:
    """Compute the lazy super-resolved image ``hr`` into ``out`` (GeoTIFF
    with RPC tags, or zarr)."""
    from tiledsm.cluster import compute_context
    from tiledsm.io import scene_rpc, write_geotiff_with_rpc, write_zarr

    with compute_context(cluster):
        if out.suffix.lower() == ".zarr":
            write_zarr(hr, out)
        else:
            tags = {k: v for k, v in hr.attrs.items() if k.startswith("sr_")}
            write_geotiff_with_rpc(hr, out, scene_rpc(hr), nodata=float("nan"), dtype="float32", tags=tags)
    scheme = f" ({hr.attrs['sr_scheme']})" if hr.attrs.get("sr_scheme") else ""
    print(f"{out}: {hr.sizes['y']} x {hr.sizes['x']} px, model {hr.attrs['sr_model']} x{scale}{scheme}")
    return 0


def run_train(args: argparse.Namespace) -> int:
    from tiledsm.sr.train import config_from_yaml, train

    overrides = {
        "model": args.model, "scale": args.scale, "out": args.out, "steps": args.steps,
        "max_seconds": args.max_seconds, "threads": args.threads,
        "data_dirs": tuple(args.data_dir) if args.data_dir else None,
        "ship": True if args.ship else None,
    }
    config = config_from_yaml(args.recipe, **{k: v for k, v in overrides.items() if v is not None})
    card = train(config, log=lambda m: print(m, flush=True))
    for name, r in card["heldout_psnr_db"].items():
        print(f"{name}: {config.model} {r['model']:.2f} dB, bicubic {r['bicubic']:.2f} dB")
    print(f"wrote {config.out} and {Path(config.out).with_suffix('.md')}")
    if not card["finished"]:
        print(f"NOT FINISHED: {card['steps']} of {card['steps_planned']} steps (max_seconds); run the same command to continue")
        return 3
    return 0
