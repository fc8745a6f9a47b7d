"""Simulated multi-robot mapping without ROS or Gazebo: trimesh scenes, depth sensors ray cast
in JAX, robot trajectories and two-robot datasets with ground-truth transforms.

Ray casting is brute force over triangles (``raycast.py``): the built-in scenes have a few
hundred (indoor) to about two thousand (the outdoor ``campus``) triangles, too few for a
grid or BVH to pay.
"""

from .box_room import scene_pair, surface_samples, voxel_centres
from .datasets import RobotRun, build_map, make_two_robot_maps, simulate_runs
from .raycast import cast_rays, cast_rays_host, mesh_triangles
from .scenes import Scene, campus, lab_room, make_scene, mesh_scene, office_floor
from .small_room import small_room_map, small_room_voxels
from .team import TeamMaps, team_maps, tile_grid
from .sensors import DepthCamera, SpinningLidar, kinect_axial_noise_std, scan
from .trajectory import apply_odometry_drift, pose_from_xyz_rpy, poses_along_path, resample_path

__all__ = [
    "scene_pair", "surface_samples", "voxel_centres", "small_room_map", "small_room_voxels",
    "RobotRun", "build_map", "make_two_robot_maps", "simulate_runs",
    "cast_rays", "cast_rays_host", "mesh_triangles",
    "Scene", "campus", "lab_room", "make_scene", "mesh_scene", "office_floor",
    "TeamMaps", "team_maps", "tile_grid",
    "DepthCamera", "SpinningLidar", "kinect_axial_noise_std", "scan",
    "apply_odometry_drift", "pose_from_xyz_rpy", "poses_along_path", "resample_path",
]
