"""ROS bags (ROS 1 ``.bag``, ROS 2 sqlite3 / MCAP) through ``rosbags``, without a ROS install:
``octomap_msgs/Octomap`` maps in and out, ``PointCloud2`` scans with their poses in.
``rosbags`` is the optional ``bags`` extra, imported when a bag is opened."""

from ._store import BagError, is_bag, typestore
from .maps import DEFAULT_MAP_TOPICS, BagMap, read_bag, select_map, write_bag
from .scans import DEFAULT_MAX_POSE_GAP_S, BagScans, TransformBuffer, decode_point_cloud2, read_bag_scans

__all__ = ["BagError", "BagMap", "BagScans", "DEFAULT_MAP_TOPICS", "DEFAULT_MAX_POSE_GAP_S", "TransformBuffer",
           "decode_point_cloud2", "is_bag", "read_bag", "read_bag_scans", "select_map", "typestore",
           "write_bag"]
