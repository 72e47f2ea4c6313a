"""``tiledsm evaluate RUN_DIR [--truth PATH]``: score a finished run
folder against a truth (:mod:`tiledsm.evaluate`)."""

from __future__ import annotations

import argparse

__all__ = ["add_parser", "run"]


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "evaluate",
        help="score a finished run folder against a truth (synthetic scene, true displacement, reference DSM)",
        description="Score the products of a finished run (dsm, displace, deformation, sr_dsm) against a truth "
        "and write evaluation.json (and quick-looks under evaluation/) into RUN_DIR. The truth defaults to the "
        "synthetic scene the run made (RUN_DIR/scene), else the recipe's input.reference (dsm, sr_dsm) or "
        "input.truth_dh (deformation).",
    )
    p.add_argument("run_dir", metavar="RUN_DIR", help="folder of a finished run (holds recipe.resolved.yaml)")
    p.add_argument("--truth", default=None, metavar="PATH",
                   help="the truth: a synthetic scene folder (scene.json), a reference DSM, a folder with the "
                   "true dE.tif, dN.tif (dU.tif) of a displacement, or a true dh raster of a deformation run")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import json

    from tiledsm.evaluate import EVALUATION, evaluate_run

    doc = evaluate_run(args.run_dir, args.truth)
    print(json.dumps({"evaluation": f"{doc['run']}/{EVALUATION}", "pipeline": doc["pipeline"],
                      "truth": doc["scores"].get("truth")}, indent=2))
    return 0
