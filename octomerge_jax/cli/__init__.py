"""The ``octomerge`` command line: one console script with subcommands.

Each subcommand lives in its own module in this package and exposes
``register(subparsers) -> None`` (adding a parser whose ``func`` default is ``run(args) -> int``).
Only the module of the command being run is imported (with JAX and the pipeline behind it);
``octomerge --help`` lists the commands from ``COMMANDS`` without importing any:
docs/design.md, "Start-up: lazy imports".
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

from ..budget import MemoryBudgetError
from ..hostmem import reuse_host_memory
from ._common import CliError
from .cache import command_caches, use_fast_compile

# command -> (module in this package, the one-line summary ``octomerge --help`` shows; the same
# text as the module's ``add_parser(help=...)``, checked by tests/test_startup.py), in --help order
COMMANDS = {
    "merge": ("merge", "merge two maps (ICP-refined transform, trilinear resampling, log-odds fusion)"),
    "merge-many": ("merge_many", "merge N maps into one consistent map (pairwise registration + pose graph)"),
    "batch": ("batch", "merge many pairs or groups of maps from a CSV manifest (resumable, Dask optional)"),
    "demo": ("demo", "simulate two robots, merge their maps from a wrong guess, write figures"),
    "info": ("info", "print resolution, leaves per depth, occupancy, bounds of a map"),
    "convert": ("convert", "convert a map between .bt and .ot"),
    "build": ("build", "build a .bt/.ot map from scans (.graph/.log/.ply/.pcd), like graph2tree"),
    "export": ("export", "write voxels as .glb/.ply/.obj/.pcd, or a merge's transform as TUM"),
    "dump-config": ("dump_config", "print all settings (TOML) for --config"),
    "view": ("view", "live 3-D view of maps in the web browser (viser)"),
    "warmup": ("warmup", "compile the merge kernels for common map sizes into the persistent cache"),
}


class _VersionAction(argparse.Action):
    """``--version``: reads the installed version only when asked (importlib.metadata is slow)."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        from .. import __version__

        parser.exit(message=f"{parser.prog} {__version__}\n")


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``octomerge`` parser. ``command``: import and register only that subcommand's module
    (the others get a placeholder parser with their summary); ``None`` registers every command."""
    parser = argparse.ArgumentParser(
        prog="octomerge",
        description="Merge OctoMap occupancy octrees (.bt/.ot) built by different robots.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action=_VersionAction, help="show the version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module_name, summary) in COMMANDS.items():
        if command is not None and name != command:
            sub.add_parser(name, help=summary, add_help=False)
            continue
        try:
            module = importlib.import_module(f"{__name__}.{module_name}")
        except ModuleNotFoundError as err:  # a subcommand whose optional dependency is missing
            if err.name and err.name.startswith(__name__):
                raise
            continue
        module.register(sub)
    return parser


def _command_of(argv: list[str]) -> str | None:
    """The subcommand named in ``argv`` (the first word that is not an option), if it is one."""
    first = next((a for a in argv if not a.startswith("-")), None)
    return first if first in COMMANDS else None


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    command = _command_of(argv)
    parser = build_parser(command if command is not None else "")
    args = parser.parse_args(argv)
    if getattr(args, "func", None) is None:
        parser.print_help()
        return 2
    try:
        with command_caches():
            return int(args.func(args) or 0)
    except CliError as err:
        print(f"octomerge {args.command}: error: {err}", file=sys.stderr)
        return err.exit_code
    except (ValueError, OSError, MemoryBudgetError) as err:  # OSError: a write that failed late
        print(f"octomerge {args.command}: error: {err}", file=sys.stderr)
        return 1


#: commands that run the same large kernels many times in one process: they keep XLA:CPU's scratch
#: memory between calls (``hostmem.reuse_host_memory``); one merge would gain little and compile
#: slower (docs/design.md, "Host-memory reuse")
REUSING_COMMANDS = frozenset({"batch"})


def _wants_host_memory_reuse(command: str | None, environ=os.environ) -> bool:
    """``OCTOMERGE_REUSE_HOST_MEMORY``: ``1 / on / yes / true`` for every command, ``0 / off / no
    / false`` for none; unset (or another value): for the commands of ``REUSING_COMMANDS``."""
    value = environ.get("OCTOMERGE_REUSE_HOST_MEMORY", "").strip().lower()
    if value in ("1", "on", "yes", "true"):
        return True
    if value in ("0", "off", "no", "false"):
        return False
    return command in REUSING_COMMANDS


def console_main() -> int:
    """The ``octomerge`` command: ``main`` in a process of its own, a subcommand compiling with
    ``cache.FAST_COMPILE_FLAGS`` (``cache.use_fast_compile``); ``batch`` keeps XLA:CPU's scratch
    memory for reuse between calls (``hostmem.reuse_host_memory``; every command with
    ``OCTOMERGE_REUSE_HOST_MEMORY=1``, none with ``=0``)."""
    command = _command_of(sys.argv[1:])
    if _wants_host_memory_reuse(command):
        reuse_host_memory()
    if command is not None:  # --help and --version load no JAX
        use_fast_compile()
    return main()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(console_main())
