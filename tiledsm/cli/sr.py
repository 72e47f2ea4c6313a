"""``tiledsm sr IMAGE OUT`` (super-resolve an image into a run folder, RPC regenerated) and
``tiledsm train-sr`` (train an SR network on offline images)."""

from __future__ import annotations

import argparse
from pathlib import Path

from tiledsm.cli.run import add_cluster_arguments, add_overwrite_argument, add_plan_arguments, cluster_config

__all__ = ["add_parser", "run_sr", "run_train", "sr_recipe", "run_folder"]


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
        description="Super-resolve IMAGE tile by tile (halo = the model's receptive field) into the run folder "
        "OUT: sr.tif (GeoTIFF with RPC tags; --format zarr: sr.zarr), metrics.json, recipe.resolved.yaml and "
        "run.log. The RPC of the output is the RPC of IMAGE scaled by --scale; nodata stays nodata.",
    )
    p.add_argument("input", metavar="IMAGE", help="image with an RPC (tags or sidecar)")
    p.add_argument("output", metavar="OUT", nargs="?", default=None,
                   help="run folder (new, or from an earlier run of the same options); or give --out")
    p.add_argument("--out", default=None, help="run folder (the same as OUT)")
    p.add_argument("--format", default="tif", help="tif (sr.tif, GeoTIFF + RPC tags; default) or zarr (sr.zarr)")
    p.add_argument("--model", default="srmd_official",
                   help="SR network: bicubic, srcnn, srcnn_residual, vdsr, srmd or srmd_official (default: the "
                        "published SRMD weights, the best on held-out images; srcnn is about 10x faster)")
    p.add_argument("--scale", type=int, default=2,
                   help="upscaling factor; a network without native weights at it applies its x2 weights "
                        "repeatedly (a power of two; said in the output's sr_scheme tag)")
    p.add_argument("--weights", default=None, help="weights file (default: the shipped weights of --model at --scale)")
    p.add_argument("--blur-sigma", type=_blur_sigma, default=None,
                   help="SRMD: Gaussian blur sigma of the LR image, HR pixels, or 'bicubic' (LR made by bicubic downsampling)")
    p.add_argument("--noise", type=float, default=None, help="SRMD: noise standard deviation, digital numbers")
    p.add_argument("--bit-depth", type=int, default=None, help="sensor bit depth (default: smallest of 8/10/11/12/14/16 covering the data)")
    p.add_argument("--normalisation", default="stretch",
                   help="value mapped to 1 before the network: stretch, the image's 99.9th percentile (default; the "
                        "networks were trained on full-range images), or full_scale, 2**bit-depth - 1")
    p.add_argument("--chunk", type=int, default=512, help="tile side, input pixels")
    p.add_argument("--device", default="cpu", help="torch device: cpu (default) or cuda (only when available)")
    # torch's convolutions release the GIL: threads of this process, as dsm and compare, start in no time and
    # leave no worker processes behind a failed write (a full disk's error stays one line)
    add_cluster_arguments(p, default_scheduler="threads")
    add_overwrite_argument(p)
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


def run_folder(args: argparse.Namespace) -> str:
    """The run folder of ``tiledsm sr IMAGE OUT`` (or ``--out OUT``); a
    path ending in .tif/.tiff/.zarr (the command's older form, which named
    the output file) is refused with the new form spelled out."""
    from tiledsm.errors import InvalidOptionError

    if args.output and args.out and Path(args.output).resolve() != Path(args.out).resolve():
        raise InvalidOptionError(f"OUT: {args.output} and --out {args.out} name two folders; give one")
    out = args.output or args.out
    if out is None:
        raise InvalidOptionError("OUT: give the run folder: tiledsm sr IMAGE OUT (it receives sr.tif and the run files)")
    if Path(out).suffix.lower() in (".tif", ".tiff", ".zarr"):
        raise InvalidOptionError(
            f"{out}: OUT: is a run folder, not the output file: it receives sr.tif (or, with --format zarr, sr.zarr) "
            f"beside metrics.json, recipe.resolved.yaml and run.log; give a folder, e.g. {Path(out).with_suffix('')}")
    return out


def sr_recipe(args: argparse.Namespace):
    """The ``pipeline: sr`` recipe of the command's options, every path
    absolute; a bad value is an :class:`~tiledsm.errors.InvalidOptionError`
    naming the option."""
    from tiledsm.cli.run import absolute_path, recipe_of_options
    from tiledsm.sr.recipe import SRRecipe

    spec = {"model": args.model, "scale": args.scale, "weights": absolute_path(args.weights),
            "blur_sigma": args.blur_sigma, "noise": args.noise, "bit_depth": args.bit_depth,
            "normalisation": args.normalisation, "chunk": args.chunk, "device": args.device}
    return recipe_of_options(SRRecipe, {
        "pipeline": "sr", "name": Path(args.out).name, "input": {"image": absolute_path(args.input)},
        "sr": spec, "output": {"format": args.format},
    })


def print_sr_summary(metrics: dict) -> None:
    """One line: the product, its size and the network."""
    sr = metrics["sr"]
    scheme = f" ({sr['scheme']})" if sr.get("scheme") else ""
    print(f"{metrics['product']}: {metrics['shape'][0]} x {metrics['shape'][1]} px, model {sr['model']} "
          f"x{sr['scale']}{scheme}")


def run_sr(args: argparse.Namespace) -> int:
    from tiledsm.cli.run import plan_and_run
    from tiledsm.plan import FieldNames
    from tiledsm.recipes import options_of
    from tiledsm.sr.recipe import SRRecipe

    args.out = run_folder(args)
    cluster = cluster_config(args)
    return plan_and_run(sr_recipe(args), args, cluster, FieldNames.of_options(options_of(SRRecipe)), summary=print_sr_summary)


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
