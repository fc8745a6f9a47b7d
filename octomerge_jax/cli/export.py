"""``octomerge export MAP OUT``: occupied voxels as a coloured mesh (or points) for viewers."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..io import load
from ..io.export import EXPORT_FORMATS, export_map
from ._common import CliError
from .outputs import check_input, check_output, writing

EPILOG = """examples:
  octomerge export merged.bt merged.glb                  # cubes coloured by height
  octomerge export robot1.ot robot1.ply --color occupancy
  octomerge export room.bt room_points.ply --points
"""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "export", help="write occupied voxels as a .glb/.ply/.obj mesh for viewing",
        description="Write a map's voxels (occupied by default) as a mesh of cubes, one per "
                    "leaf at its size, coloured by height or occupancy probability; or as "
                    "points (leaf centres) in a .ply.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("map", type=Path, metavar="MAP", help="a .bt or .ot file")
    p.add_argument("output", type=Path, metavar="OUT", help="output .glb, .ply or .obj")
    p.add_argument("--color", choices=("height", "occupancy"), default="height",
                   help="colouring (default: height)")
    p.add_argument("--which", choices=("occupied", "free", "all"), default="occupied",
                   help="which leaves to export (default: occupied)")
    p.add_argument("--points", action="store_true", help="leaf centres as points (.ply only)")
    p.add_argument("--force", action="store_true", help="allow OUT to overwrite an existing file")
    p.set_defaults(func=run)


def run(args) -> int:
    check_input(args.map, "map")
    check_output(args.output, inputs=[args.map], force=args.force, suffixes=EXPORT_FORMATS, side=True)
    if args.points and args.output.suffix.lower() != ".ply":
        raise CliError(f"{args.output}: --points needs a .ply output")
    m = load(args.map)
    with writing(args.output):
        export_map(m, args.output, which=args.which, color_by=args.color, points=args.points)
    print(f"wrote {args.output} ({m.num_leaves} leaves in map)")
    return 0
