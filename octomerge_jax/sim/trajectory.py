"""Robot trajectories: sensor poses along a path of xy waypoints.

Poses are ``T_world_sensor`` (4x4, maps sensor-frame points into the world). The sensor frame
is x forward, y left, z up (ROS ``base_link`` convention); a pose's yaw faces along the path
or towards a target point, like a ground robot with a fixed, level sensor.
"""

from __future__ import annotations

import numpy as np

from .. import se3

__all__ = ["resample_path", "poses_along_path", "pose_from_xyz_rpy",
           "apply_odometry_drift"]


def pose_from_xyz_rpy(x, y, z, roll_rad, pitch_rad, yaw_rad) -> np.ndarray:
    """``(4, 4)`` float64 pose from a translation [m] and roll/pitch/yaw [rad]
    (``se3.from_xyz_rpy`` on the host: OctoMap's ``Pose6D``)."""
    return se3.from_xyz_rpy(x, y, z, roll_rad, pitch_rad, yaw_rad, xp=np)


def _resample(waypoints, spacing: float, closed: bool):
    """(points (N, 2), their arc length (N,), waypoint arc lengths (k [+1],))."""
    w = np.asarray(waypoints, dtype=np.float64)
    if w.ndim != 2 or w.shape[1] != 2 or len(w) == 0:
        raise ValueError(f"waypoints: expected (k, 2), got shape {w.shape}")
    if not spacing > 0:
        raise ValueError(f"spacing must be positive metres, got {spacing!r}")
    if closed:
        w = np.vstack([w, w[:1]])
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(w, axis=0), axis=1))])
    if len(w) == 1 or s[-1] == 0:
        return w[:1].copy(), np.zeros(1), s
    stop = s[-1] if not closed else s[-1] - spacing / 2
    t = np.arange(0.0, stop + 1e-9, spacing)
    xy = np.stack([np.interp(t, s, w[:, 0]), np.interp(t, s, w[:, 1])], axis=1)
    return xy, t, s


def resample_path(waypoints, spacing: float, closed: bool = False) -> np.ndarray:
    """Points every ``spacing`` metres (arc length) along the polyline through ``waypoints (k, 2)``."""
    return _resample(waypoints, spacing, closed)[0]


def poses_along_path(waypoints, spacing: float = 0.25, height: float = 0.5, target=None,
                     closed: bool = False) -> np.ndarray:
    """Sensor poses ``T_world_sensor (N, 4, 4)`` every ``spacing`` m along the path.

    ``target``: ``None`` (face along the direction of travel), one xy point ``(2,)`` to face
    throughout, or ``(k, 2)`` points, one per waypoint, faced along the segment starting there
    (rows of NaN mean: face along the path on that segment).
    """
    w = np.asarray(waypoints, dtype=np.float64)
    xy, t, s = _resample(w, spacing, closed)
    if closed:
        d = np.roll(xy, -1, axis=0) - xy
    else:
        d = np.zeros_like(xy)
        d[:, 0] = 1.0
        if len(xy) > 1:
            d[:-1] = xy[1:] - xy[:-1]
            d[-1] = d[-2]
    if target is not None:
        tg = np.asarray(target, dtype=np.float64)
        if tg.shape == (2,):
            tg = np.broadcast_to(tg, w.shape)
        if tg.shape != w.shape:
            raise ValueError(f"target: expected (2,) or one xy per waypoint {w.shape}, got {tg.shape}")
        seg = np.clip(np.searchsorted(s, t + 1e-9, side="right") - 1, 0, len(w) - 1)
        per = tg[seg]
        face = np.all(np.isfinite(per), axis=1)
        d[face] = per[face] - xy[face]
    yaw = np.arctan2(d[:, 1], d[:, 0])
    return np.stack([pose_from_xyz_rpy(x, y, height, 0.0, 0.0, a) for (x, y), a in zip(xy, yaw)])


def apply_odometry_drift(poses, rng: np.random.Generator, translation_std: float = 0.01,
                         yaw_std_rad: float = 0.002) -> np.ndarray:
    """Dead-reckoning drift: compose the relative motions between consecutive poses with a
    random error (per metre travelled, std ``translation_std`` [m/m] in x,y and
    ``yaw_std_rad`` [rad/m]), accumulating from the first pose, which stays exact."""
    poses = np.asarray(poses, dtype=np.float64)
    out = poses.copy()
    for i in range(1, len(poses)):
        rel = np.linalg.inv(poses[i - 1]) @ poses[i]
        dist = float(np.linalg.norm(rel[:3, 3]))
        noise = np.eye(4)
        noise[:3, :3] = se3.rot_z(rng.normal(0.0, yaw_std_rad * dist), xp=np)
        noise[:2, 3] = rng.normal(0.0, translation_std * dist, 2)
        out[i] = out[i - 1] @ rel @ noise
    return out
