"""Writing test bags with rosbags' own writers and message classes (not part of the package):
PointCloud2 scans, Odometry / PoseStamped poses, /tf and /tf_static, raw Octomap messages."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from octomerge_jax import se3
from octomerge_jax.io.bags import typestore

KINDS = ("ros1", "sqlite3", "mcap")


def bag_path(tmp_path, kind: str, name: str = "run") -> Path:
    return tmp_path / (f"{name}.bag" if kind == "ros1" else f"{name}_{kind}")


class BagWriter:
    """``with BagWriter(path, kind) as w: w.write(topic, msgtype, msg, stamp_ns)``."""

    def __init__(self, path, kind: str):
        from rosbags.rosbag1 import Writer as W1
        from rosbags.rosbag2 import StoragePlugin, Writer as W2

        self.ros = 1 if kind == "ros1" else 2
        self.store = typestore(self.ros)
        self.writer = W1(Path(path)) if self.ros == 1 else W2(
            Path(path), version=8, storage_plugin=StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3)
        self.conns = {}

    def __enter__(self):
        self.writer.open()
        return self

    def __exit__(self, *exc):
        self.writer.close()

    def T(self, name):
        return self.store.types[name]

    def header(self, stamp_ns: int, frame: str):
        stamp = self.T("builtin_interfaces/msg/Time")(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
        H = self.T("std_msgs/msg/Header")
        return H(seq=0, stamp=stamp, frame_id=frame) if self.ros == 1 else H(stamp=stamp, frame_id=frame)

    def write(self, topic: str, msgtype: str, msg, stamp_ns: int):
        if topic not in self.conns:
            self.conns[topic] = self.writer.add_connection(topic, msgtype, typestore=self.store)
        data = self.store.serialize_ros1(msg, msgtype) if self.ros == 1 else self.store.serialize_cdr(msg, msgtype)
        self.writer.write(self.conns[topic], stamp_ns, data)

    def write_raw(self, topic: str, msgtype: str, data: bytes, stamp_ns: int):
        if topic not in self.conns:
            self.conns[topic] = self.writer.add_connection(topic, msgtype, typestore=self.store)
        self.writer.write(self.conns[topic], stamp_ns, data)

    # --- messages
    def cloud(self, points, stamp_ns, frame, *, dtype="<f4", extra_field=True, row_pad=0, nan_rows=0):
        """A PointCloud2 with x y z (and an intensity field between y and z), rows padded by
        ``row_pad`` bytes, ``nan_rows`` invalid points appended (is_dense False)."""
        PF = self.T("sensor_msgs/msg/PointField")
        pts = np.asarray(points, np.float64)
        if nan_rows:
            pts = np.concatenate([pts, np.full((nan_rows, 3), np.nan)])
        dt = np.dtype(dtype)
        kind = 7 if dt.itemsize == 4 else 8
        size = dt.itemsize
        names = ["x", "y", "intensity", "z"] if extra_field else ["x", "y", "z"]
        fields = [PF(name=n, offset=i * size, datatype=kind, count=1) for i, n in enumerate(names)]
        rec = np.zeros((len(pts), len(names)), dt)
        for i, n in enumerate(names):
            rec[:, i] = pts[:, "xyz".index(n)] if n in "xyz" else 7.0
        step = len(names) * size
        h = 2 if len(pts) % 2 == 0 and len(pts) else 1
        w = len(pts) // h
        rows = rec.view(np.uint8).reshape(h, w * step)
        rows = np.concatenate([rows, np.full((h, row_pad), 0xAB, np.uint8)], axis=1)
        return self.T("sensor_msgs/msg/PointCloud2")(
            header=self.header(stamp_ns, frame), height=h, width=w, fields=fields, is_bigendian=dt.byteorder == ">",
            point_step=step, row_step=w * step + row_pad, data=rows.ravel().copy(), is_dense=not nan_rows)

    def _pose(self, T):
        q = np.asarray(se3.to_quaternion(np.asarray(T, np.float64), xp=np))
        P = self.T("geometry_msgs/msg/Pose")
        return P(position=self.T("geometry_msgs/msg/Point")(x=T[0, 3], y=T[1, 3], z=T[2, 3]),
                 orientation=self.T("geometry_msgs/msg/Quaternion")(x=q[1], y=q[2], z=q[3], w=q[0]))

    def odometry(self, T, stamp_ns, frame="odom", child="base_link"):
        V3, Tw = self.T("geometry_msgs/msg/Vector3"), self.T("geometry_msgs/msg/Twist")
        return self.T("nav_msgs/msg/Odometry")(
            header=self.header(stamp_ns, frame), child_frame_id=child,
            pose=self.T("geometry_msgs/msg/PoseWithCovariance")(pose=self._pose(T), covariance=np.zeros(36)),
            twist=self.T("geometry_msgs/msg/TwistWithCovariance")(
                twist=Tw(linear=V3(x=0.0, y=0.0, z=0.0), angular=V3(x=0.0, y=0.0, z=0.0)), covariance=np.zeros(36)))

    def pose_stamped(self, T, stamp_ns, frame="map"):
        return self.T("geometry_msgs/msg/PoseStamped")(header=self.header(stamp_ns, frame), pose=self._pose(T))

    def tf(self, items):
        """``items``: ``[(parent, child, T_parent_child, stamp_ns)]`` -> a TFMessage."""
        V3, Q = self.T("geometry_msgs/msg/Vector3"), self.T("geometry_msgs/msg/Quaternion")
        out = []
        for parent, child, T, stamp in items:
            q = np.asarray(se3.to_quaternion(np.asarray(T, np.float64), xp=np))
            tr = self.T("geometry_msgs/msg/Transform")(translation=V3(x=T[0, 3], y=T[1, 3], z=T[2, 3]),
                                                        rotation=Q(x=q[1], y=q[2], z=q[3], w=q[0]))
            out.append(self.T("geometry_msgs/msg/TransformStamped")(
                header=self.header(stamp, parent), child_frame_id=child, transform=tr))
        return self.T("tf2_msgs/msg/TFMessage")(transforms=out)
