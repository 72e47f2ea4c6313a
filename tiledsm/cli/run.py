"""``tiledsm run RECIPE --out DIR``: run a recipe end to end."""

from __future__ import annotations

import argparse
import json

__all__ = ["add_parser"]


def add_cluster_arguments(p: argparse.ArgumentParser) -> None:
    """``--scheduler`` and ``--workers``, shared by every computing command."""
    p.add_argument("--scheduler", default=None, help="dask scheduler address (tcp://host:8786) or 'synchronous'; default: a local cluster")
    p.add_argument("--workers", type=int, default=None, help="local workers (one single-threaded process each); default: one per core")
    p.add_argument("--no-progress", action="store_true", help="do not show a progress bar")


def add_overwrite_argument(p: argparse.ArgumentParser) -> None:
    """``--overwrite``, for commands that write resumable stores into ``--out``."""
    p.add_argument(
        "--overwrite", action="store_true",
        help="recompute stores that an earlier run left in --out with other inputs or parameters "
        "(default: resume only the same run, refuse otherwise)",
    )


def cluster_config(args: argparse.Namespace, recipe_cluster=None):
    from tiledsm.cluster import ClusterConfig

    scheduler = args.scheduler or (recipe_cluster.scheduler if recipe_cluster else None)
    workers = args.workers or (recipe_cluster.workers if recipe_cluster else None)
    return ClusterConfig(scheduler=scheduler, workers=workers, progress=not args.no_progress)


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "run",
        help="run a recipe (YAML) into an output folder",
        description="Validate a recipe and run its pipeline. The run folder receives the stores, "
        "products, metrics.json, recipe.resolved.yaml and run.log.",
    )
    p.add_argument("recipe", help="recipe YAML file (see recipes/)")
    p.add_argument("--out", required=True, help="run folder")
    add_cluster_arguments(p)
    add_overwrite_argument(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from tiledsm.pipelines import run_recipe
    from tiledsm.recipes import load_recipe

    recipe = load_recipe(args.recipe)
    metrics = run_recipe(recipe, args.out, cluster_config(args, getattr(recipe, "cluster", None)), overwrite=args.overwrite)
    _print_summary(metrics)
    return 0


def _print_summary(metrics: dict) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title="run summary", show_header=False)

    def add(prefix: str, obj) -> None:
        for k, v in obj.items():
            key = f"{prefix}{k}"
            if isinstance(v, dict):
                add(key + ".", v)
            elif isinstance(v, float):
                table.add_row(key, f"{v:.4g}")
            elif isinstance(v, (int, str)):
                table.add_row(key, str(v))
            else:
                table.add_row(key, json.dumps(v, default=str))

    add("", metrics)
    Console().print(table)
