"""``octomerge dump-config [--config FILE] [--out FILE]``: print every setting as TOML."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from .._fileutil import atomic_write_bytes
from ..pipeline import MergeConfig, config_to_dict, dumps_toml, load_config
from ._common import CliError
from .outputs import check_output, writing

EPILOG = """examples:
  octomerge dump-config > merge.toml          # defaults, edit what you need
  octomerge merge a.bt b.bt out.bt --config merge.toml
  octomerge dump-config --config merge.toml   # check a file: prints it with defaults filled in
  octomerge dump-config --json --out merge.json   # --force to overwrite it
"""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "dump-config", help="print all settings (TOML) for --config",
        description="Print every pipeline setting, grouped by stage, as TOML (or JSON). Files "
                    "may be partial: omitted keys keep their defaults.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", type=Path, metavar="FILE", help="start from this file instead of the defaults")
    p.add_argument("--out", type=Path, metavar="FILE", help="write to FILE (atomically) instead of stdout")
    p.add_argument("--json", action="store_true", help="JSON instead of TOML")
    p.add_argument("--force", action="store_true", help="allow --out to overwrite an existing file")
    p.set_defaults(func=run)


def run(args) -> int:
    if args.out:
        check_output(args.out, inputs=[args.config] if args.config else [], force=args.force, what="--out",
                     side=True)
    try:
        cfg = load_config(args.config) if args.config else MergeConfig()
    except (ValueError, FileNotFoundError) as err:
        raise CliError(str(err)) from None
    text = json.dumps(config_to_dict(cfg), indent=2) + "\n" if args.json else dumps_toml(cfg)
    if args.out:
        with writing(args.out):
            atomic_write_bytes(args.out, text.encode())
    else:
        print(text, end="")
    return 0
