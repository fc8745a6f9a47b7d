"""``octomerge convert IN OUT``: between OctoMap .bt and .ot (or rewrite one)."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..io import num_nodes, save
from ..io.bags import write_bag
from ._common import CliError
from ._inputs import add_bag_options, check_map_input, load_map_inputs
from .outputs import MAP_SUFFIXES, check_output, writing

EPILOG = """examples:
  octomerge convert robot1.ot robot1.bt     # full log-odds -> maximum likelihood (lossy)
  octomerge convert room.bt room.ot         # binary -> full (leaves at clamping min/max)
  octomerge convert old.bt old.bt --force   # rewrite in place (e.g. a legacy .bt)
  octomerge convert run1.bag last.ot --topic /octomap_full     # the bag's last map
  octomerge convert room.bt room.bag        # one octomap_msgs/Octomap message (ROS 1)
  octomerge convert room.ot room_bag/ --full  # a ROS 2 bag folder (MCAP), full payload

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
    p.add_argument("input", type=Path, metavar="IN", help="a .bt or .ot file, or a ROS bag")
    p.add_argument("output", type=Path, metavar="OUT",
                   help="the .bt or .ot file to write, or a bag (.bag: ROS 1; other: a ROS 2 bag folder)")
    p.add_argument("--force", action="store_true", help="allow OUT to overwrite an existing file (IN too)")
    p.add_argument("--lenient", action="store_true",
                   help="accept trailing bytes and a wrong header size in IN")
    p.add_argument("--full", action="store_true",
                   help="bag OUT: a full (.ot-like, log-odds) payload instead of a binary one")
    p.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap",
                   help="bag OUT (ROS 2): storage plugin (default mcap)")
    add_bag_options(p)
    p.set_defaults(func=run)


def run(args) -> int:
    check_map_input(args.input)
    to_bag = args.output.suffix.lower() not in MAP_SUFFIXES
    if to_bag and not (args.output.suffix.lower() == ".bag" or not args.output.suffix):
        raise CliError(f"{args.output}: OUT must end in .bt or .ot (or .bag, or name a ROS 2 bag folder)")
    check_output(args.output, inputs=[args.input], force=args.force, suffixes=None if to_bag else MAP_SUFFIXES)
    (m, b), = load_map_inputs([args.input], args, strict=not args.lenient)
    with writing(args.output):
        if to_bag:
            write_bag(args.output, m, binary=not args.full, storage=None if args.output.suffix else args.storage,
                      frame_id=b.frame_id if b else "map", stamps_ns=[b.stamp_ns] if b else None)
            size = sum(f.stat().st_size for f in args.output.rglob("*")) if args.output.is_dir() else \
                args.output.stat().st_size
        else:
            save(m, args.output)
            size = args.output.stat().st_size
    print(f"{args.input} -> {args.output}: {m.num_leaves:,} leaves "
          f"({num_nodes(m):,} nodes) at {m.resolution:g} m, {size:,} bytes")
    return 0
