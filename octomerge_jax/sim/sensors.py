"""Depth sensors: a Kinect-like camera and a spinning lidar, ray cast against a scene in JAX.

Sensor frame: x forward, y left, z up. ``scan`` returns end points in the **sensor frame**
(like the clouds stored in an OctoMap ScanGraph) for each pose ``T_world_sensor``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .raycast import cast_rays_host

__all__ = ["DepthCamera", "SpinningLidar", "scan", "kinect_axial_noise_std"]


def kinect_axial_noise_std(depth):
    """Kinect v1 axial depth noise [m] at ``depth`` [m]: ``0.0012 + 0.0019 (z - 0.4)^2``
    (Nguyen, Izadi, Lovell, 3DIMPVT 2012)."""
    depth = np.asarray(depth, dtype=np.float64)
    return 0.0012 + 0.0019 * (depth - 0.4) ** 2


@dataclasses.dataclass(frozen=True)
class DepthCamera:
    """A Kinect-like depth camera (pinhole, depth along the optical axis = sensor x).

    Attributes:
      width, height: image size [px] (Kinect: 640 x 480).
      fov_x_deg, fov_y_deg: horizontal / vertical field of view [deg] (Kinect: 57 x 43).
      min_range, max_range: valid depth interval [m] (Kinect: 0.5 to 4.5); pixels outside
        return nothing.
      noise_scale: multiplies the Kinect axial noise model (0 = exact depths).
      dropout: probability that a valid pixel returns nothing.
    """

    width: int = 640
    height: int = 480
    fov_x_deg: float = 57.0
    fov_y_deg: float = 43.0
    min_range: float = 0.5
    max_range: float = 4.5
    noise_scale: float = 1.0
    dropout: float = 0.0

    def ray_directions(self) -> np.ndarray:
        """``(height * width, 3)`` unit ray directions in the sensor frame, row-major pixels."""
        fx = (self.width / 2) / np.tan(np.radians(self.fov_x_deg) / 2)
        fy = (self.height / 2) / np.tan(np.radians(self.fov_y_deg) / 2)
        u = np.arange(self.width) + 0.5 - self.width / 2
        v = np.arange(self.height) + 0.5 - self.height / 2
        uu, vv = np.meshgrid(u, v)
        d = np.stack([np.ones_like(uu), -uu / fx, -vv / fy], axis=-1).reshape(-1, 3)
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def measure(self, distances, directions, rng: np.random.Generator) -> np.ndarray:
        """Ray distances -> sensor-frame points ``(n, 3)`` of the valid, noisy returns."""
        depth = distances * directions[:, 0]
        ok = np.isfinite(depth) & (depth >= self.min_range) & (depth <= self.max_range)
        if self.dropout > 0:
            ok &= rng.random(depth.shape) >= self.dropout
        depth = depth[ok]
        if self.noise_scale > 0:
            depth = depth + rng.normal(0.0, 1.0, depth.shape) * self.noise_scale * kinect_axial_noise_std(depth)
        d = directions[ok]
        return (d * (depth / d[:, 0])[:, None]).astype(np.float32)


@dataclasses.dataclass(frozen=True)
class SpinningLidar:
    """A spinning multi-beam lidar (e.g. 16 beams, 360 deg).

    Attributes:
      num_beams: vertical beams, evenly spread over ``[min_elevation_deg, max_elevation_deg]``.
      azimuth_steps: horizontal samples per revolution.
      min_range, max_range: valid range [m]; misses and out-of-range returns are dropped.
      noise_std: range noise [m] (Gaussian, along the ray).
      dropout: probability that a return is lost.
    """

    num_beams: int = 16
    min_elevation_deg: float = -15.0
    max_elevation_deg: float = 15.0
    azimuth_steps: int = 900
    min_range: float = 0.3
    max_range: float = 30.0
    noise_std: float = 0.01
    dropout: float = 0.0

    def ray_directions(self) -> np.ndarray:
        el = np.radians(np.linspace(self.min_elevation_deg, self.max_elevation_deg, self.num_beams))
        az = np.linspace(-np.pi, np.pi, self.azimuth_steps, endpoint=False)
        ee, aa = np.meshgrid(el, az, indexing="ij")
        return np.stack([np.cos(ee) * np.cos(aa), np.cos(ee) * np.sin(aa), np.sin(ee)],
                        axis=-1).reshape(-1, 3)

    def measure(self, distances, directions, rng: np.random.Generator) -> np.ndarray:
        r = np.asarray(distances, dtype=np.float64)
        ok = np.isfinite(r) & (r >= self.min_range) & (r <= self.max_range)
        if self.dropout > 0:
            ok &= rng.random(r.shape) >= self.dropout
        r = r[ok]
        if self.noise_std > 0:
            r = r + rng.normal(0.0, self.noise_std, r.shape)
        return (directions[ok] * r[:, None]).astype(np.float32)


def scan(sensor, triangles, poses_world_sensor, seed: int = 0) -> list[np.ndarray]:
    """Simulate ``sensor`` at each pose: a list of ``(n_i, 3)`` float32 points in the sensor frame.

    Args:
      sensor: ``DepthCamera`` or ``SpinningLidar``.
      triangles: ``(T, 3, 3)`` scene triangles [m] in the world frame (``Scene.triangles``).
      poses_world_sensor: ``(N, 4, 4)`` or ``(4, 4)`` poses ``T_world_sensor``.
      seed: noise / dropout seed (deterministic).
    """
    poses = np.asarray(poses_world_sensor, dtype=np.float64)
    if poses.shape == (4, 4):
        poses = poses[None]
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"poses_world_sensor: expected (N, 4, 4), got {poses.shape}")
    rng = np.random.default_rng(seed)
    dirs = sensor.ray_directions()
    world_dirs = np.einsum("nij,rj->nri", poses[:, :3, :3], dirs).reshape(-1, 3)
    origins = np.repeat(poses[:, :3, 3], len(dirs), axis=0)
    dist = cast_rays_host(triangles, origins, world_dirs).reshape(len(poses), len(dirs))
    return [sensor.measure(dist[i].astype(np.float64), dirs, rng) for i in range(len(poses))]
