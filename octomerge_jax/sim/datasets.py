"""Two-robot mapping runs with ground truth (thesis §7.1.2 and §7.2.2).

Robot 1 maps in the world frame. Robot 2 maps in its own frame ``m2``, rotated by ``yaw_2_rad``
(pi/4 in the thesis, "so that maps are built in different voxel discretizations") and offset
from the world: ``T_1_2`` (= ``T_m1_m2``) maps points of robot 2's map frame into robot 1's.
Optional odometry drift perturbs each robot's believed poses (the scans are taken at the true
poses but inserted at the drifted ones), as when a robot localises by dead reckoning.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..insert import CapacityPlan, insert_point_clouds
from ..map import OccupancyMap, OccupancyParams, empty
from .scenes import Scene, make_scene
from .sensors import DepthCamera, scan
from .trajectory import apply_odometry_drift, pose_from_xyz_rpy, poses_along_path

__all__ = ["RobotRun", "simulate_runs", "build_map", "make_two_robot_maps"]


@dataclasses.dataclass(frozen=True)
class RobotRun:
    """One robot's mapping run.

    Attributes:
      scans: list of ``(n_i, 3)`` float32 point clouds [m] in the sensor frame.
      poses_map_sensor: ``(N, 4, 4)`` believed sensor poses in the robot's map frame (drifted
        if drift was requested): what the robot inserts with.
      poses_world_sensor: ``(N, 4, 4)`` true sensor poses in the world frame.
      T_world_map: ``(4, 4)`` the robot's map frame in the world.
    """

    scans: list
    poses_map_sensor: np.ndarray
    poses_world_sensor: np.ndarray
    T_world_map: np.ndarray


def _map_clouds(scans, poses_map_sensor) -> tuple[list[np.ndarray], np.ndarray]:
    """Sensor-frame scans moved to the map frame: ``(clouds (n_i, 3) float32, origins (N, 3))``."""
    clouds, origins = [], []
    for pts, T in zip(scans, np.asarray(poses_map_sensor, dtype=np.float64)):
        clouds.append((np.asarray(pts, np.float64).reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]).astype(np.float32))
        origins.append(T[:3, 3])
    return clouds, np.asarray(origins, np.float64).reshape(-1, 3)


def build_map(scans, poses_map_sensor, resolution: float, max_range: float = -1.0,
              params: OccupancyParams | None = None) -> OccupancyMap:
    """Insert sensor-frame scans ``(n_i, 3)`` [m] at their poses ``(N, 4, 4)`` (OctoMap
    ``insertPointCloud`` per scan)."""
    clouds, origins = _map_clouds(scans, poses_map_sensor)
    return insert_point_clouds(empty(resolution, params), clouds, origins, max_range)


def simulate_runs(scene="lab", *, sensor=None, spacing: float | None = None, yaw_2_rad: float = np.pi / 4,
                  offset_2=(1.5, -0.8, 0.0), drift_translation: float = 0.0,
                  drift_yaw_rad: float = 0.0, seed: int = 0) -> tuple[RobotRun, RobotRun, np.ndarray]:
    """Simulate the two robots' scans along the scene's paths.

    Returns ``(run1, run2, T_1_2)``; ``T_1_2`` maps robot 2's map frame into robot 1's (world).
    ``drift_translation`` [m per m travelled] and ``drift_yaw_rad`` [rad per m] add odometry drift.
    """
    sc: Scene = make_scene(scene, seed)
    if sensor is None:  # the scene's suggestion, else the default depth camera
        sensor = DepthCamera(width=128, height=96) if sc.sensor is None else sc.sensor
    if spacing is None:
        spacing = 0.5 if sc.spacing is None else sc.spacing
    rng = np.random.default_rng(seed)
    T_1_2 = pose_from_xyz_rpy(*offset_2, 0.0, 0.0, yaw_2_rad)
    runs = []
    for i, T_world_map in enumerate((np.eye(4), T_1_2)):
        P_world = poses_along_path(sc.paths[i], spacing, sc.sensor_height, sc.targets[i], sc.closed[i])
        scans = scan(sensor, sc.triangles, P_world, seed=seed * 2 + i)
        P_map = np.linalg.inv(T_world_map) @ P_world
        if drift_translation > 0 or drift_yaw_rad > 0:
            P_map = apply_odometry_drift(P_map, rng, drift_translation, drift_yaw_rad)
        runs.append(RobotRun(scans, P_map, P_world, T_world_map))
    return runs[0], runs[1], T_1_2


def make_two_robot_maps(scene="lab", resolution: float = 0.1, *, sensor=None, spacing: float | None = None,
                        yaw_2_rad: float = np.pi / 4, offset_2=(1.5, -0.8, 0.0),
                        max_range: float = -1.0, drift_translation: float = 0.0,
                        drift_yaw_rad: float = 0.0, seed: int = 0,
                        params: OccupancyParams | None = None):
    """Two robots map overlapping parts of ``scene``; returns ``(map1, map2, T_1_2)``.

    Args:
      scene: a ``Scene`` or ``"lab"`` (thesis §7.2) / ``"office"`` (§7.1) / ``"campus"``
        (outdoor, ~100 x 60 m; at 0.2 m ~1M leaves per map, 0.4-0.5M as ``.bt``, ~1 min to
        simulate here).
      resolution: voxel size [m] of both maps.
      sensor: ``DepthCamera`` or ``SpinningLidar``; default the scene's suggestion (the
        campus: a 16-beam lidar), else a 128 x 96 depth camera (Kinect FOV and range).
      spacing: distance between scans along each path [m]; default the scene's (campus 2 m)
        or 0.5 m.
      yaw_2_rad, offset_2: robot 2's map frame in robot 1's (thesis: pi/4 yaw).
      max_range: insertion max range [m] (< 0: none).
      drift_translation, drift_yaw_rad: odometry drift per metre (0 = perfect localisation).
      seed: makes the scene, noise and drift deterministic.

    ``T_1_2`` (4x4 float64) maps points of map 2's frame into map 1's frame: the ground truth
    the merger should recover.
    """
    run1, run2, T_1_2 = simulate_runs(scene, sensor=sensor, spacing=spacing, yaw_2_rad=yaw_2_rad,
                                      offset_2=offset_2, drift_translation=drift_translation,
                                      drift_yaw_rad=drift_yaw_rad, seed=seed)
    inputs = [_map_clouds(run.scans, run.poses_map_sensor) for run in (run1, run2)]
    plan = CapacityPlan()  # both maps' scans sized up front: map 2 reuses map 1's programs
    for clouds, origins in inputs:
        for pts, o in zip(clouds, origins):
            plan.reserve(pts, o, resolution, max_range)
    map1, map2 = (insert_point_clouds(empty(resolution, params), clouds, origins, max_range, plan=plan).trimmed()
                  for clouds, origins in inputs)  # the headroom the run's updates grew with trimmed
    return map1, map2, T_1_2
