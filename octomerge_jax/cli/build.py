"""``octomerge build SCANS OUT``: build a map from scans (files or a ROS bag), like OctoMap's ``graph2tree``."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ..insert import CapacityPlan, insert_point_clouds
from ..io import save
from ..io.bags import DEFAULT_MAX_POSE_GAP_S, is_bag, read_bag_scans
from ..io.scans import Scan, read_scans
from ..map import empty
from ._common import CliError
from ._inputs import check_map_input
from .outputs import MAP_SUFFIXES, check_output, writing
from .progress import Progress, show_bars

EPILOG = """examples:
  octomerge build run1.graph robot1.bt --res 0.05
  octomerge build scans.log robot1.ot --res 0.1 --max-range 4.5
  octomerge build cloud.pcd cloud.bt --res 0.05 --origin 0 0 0.5
  octomerge build run1.bag run1.bt --cloud-topic /points --pose-topic /odom --res 0.1
  octomerge build run1_ros2/ run1.bt --cloud-topic /velodyne_points --max-range 30   # poses from /tf

SCANS: an OctoMap ScanGraph (.graph), a plain log (.dat/.log/.txt: 'NODE x y z roll pitch
yaw' lines followed by 'x y z' points), or one point cloud (.ply/.pcd/.xyz) whose sensor
sits at --origin. Every scan is inserted as OctoMap's insertPointCloud does (rays from the
scan pose's position; free space along each ray, a hit at its end).

A ROS bag (ROS 1 .bag, ROS 2 folder, .db3 or .mcap): the sensor_msgs/PointCloud2 clouds of
--cloud-topic, each placed by the nav_msgs/Odometry or geometry_msgs/PoseStamped message of
--pose-topic with the nearest stamp (an Odometry's child frame is joined to the cloud's frame
through /tf_static or /tf), or without --pose-topic by the /tf + /tf_static chain from
--fixed-frame (default: the root of the tree) to the cloud's frame. A cloud with no pose (or a
dynamic /tf edge) within --max-pose-gap seconds of its stamp is skipped and counted.
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
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    g = p.add_argument_group("ROS bag input")
    g.add_argument("--cloud-topic", metavar="T", help="sensor_msgs/PointCloud2 topic (required for a bag)")
    g.add_argument("--pose-topic", metavar="T", help="nav_msgs/Odometry or geometry_msgs/PoseStamped topic "
                   "(default: poses from /tf)")
    g.add_argument("--fixed-frame", metavar="F", help="with /tf: the map's frame (default: the tf tree's root)")
    g.add_argument("--max-pose-gap", type=float, default=DEFAULT_MAX_POSE_GAP_S, metavar="S",
                   help=f"largest time [s] between a cloud and its pose (default {DEFAULT_MAX_POSE_GAP_S:g}: "
                        "half the period of a 10 Hz lidar)")
    p.set_defaults(func=run)


def run(args) -> int:
    if not args.res > 0:
        raise CliError(f"--res must be positive, got {args.res}")
    check_map_input(args.scans, "scan")
    check_output(args.output, inputs=[args.scans], force=args.force, suffixes=MAP_SUFFIXES, side=True)
    skipped = 0
    if is_bag(args.scans):
        if args.cloud_topic is None:
            raise CliError(f"{args.scans}: a bag needs --cloud-topic (a sensor_msgs/PointCloud2 topic)", 2)
        try:
            got = read_bag_scans(args.scans, args.cloud_topic, args.pose_topic, fixed_frame=args.fixed_frame,
                                 max_gap_s=args.max_pose_gap)
        except ModuleNotFoundError as err:
            raise CliError(str(err)) from None
        scans, skipped = got.scans, got.skipped
    elif args.cloud_topic or args.pose_topic or args.fixed_frame:
        raise CliError(f"{args.scans}: --cloud-topic / --pose-topic / --fixed-frame apply to a ROS bag", 2)
    else:
        scans = read_scans(args.scans)
    if args.origin is not None:
        if len(scans) != 1:
            raise CliError("--origin applies to a single point cloud; the scan file has poses")
        pose = np.eye(4)
        pose[:3, 3] = args.origin
        scans = [Scan(scans[0].points - pose[:3, 3], pose, 0)]
    clouds = [s.world_points().astype(np.float32) for s in scans]
    origins = np.array([s.sensor_origin for s in scans]).reshape(-1, 3)
    if args.batch < 1:
        raise CliError(f"--batch must be >= 1, got {args.batch}", 2)
    m, plan = empty(args.res), CapacityPlan()
    for pts, o in zip(clouds, origins):
        plan.reserve(pts, o, m.resolution, args.max_range)
    bar = Progress(len(clouds), show_bars(args.quiet), desc="inserting", unit="scan")
    for start in range(0, len(clouds), args.batch):  # the same map as one call over all scans
        part = slice(start, start + args.batch)
        m = insert_point_clouds(m, clouds[part], origins[part], args.max_range, batch_size=args.batch, plan=plan)
        bar.update(n=len(clouds[part]))
    bar.close()
    with writing(args.output):
        save(m, args.output)
    n_pts = sum(len(c) for c in clouds)
    print(f"wrote {args.output}: {len(scans)} scans, {n_pts} points, {m.num_leaves} leaves "
          f"at {args.res:g} m" + (f" ({skipped} clouds without a pose skipped)" if skipped else ""))
    return 0
