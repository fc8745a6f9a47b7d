"""``octomerge convert IN OUT``: between OctoMap .bt and .ot (or rewrite one)."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..io import load, num_nodes, save
from .outputs import MAP_SUFFIXES, check_input, check_output, writing

EPILOG = """examples:
  octomerge convert robot1.ot robot1.bt     # full log-odds -> maximum likelihood (lossy)
  octomerge convert room.bt room.ot         # binary -> full (leaves at clamping min/max)
  octomerge convert old.bt old.bt --force   # rewrite in place (e.g. a legacy .bt)

.bt stores only free/occupied: converting to .bt applies maximum likelihood and OctoMap's
prune, exactly as OctoMap's writeBinary does. Output is written atomically; an existing OUT
is overwritten only with --force.
"""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "convert", help="convert a map between .bt and .ot",
        description="Read an OctoMap .bt/.ot file and write it as .bt or .ot (by OUT's "
                    "extension), byte-identical to what OctoMap 1.10 writes for the tree.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("input", type=Path, metavar="IN", help="a .bt or .ot file")
    p.add_argument("output", type=Path, metavar="OUT", help="the .bt or .ot file to write")
    p.add_argument("--force", action="store_true", help="allow OUT to overwrite an existing file (IN too)")
    p.add_argument("--lenient", action="store_true",
                   help="accept trailing bytes and a wrong header size in IN")
    p.set_defaults(func=run)


def run(args) -> int:
    check_input(args.input, "map")
    check_output(args.output, inputs=[args.input], force=args.force, suffixes=MAP_SUFFIXES)
    m = load(args.input, strict=not args.lenient)
    with writing(args.output):
        save(m, args.output)
    print(f"{args.input} -> {args.output}: {m.num_leaves:,} leaves "
          f"({num_nodes(m):,} nodes) at {m.resolution:g} m, "
          f"{args.output.stat().st_size:,} bytes")
    return 0
