"""Simulated multi-robot mapping without ROS or Gazebo: trimesh scenes, depth sensors ray cast
in JAX, robot trajectories and two-robot datasets with ground-truth transforms.

Ray casting is brute force over triangles (``raycast.py``): for the built-in indoor scenes
(~300-400 triangles) 300k rays take ~0.2 s on 2 CPU cores, so a grid/BVH does not pay here; the
outdoor ``campus`` (~1900 triangles, 14,400 lidar rays per scan) simulates in about a minute.
"""

from .box_room import scene_pair, surface_samples, voxel_centres
from .datasets import RobotRun, build_map, make_two_robot_maps, simulate_runs
from .raycast import cast_rays, cast_rays_host, mesh_triangles
from .scenes import Scene, campus, lab_room, make_scene, mesh_scene, office_floor
from .sensors import DepthCamera, SpinningLidar, kinect_axial_noise_std, scan
from .trajectory import apply_odometry_drift, pose_from_xyz_rpy, poses_along_path, resample_path

__all__ = [
    "scene_pair", "surface_samples", "voxel_centres",
    "RobotRun", "build_map", "make_two_robot_maps", "simulate_runs",
    "cast_rays", "cast_rays_host", "mesh_triangles",
    "Scene", "campus", "lab_room", "make_scene", "mesh_scene", "office_floor",
    "DepthCamera", "SpinningLidar", "kinect_axial_noise_std", "scan",
    "apply_odometry_drift", "pose_from_xyz_rpy", "poses_along_path", "resample_path",
]
