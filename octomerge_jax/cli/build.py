"""``octomerge build SCANS OUT``: build a map from scans, like OctoMap's ``graph2tree``."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ..insert import insert_point_clouds
from ..io import save
from ..io.scans import Scan, read_scans
from ..map import empty
from ._common import CliError
from .outputs import MAP_SUFFIXES, check_input, check_output, writing

EPILOG = """examples:
  octomerge build run1.graph robot1.bt --res 0.05
  octomerge build scans.log robot1.ot --res 0.1 --max-range 4.5
  octomerge build cloud.pcd cloud.bt --res 0.05 --origin 0 0 0.5

SCANS: an OctoMap ScanGraph (.graph), a plain log (.dat/.log/.txt: 'NODE x y z roll pitch
yaw' lines followed by 'x y z' points), or one point cloud (.ply/.pcd/.xyz) whose sensor
sits at --origin. Every scan is inserted as OctoMap's insertPointCloud does (rays from the
scan pose's position; free space along each ray, a hit at its end).
"""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "build", help="build a .bt/.ot map from scans (.graph/.log/.ply/.pcd), like graph2tree",
        description="Insert every scan of SCANS into a new map and save it as OUT (.bt or .ot).",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scans", type=Path, metavar="SCANS", help="scan file")
    p.add_argument("output", type=Path, metavar="OUT", help="output .bt or .ot")
    p.add_argument("--res", type=float, default=0.1, help="voxel size in metres (default 0.1)")
    p.add_argument("--max-range", type=float, default=-1.0, dest="max_range",
                   help="cut rays longer than this many metres (default: no limit)")
    p.add_argument("--origin", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                   help="sensor position for a single point cloud file (default 0 0 0)")
    p.add_argument("--batch", type=int, default=8, help="scans per update batch (default 8)")
    p.add_argument("--force", action="store_true", help="allow OUT to overwrite an existing file")
    p.set_defaults(func=run)


def run(args) -> int:
    if not args.res > 0:
        raise CliError(f"--res must be positive, got {args.res}")
    check_input(args.scans, "scan")
    check_output(args.output, inputs=[args.scans], force=args.force, suffixes=MAP_SUFFIXES, side=True)
    scans = read_scans(args.scans)
    if args.origin is not None:
        if len(scans) != 1:
            raise CliError("--origin applies to a single point cloud; the scan file has poses")
        pose = np.eye(4)
        pose[:3, 3] = args.origin
        scans = [Scan(scans[0].points - pose[:3, 3], pose, 0)]
    clouds = [s.world_points().astype(np.float32) for s in scans]
    origins = np.array([s.sensor_origin for s in scans]).reshape(-1, 3)
    m = insert_point_clouds(empty(args.res), clouds, origins, args.max_range, batch_size=args.batch)
    with writing(args.output):
        save(m, args.output)
    n_pts = sum(len(c) for c in clouds)
    print(f"wrote {args.output}: {len(scans)} scans, {n_pts} points, {m.num_leaves} leaves "
          f"at {args.res:g} m")
    return 0
