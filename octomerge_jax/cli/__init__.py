"""The ``octomerge`` command line: one console script with subcommands.

Each subcommand lives in its own module in this package and exposes
``register(subparsers) -> None`` (adding a parser whose ``func`` default is ``run(args) -> int``).
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

from pathlib import Path

import jax

from .. import __version__
from ..budget import MemoryBudgetError
from ..hostmem import reuse_host_memory
from ._common import CliError

# Subcommand modules, in the order ``--help`` lists them.
_COMMANDS = ["merge", "merge_many", "batch", "demo", "info", "convert", "build", "export", "dump_config", "view"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="octomerge",
        description="Merge OctoMap occupancy octrees (.bt/.ot) built by different robots.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in _COMMANDS:
        try:
            module = importlib.import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as err:  # a subcommand whose optional dependency is missing
            if err.name and err.name.startswith(__name__):
                raise
            continue
        module.register(sub)
    return parser


def enable_compilation_cache() -> str | None:
    """Turn on JAX's persistent compilation cache for this process (the command line only:
    importing the library changes no JAX setting). Compiled kernels are reused by later runs,
    which cuts a merge's first call (mostly XLA compilation) on the next invocation.

    Directory: ``$OCTOMERGE_CACHE_DIR`` if set (``""`` or ``"off"`` disables), else
    ``$XDG_CACHE_HOME/octomerge_jax/xla`` (``~/.cache/...``). A cache directory the user already
    gave JAX (``JAX_COMPILATION_CACHE_DIR``) is left alone. Returns the directory in use or
    ``None``; a directory that cannot be created disables the cache silently."""
    if jax.config.jax_compilation_cache_dir:
        return jax.config.jax_compilation_cache_dir
    path = os.environ.get("OCTOMERGE_CACHE_DIR")
    if path is None:
        base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
        path = str(Path(base) / "octomerge_jax" / "xla")
    if path.strip().lower() in ("", "off", "0", "none"):
        return None
    try:
        Path(path).mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", path)
    return path


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "func", None) is None:
        parser.print_help()
        return 2
    enable_compilation_cache()
    try:
        return int(args.func(args) or 0)
    except CliError as err:
        print(f"octomerge {args.command}: error: {err}", file=sys.stderr)
        return err.exit_code
    except (ValueError, OSError, MemoryBudgetError) as err:  # OSError: a write that failed late
        print(f"octomerge {args.command}: error: {err}", file=sys.stderr)
        return 1


def _wants_host_memory_reuse(environ=os.environ) -> bool:
    """``OCTOMERGE_REUSE_HOST_MEMORY`` unset or not one of ``0 / off / no / false``."""
    value = environ.get("OCTOMERGE_REUSE_HOST_MEMORY", "1").strip().lower()
    return value not in ("0", "off", "no", "false")


def console_main() -> int:
    """The ``octomerge`` command: ``main`` in a process of its own, so XLA:CPU's scratch
    memory is kept for reuse between calls (``hostmem.reuse_host_memory``; opt out with
    ``OCTOMERGE_REUSE_HOST_MEMORY=0``)."""
    if _wants_host_memory_reuse():
        reuse_host_memory()
    return main()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(console_main())
