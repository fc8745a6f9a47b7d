"""The ``octomerge`` command line: one console script with subcommands.

Each subcommand lives in its own module in this package and exposes
``register(subparsers) -> None`` (adding a parser whose ``func`` default is ``run(args) -> int``).
"""

from __future__ import annotations

import argparse
import importlib
import sys

from ._common import CliError

# Subcommand modules, in the order ``--help`` lists them.
_COMMANDS = ["merge", "batch", "demo", "info", "convert", "build", "export", "dump_config"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="octomerge",
        description="Merge OctoMap occupancy octrees (.bt/.ot) built by different robots.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    from .. import __version__

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


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "func", None) is None:
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except CliError as err:
        print(f"octomerge {args.command}: error: {err}", file=sys.stderr)
        return err.exit_code
    except (ValueError, FileNotFoundError, PermissionError, IsADirectoryError) as err:
        print(f"octomerge {args.command}: error: {err}", file=sys.stderr)
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
