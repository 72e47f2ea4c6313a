"""``tiledsm`` command line: one argparse sub-command per module.

Each command module exposes ``add_parser(subparsers)``, which registers its
sub-command(s) and sets ``func`` (called with the parsed namespace). Modules
are listed explicitly (no folder scanning); heavy imports happen inside the
handlers so ``tiledsm --help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from typing import NoReturn, Sequence

from tiledsm import __version__
from tiledsm.errors import TiledsmError

#: command modules, in the order their commands appear in ``--help``
COMMAND_MODULES = (
    "tiledsm.cli.info",
    "tiledsm.cli.synth",
    "tiledsm.cli.sr",
    "tiledsm.cli.compare",
    "tiledsm.cli.run",
    "tiledsm.cli.dsm",
    "tiledsm.cli.ortho",
    "tiledsm.cli.orient",
    "tiledsm.cli.displace",
    "tiledsm.cli.evaluate",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="tiledsm",
        description="Tiled digital surface models from satellite and UAV image scenes.",
    )
    parser.add_argument("--version", action="version", version=f"tiledsm {__version__}")
    parser.add_argument("--debug", action="store_true", help="on an error, also print its traceback")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in COMMAND_MODULES:
        importlib.import_module(name).add_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    from tiledsm.allocator import return_freed_memory

    # each phase of a command frees what it allocated: give it back, so that phases do not add up
    return_freed_memory()
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        result = args.func(args)
    except TiledsmError as exc:
        if args.debug:
            import traceback

            traceback.print_exc()
        print(f"tiledsm {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # the machine's fault (full disk, read-only folder): one line, not a traceback
        from tiledsm.errors import file_fault

        message = file_fault(exc, getattr(args, "out", None) or getattr(args, "output", None))
        if message is None:
            raise
        if args.debug:
            import traceback

            traceback.print_exc()
        print(f"tiledsm {args.command}: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"tiledsm {args.command}: interrupted", file=sys.stderr)
        return 130
    return int(result or 0)


def run() -> NoReturn:
    """The ``tiledsm`` console command: :func:`main`, then :func:`leave`."""
    leave(main())


def leave(code: int) -> NoReturn:
    """End the process with ``code`` once a command has returned, without
    the interpreter's teardown of its modules.

    Tearing down numba, llvmlite, xarray and pandas takes about 0.5 s after
    every command, however small (``benchmarks/exit_time.py``). Nothing a
    command writes needs it: its files are closed when it returns. What an
    exit still owes is done here: the exit handlers (:mod:`atexit`:
    logging's flush, temporary directories, a distributed cluster's
    close) and the flush of stdout and stderr. An exception leaving
    :func:`main` never gets here: Python prints it and exits as usual.
    """
    import atexit
    import os

    # the handlers run as at a normal exit (last registered first)
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # closed or broken pipe: nothing more can reach it
            pass
    os._exit(code)


if __name__ == "__main__":  # pragma: no cover
    run()
