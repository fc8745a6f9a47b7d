"""``octomerge export MAP OUT``: occupied voxels as a coloured mesh or point cloud for viewers
and point-cloud tools; ``octomerge export REPORT.json OUT.tum``: a merge's transform as TUM."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from ..io.export import EXPORT_FORMATS, export_map, write_tum
from ._common import CliError
from ._inputs import add_bag_options, check_map_input, load_map_inputs
from .outputs import check_input, check_output, writing
from .progress import StageBar, show_bars

EPILOG = """examples:
  octomerge export merged.bt merged.glb                  # cubes coloured by height
  octomerge export robot1.ot robot1.ply --color occupancy
  octomerge export room.bt room_points.ply --points      # leaf centres (trimesh, Open3D)
  octomerge export room.bt room.pcd [--ascii]            # leaf centres for PCL / Open3D
  octomerge export report.json T_1_2.tum                 # the merge's transform, TUM format

A .pcd holds x y z (float32) and PCL's packed rgb of the selected leaf centres. A .tum/.txt
output from a merge report (octomerge merge --report) holds one line 'timestamp tx ty tz qx qy
qz qw' per transform T_1_2 (map 2's frame in map 1's; timestamp 0, or the report's position
in a JSON list of reports), as evo and the TUM tools read.
"""

TUM_SUFFIXES = (".tum", ".txt")


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "export", help="write voxels as .glb/.ply/.obj/.pcd, or a merge's transform as TUM",
        description="Write a map's voxels (occupied by default) as a mesh of cubes, one per "
                    "leaf at its size, coloured by height or occupancy probability; or as "
                    "points (leaf centres) in a .ply or .pcd. From a merge report (.json), write "
                    "the merged transform in the TUM trajectory format.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("map", type=Path, metavar="MAP", help="a .bt or .ot file, a ROS bag, or a merge report .json")
    p.add_argument("output", type=Path, metavar="OUT", help="output .glb, .ply, .obj, .pcd (or .tum from a report)")
    p.add_argument("--color", choices=("height", "occupancy"), default="height",
                   help="colouring (default: height)")
    p.add_argument("--which", choices=("occupied", "free", "all"), default="occupied",
                   help="which leaves to export (default: occupied)")
    p.add_argument("--points", action="store_true", help="leaf centres as points (.ply; a .pcd is always points)")
    p.add_argument("--ascii", action="store_true", help="a .pcd as text instead of binary")
    p.add_argument("--force", action="store_true", help="allow OUT to overwrite an existing file")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    add_bag_options(p)
    p.set_defaults(func=run)


def _transforms_of_report(path: Path) -> np.ndarray:
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise CliError(f"{path}: not a JSON merge report ({err})") from None
    reports = data if isinstance(data, list) else [data]
    Ts = []
    for i, r in enumerate(reports):
        if not isinstance(r, dict) or "T_1_2" not in r:
            raise CliError(f"{path}: report {i} has no T_1_2 (write one with octomerge merge --report)")
        T = np.asarray(r["T_1_2"], np.float64)
        if T.shape != (4, 4):
            raise CliError(f"{path}: report {i}: T_1_2 has shape {T.shape}, not (4, 4)")
        Ts.append(T)
    return np.stack(Ts)


def run(args) -> int:
    if args.map.suffix.lower() == ".json":
        check_input(args.map, "report")
        if args.output.suffix.lower() not in TUM_SUFFIXES:
            raise CliError(f"{args.output}: a report exports to .tum or .txt (TUM poses)")
        check_output(args.output, inputs=[args.map], force=args.force, side=True)
        Ts = _transforms_of_report(args.map)
        with writing(args.output):
            write_tum(args.output, np.arange(len(Ts), dtype=np.float64), Ts)
        print(f"wrote {args.output} ({len(Ts)} transform{'s' * (len(Ts) != 1)}, TUM)")
        return 0
    check_map_input(args.map)
    check_output(args.output, inputs=[args.map], force=args.force, suffixes=EXPORT_FORMATS, side=True)
    if args.points and args.output.suffix.lower() not in (".ply", ".pcd"):
        raise CliError(f"{args.output}: --points needs a .ply output")
    if args.ascii and args.output.suffix.lower() != ".pcd":
        raise CliError(f"{args.output}: --ascii applies to a .pcd", 2)
    bar = StageBar(show_bars(args.quiet), "export", total=2)
    try:
        with bar.stage("load"):
            (m, _), = load_map_inputs([args.map], args)
        with bar.stage("write"), writing(args.output):
            export_map(m, args.output, which=args.which, color_by=args.color, points=args.points,
                       ascii=args.ascii)
    finally:
        bar.close()
    print(f"wrote {args.output} ({m.num_leaves} leaves in map)")
    return 0
