"""Scans in ROS bags: ``sensor_msgs/PointCloud2`` clouds placed by a pose topic
(``nav_msgs/Odometry``, ``geometry_msgs/PoseStamped`` / ``PoseWithCovarianceStamped``) or by
``/tf`` + ``/tf_static``, ready for ``insert_point_clouds`` (what ``octomerge build BAG`` does).

Each cloud's pose is looked up at its header stamp: the pose message, or for every dynamic ``/tf``
edge of the frame chain the transform, with the nearest stamp; farther than ``max_gap_s`` away the
cloud is skipped and counted (docs/design.md, "Scans from bags").
"""

from __future__ import annotations

import contextlib
from typing import NamedTuple

import numpy as np

from ... import se3
from ...budget import check_allocation
from ..scans import Scan
from ._store import BagError, connections_of, open_reader, stamp_ns

__all__ = ["BagScans", "TransformBuffer", "decode_point_cloud2", "read_bag_scans", "DEFAULT_MAX_POSE_GAP_S",
           "POSE_TYPES"]

#: nearest pose farther than this from a cloud's stamp [s]: half the period of a 10 Hz lidar
DEFAULT_MAX_POSE_GAP_S = 0.05
CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
POSE_TYPES = ("nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseStamped",
              "geometry_msgs/msg/PoseWithCovarianceStamped")
TF_TYPE = "tf2_msgs/msg/TFMessage"
# sensor_msgs/PointField datatypes -> NumPy kinds
_FIELD_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


class BagScans(NamedTuple):
    """Scans read from a bag.

    Fields:
      scans: list of ``io.scans.Scan``: points ``(n, 3)`` float64 [m] in the cloud's frame, pose
        ``(4, 4)`` ``T_fixed_sensor``, id the cloud's index on its topic.
      stamps_ns: ``(len(scans),)`` int64 header stamps [ns].
      fixed_frame: str, the frame the poses are in.
      skipped: int, clouds left out for want of a pose within ``max_gap_s``.
    """

    scans: list
    stamps_ns: np.ndarray
    fixed_frame: str
    skipped: int


def decode_point_cloud2(msg, what: str = "<PointCloud2>") -> np.ndarray:
    """The ``x y z`` of a ``sensor_msgs/PointCloud2`` -> ``(n, 3)`` float64 [m] in its frame,
    non-finite points dropped (a non-dense cloud's invalid returns). Any field layout, row
    padding and byte order; ``x y z`` of any numeric PointField type.

    Raises ``BagError`` naming ``what`` for missing fields or a data size that disagrees with
    ``height * row_step``."""
    fields = {f.name: f for f in msg.fields}
    for axis in "xyz":
        if axis not in fields:
            raise BagError(f"{what}: PointCloud2 has no '{axis}' field (fields {sorted(fields)})")
    h, w, step, row = int(msg.height), int(msg.width), int(msg.point_step), int(msg.row_step)
    data = np.asarray(msg.data, np.uint8)
    if h * w == 0:
        return np.zeros((0, 3))
    if row < w * step or data.size < h * row:
        raise BagError(f"{what}: PointCloud2 data has {data.size} bytes, less than height {h} x row_step "
                       f"{row} (width {w} x point_step {step})")
    check_allocation(h * w * (step + 48), f"{what}: PointCloud2 of {h * w} points")
    rows = data[: h * row].reshape(h, row)[:, : w * step].reshape(h * w, step)
    order = ">" if msg.is_bigendian else "<"
    cols = []
    for axis in "xyz":
        f = fields[axis]
        kind = _FIELD_DTYPES.get(int(f.datatype))
        if kind is None:
            raise BagError(f"{what}: PointCloud2 field '{axis}' has unknown datatype {f.datatype}")
        dt = np.dtype(order + kind)
        if int(f.offset) + dt.itemsize > step:
            raise BagError(f"{what}: PointCloud2 field '{axis}' at offset {f.offset} lies beyond point_step {step}")
        cols.append(np.ascontiguousarray(rows[:, f.offset:f.offset + dt.itemsize]).view(dt).ravel())
    xyz = np.stack(cols, axis=1).astype(np.float64)
    return xyz[np.all(np.isfinite(xyz), axis=1)]


def _pose_matrix(position, orientation) -> np.ndarray:
    q = np.array([orientation.w, orientation.x, orientation.y, orientation.z], np.float64)
    if not np.all(np.isfinite(q)) or np.linalg.norm(q) < 1e-9:
        raise BagError(f"invalid quaternion (w x y z) {q.tolist()}")
    return np.asarray(se3.from_quaternion(q, [position.x, position.y, position.z], xp=np))


def nearest(stamps_ns: np.ndarray, t: int) -> int:
    """Index of the stamp in sorted ``stamps_ns (k,)`` nearest to ``t`` (the earlier on a tie)."""
    i = int(np.searchsorted(stamps_ns, t))
    if i == len(stamps_ns) or (i > 0 and t - int(stamps_ns[i - 1]) <= int(stamps_ns[i]) - t):
        i -= 1
    return max(i, 0)


class _Edge(NamedTuple):
    parent: str
    stamps_ns: np.ndarray  # (k,) int64, sorted
    T: np.ndarray          # (k, 4, 4) T_parent_child
    static: bool


class TransformBuffer:
    """Transforms between frames over time, as ``/tf`` and ``/tf_static`` hold them: each
    child frame has one parent and a series of ``T_parent_child`` (one constant for a static
    edge). ``lookup`` walks both frames up to their common ancestor."""

    def __init__(self):
        self._items: dict[str, tuple[str, bool, list, list]] = {}
        self._edges: dict[str, _Edge] | None = None

    def add(self, parent: str, child: str, stamp_ns: int, T_parent_child, static: bool = False) -> None:
        """Record ``T_parent_child (4, 4)`` at ``stamp_ns``; a child keeps its first parent."""
        parent, child = parent.lstrip("/"), child.lstrip("/")
        entry = self._items.setdefault(child, (parent, static, [], []))
        if entry[0] != parent:
            raise BagError(f"frame {child} has two parents in /tf: {entry[0]} and {parent}")
        entry[2].append(int(stamp_ns))
        entry[3].append(np.asarray(T_parent_child, np.float64))
        self._edges = None

    @property
    def edges(self) -> dict[str, _Edge]:
        if self._edges is None:
            self._edges = {}
            for child, (parent, static, stamps, Ts) in self._items.items():
                order = np.argsort(np.asarray(stamps, np.int64), kind="stable")
                self._edges[child] = _Edge(parent, np.asarray(stamps, np.int64)[order],
                                           np.stack(Ts)[order], static)
        return self._edges

    def root_of(self, frame: str) -> str:
        """The top of ``frame``'s chain (a frame that is nobody's child)."""
        frame, seen = frame.lstrip("/"), set()
        while frame in self.edges and frame not in seen:
            seen.add(frame)
            frame = self.edges[frame].parent
        return frame

    def _up(self, frame: str, stamp_ns: int, max_gap_ns: int):
        """The chain from ``frame`` up: ``([(frame_k, T_{frame_k}_{frame_k-1})], stop)``, the first
        entry ``(frame, identity)``; ``stop`` is the frame whose dynamic edge to its parent has no
        transform within ``max_gap_ns`` (the chain ends there), ``None`` if the root was reached."""
        chain = [(frame, np.eye(4))]
        while frame in self.edges and len(chain) <= len(self.edges):
            e = self.edges[frame]
            if e.static:
                T_pc = e.T[-1]
            else:
                i = nearest(e.stamps_ns, stamp_ns)
                if abs(int(e.stamps_ns[i]) - stamp_ns) > max_gap_ns:
                    return chain, frame
                T_pc = e.T[i]
            chain.append((e.parent, T_pc))
            frame = e.parent
        return chain, None

    def lookup(self, target: str, source: str, stamp_ns: int, max_gap_ns: int) -> np.ndarray:
        """``T_target_source (4, 4)`` at ``stamp_ns`` [ns], each dynamic edge at its nearest stamp;
        ``None`` if an edge of the chain has no transform within ``max_gap_ns`` of the stamp.

        Raises ``BagError`` if ``/tf`` does not connect the frames."""
        target, source = target.lstrip("/"), source.lstrip("/")
        up_s, stop_s = self._up(source, stamp_ns, max_gap_ns)
        up_t, stop_t = self._up(target, stamp_ns, max_gap_ns)
        # T_frame_source for each frame on the source's chain
        to_source, T = {}, np.eye(4)
        for k, (frame, T_pc) in enumerate(up_s):
            T = T_pc @ T if k else T
            to_source[frame] = T.copy()
        T = np.eye(4)
        for k, (frame, T_pc) in enumerate(up_t):
            T = T_pc @ T if k else T  # T_frame_target
            if frame in to_source:
                return se3.inverse(T, xp=np) @ to_source[frame]
        if stop_s is not None or stop_t is not None:
            return None
        raise BagError(f"/tf does not connect frame {source} to frame {target}")


def _pose_of(msg, msgtype: str):
    """``(frame_id, child_frame or None, T_frame_child (4, 4))`` of a pose message."""
    pose = msg.pose.pose if msgtype != "geometry_msgs/msg/PoseStamped" else msg.pose
    child = str(msg.child_frame_id) if msgtype == "nav_msgs/msg/Odometry" else None
    return str(msg.header.frame_id), child, _pose_matrix(pose.position, pose.orientation)


def read_bag_scans(path, cloud_topic: str, pose_topic: str | None = None, *, fixed_frame: str | None = None,
                   max_gap_s: float = DEFAULT_MAX_POSE_GAP_S) -> BagScans:
    """Read the ``PointCloud2`` scans of a bag with their sensor poses.

    Args:
      path: a ROS 1 ``.bag``, a ROS 2 bag folder or its ``.db3`` / ``.mcap``.
      cloud_topic: the ``sensor_msgs/PointCloud2`` topic.
      pose_topic: an ``Odometry`` / ``PoseStamped`` / ``PoseWithCovarianceStamped`` topic: a
        cloud is placed at the pose with the nearest stamp, times the ``/tf`` transform from the
        pose's child frame (Odometry's ``child_frame_id``) to the cloud's frame when they differ
        (a ``PoseStamped`` is taken as the pose of the cloud's frame). ``None``: the cloud's
        frame is looked up in ``/tf`` + ``/tf_static``.
      fixed_frame: the frame of the poses with ``/tf`` (default: the root of the cloud frame's chain).
      max_gap_s: largest distance [s] between a cloud's stamp and the pose (or each dynamic
        ``/tf`` edge) used for it; clouds without one are skipped and counted.

    Returns ``BagScans`` (scans in stamp order of the bag, stamps, fixed frame, skipped count).
    Raises ``BagError`` for a missing or wrong-typed topic, a malformed message, frames ``/tf``
    does not connect, or no cloud with a pose."""
    if not max_gap_s >= 0:
        raise BagError(f"--max-pose-gap must be >= 0 seconds, got {max_gap_s}")
    gap_ns = int(round(max_gap_s * 1e9))
    tf = TransformBuffer()
    poses_t, poses_T, pose_frame, pose_child = [], [], None, None
    clouds = []  # (stamp_ns, frame, points)
    with contextlib.closing(open_reader(path)) as reader:
        cloud_conns = connections_of(reader, path, cloud_topic, (CLOUD_TYPE,), "PointCloud2")
        pose_conns = [] if pose_topic is None else \
            connections_of(reader, path, pose_topic, POSE_TYPES, "pose")
        tf_conns = [c for c in reader.connections if c.topic in ("/tf", "/tf_static") and c.msgtype == TF_TYPE]
        for con, t, raw in reader.messages(connections=[*cloud_conns, *pose_conns, *tf_conns]):
            where = f"{path}: {con.topic} at bag time {t / 1e9:.9f} s"
            try:
                msg = reader.deserialize(raw, con.msgtype)
                if con.msgtype == CLOUD_TYPE:
                    clouds.append((stamp_ns(msg.header, t), str(msg.header.frame_id).lstrip("/"),
                                   decode_point_cloud2(msg, where)))
                elif con.msgtype == TF_TYPE:
                    for ts in msg.transforms:
                        tr = ts.transform
                        tf.add(str(ts.header.frame_id), str(ts.child_frame_id), stamp_ns(ts.header, t),
                               _pose_matrix(tr.translation, tr.rotation), static=con.topic == "/tf_static")
                else:
                    frame, child, T = _pose_of(msg, con.msgtype)
                    pose_frame, pose_child = pose_frame or frame.lstrip("/"), child and child.lstrip("/")
                    poses_t.append(stamp_ns(msg.header, t))
                    poses_T.append(T)
            except BagError as err:
                raise BagError(str(err) if str(err).startswith(where) else f"{where}: {err}") from None
            except Exception as err:  # rosbags' decoder errors
                raise BagError(f"{where}: malformed {con.msgtype.replace('/msg/', '/')} "
                               f"({' '.join(str(err).split())[:160]})") from None
    if not clouds:
        raise BagError(f"{path}: {cloud_topic} has no messages")
    if pose_topic is not None and not poses_t:
        raise BagError(f"{path}: {pose_topic} has no messages")
    order = np.argsort(np.asarray(poses_t, np.int64), kind="stable")
    poses_t = np.asarray(poses_t, np.int64)[order]
    poses_T = np.asarray(poses_T, np.float64).reshape(-1, 4, 4)[order]
    fixed = pose_frame if pose_topic is not None else (fixed_frame or tf.root_of(clouds[0][1]))
    scans, stamps, skipped = [], [], 0
    for k, (t, frame, pts) in enumerate(clouds):
        try:
            if pose_topic is None:
                T = tf.lookup(fixed, frame, t, gap_ns)
            else:
                i = nearest(poses_t, t)
                T = poses_T[i] if abs(int(poses_t[i]) - t) <= gap_ns else None
                if T is not None and pose_child and pose_child != frame:
                    T_child_frame = tf.lookup(pose_child, frame, t, gap_ns)
                    T = None if T_child_frame is None else T @ T_child_frame
        except BagError as err:
            raise BagError(f"{path}: {cloud_topic}: {err}") from None
        if T is None:
            skipped += 1
            continue
        scans.append(Scan(pts, T, k))
        stamps.append(t)
    if not scans:
        src = pose_topic or "/tf"
        raise BagError(f"{path}: none of the {len(clouds)} clouds on {cloud_topic} has a pose on {src} "
                       f"within --max-pose-gap {max_gap_s:g} s")
    return BagScans(scans, np.asarray(stamps, np.int64), fixed, skipped)
