"""``tiledsm run RECIPE --out DIR``: run a recipe end to end."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

__all__ = [
    "add_parser", "add_cluster_arguments", "add_overwrite_argument", "add_plan_arguments", "cluster_config",
    "absolute_path", "print_warnings", "print_summary", "plan_and_run", "recipe_of_options",
]


def add_cluster_arguments(p: argparse.ArgumentParser, default_scheduler: str | None = None) -> None:
    """``--cluster``, ``--scheduler`` and ``--workers``, shared by every computing command.

    ``default_scheduler``: what the command runs on without ``--scheduler``
    or ``--cluster`` (``None``: a local cluster of worker processes;
    ``"threads"``: threads of its own process), read by :func:`cluster_config`."""
    p.add_argument(
        "--cluster", default=None, metavar="FILE",
        help="YAML file with a recipe's 'cluster' section (kind: local | address | slurm | pbs | sge, "
        "with 'jobqueue' resources for batch systems); --scheduler and --workers override it",
    )
    default = ("--workers threads of this process (its kernels release the GIL; --cluster FILE with kind: local "
               "starts worker processes instead)" if default_scheduler == "threads" else "a local cluster")
    p.add_argument("--scheduler", default=None, help="dask scheduler address (tcp://host:8786), 'threads' (--workers threads of this process: "
                   f"no worker processes) or 'synchronous'; default: {default}")
    p.set_defaults(default_scheduler=default_scheduler)
    p.add_argument("--workers", type=int, default=None, help="local workers (one single-threaded process each, >= 1); default: one per core")
    p.add_argument(
        "--memory-per-worker", default=None, metavar="SIZE",
        help="memory of each worker, e.g. 4GiB: a local worker is stopped beyond it, and the plan sizes chunks "
        "for it (default: the machine's memory divided among the local workers)",
    )
    p.add_argument("--no-progress", action="store_true", help="do not show a progress bar")


def add_overwrite_argument(p: argparse.ArgumentParser) -> None:
    """``--overwrite``, for commands that write resumable stores into ``--out``."""
    p.add_argument(
        "--overwrite", action="store_true",
        help="recompute stores that an earlier run left in --out with other inputs or parameters "
        "(default: resume only the same run, refuse otherwise)",
    )


def add_plan_arguments(p: argparse.ArgumentParser, large: bool = True) -> None:
    """``--dry-run`` (and ``--allow-large``), for commands planned before
    they run (:mod:`tiledsm.plan`)."""
    p.add_argument(
        "--dry-run", action="store_true",
        help="check the inputs and print the plan (grid, chunks, tasks, memory per worker, what would be "
        "reused) without computing or writing anything",
    )
    if large:
        p.add_argument(
            "--allow-large", action="store_true",
            help="run grids beyond the size limits (4e9 cells, 20000 chunks) that are otherwise refused",
        )


def cluster_config(args: argparse.Namespace, recipe_cluster=None):
    """The :class:`~tiledsm.cluster.ClusterConfig` of the options (falling
    back on a recipe's ``cluster`` section, then on the command's default
    scheduler, :func:`add_cluster_arguments`); refuses ``--workers`` < 1."""
    import dataclasses

    from tiledsm.cluster import ClusterConfig
    from tiledsm.plan import check_workers

    check_workers(args.workers, "--workers")
    if getattr(args, "cluster", None):
        from tiledsm.recipes import load_cluster

        recipe_cluster = load_cluster(args.cluster)
    progress = not args.no_progress
    memory = getattr(args, "memory_per_worker", None)
    if memory is not None:
        from tiledsm.recipes import check_size

        check_size(memory, "--memory-per-worker")
    if args.scheduler is None and args.workers is None and recipe_cluster is not None:
        config = recipe_cluster.config(progress)
        return dataclasses.replace(config, memory_limit=memory) if memory else config
    if recipe_cluster is not None and recipe_cluster.kind in ("slurm", "pbs", "sge"):
        from tiledsm.errors import InvalidOptionError

        raise InvalidOptionError(
            f"--scheduler/--workers: the run's cluster is a {recipe_cluster.kind} cluster (from --cluster or the recipe); "
            "give one or the other"
        )
    base = recipe_cluster.config(progress) if recipe_cluster is not None else ClusterConfig(progress=progress)
    return ClusterConfig(
        scheduler=args.scheduler or base.scheduler or (getattr(args, "default_scheduler", None) if recipe_cluster is None else None),
        workers=args.workers if args.workers is not None else base.workers,
        memory_limit=memory or base.memory_limit,
        progress=progress,
    )


def print_warnings(command: str, messages) -> None:
    """Each warning as one ``tiledsm COMMAND: warning: ...`` line on stderr."""
    import sys

    for m in messages:
        print(f"tiledsm {command}: warning: {m}", file=sys.stderr)


def plan_and_run(recipe, args: argparse.Namespace, cluster, names, summary=None) -> int:
    """Plan a recipe into ``args.out``; print the plan (``--dry-run``) or
    run it, printing its warnings on stderr and its summary
    (``summary(metrics)``; default :func:`print_summary`)."""
    from tiledsm.pipelines import run_recipe
    from tiledsm.plan import Limits, plan_recipe

    plan = plan_recipe(
        recipe, args.out, cluster, overwrite=args.overwrite, limits=Limits(allow_large=getattr(args, "allow_large", False)),
        names=names, command=args.command,
    )
    print_warnings(args.command, plan.warnings)
    if args.dry_run:
        print(plan.summary())
        return 0
    metrics = run_recipe(recipe, args.out, cluster, overwrite=args.overwrite, plan=plan)
    (summary or print_summary)(metrics)
    print_warnings(args.command, [w for w in metrics.get("warnings", []) if w not in plan.warnings])
    return 0


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
    add_plan_arguments(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from tiledsm.plan import RECIPE_NAMES, check_workers
    from tiledsm.pipelines import load_recipe

    check_workers(args.workers, "--workers")
    import dataclasses

    recipe = load_recipe(args.recipe)
    # the scheduler's address came from the command line or from the recipe: the plan names whichever it was
    names = dataclasses.replace(RECIPE_NAMES, scheduler="--scheduler") if args.scheduler else RECIPE_NAMES
    return plan_and_run(recipe, args, cluster_config(args, getattr(recipe, "cluster", None)), names)


def print_summary(metrics: dict) -> None:
    """The metrics of a run as a table (nested keys dotted)."""
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


def absolute_path(path: str | None) -> str | None:
    """``path`` made absolute (``~`` expanded, links resolved); ``None``
    stays ``None``: a command's recipe means the same files to the workers
    of an external cluster, whatever their working folder."""
    return None if path is None else str(Path(path).expanduser().resolve())


def recipe_of_options(model, data: dict):
    """``model`` validated from a command's options gathered as a recipe
    (``data``); a bad value is an :class:`~tiledsm.errors.InvalidOptionError`
    naming the option of the field at fault, as the model's field metadata
    spells it (:func:`tiledsm.recipes.options_of`; a field's sub-fields
    included)."""
    from pydantic import ValidationError

    from tiledsm.errors import InvalidOptionError
    from tiledsm.recipes import options_of

    option_of_field = options_of(model)

    try:
        return model.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        loc = ".".join(str(p) for p in err["loc"])
        # the deepest field with an option that holds the error's location
        option = next((o for f, o in sorted(option_of_field.items(), key=lambda fo: -len(fo[0]))
                       if loc == f or loc.startswith(f + ".")), loc)
        raise InvalidOptionError(f"{option}: {err['msg'].removeprefix('Value error, ')}") from None
