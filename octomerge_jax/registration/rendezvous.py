"""Initial transform estimate from a rendezvous (thesis §5.2.1.1, eqs. 5.8-5.11, after
Dinnissen).

Two robots, *c* (current, mapping into map 1) and *o* (other, map 2), observe each other.

2-D, as printed (eq. 5.8): ``T_1i^2 = T_c T_r T_o^{-1}`` with

- ``T_c``: pose ``(x_c, y_c, psi_c)`` of robot c in map 1 (``T_map1_c``),
- ``T_o``: pose ``(x_o, y_o, psi_o)`` of robot o in map 2 (``T_map2_o``),
- ``T_r`` (eqs. 5.9-5.11): robot o in robot c's frame from the mutual observation: c sees o
  at range ``r`` and bearing ``theta_c`` (in c's frame), o sees c at bearing ``theta_o`` (in
  o's frame); then o's heading in c's frame is ``theta_r = pi - theta_o + theta_c`` and its
  position ``r (cos theta_c, sin theta_c)``.

(The thesis reuses the symbols theta_c, theta_o for both the headings in eq. 5.8 and the
bearings in eqs. 5.9-5.11; we name them ``heading`` and ``bearing``.) When robot c measures
o's relative heading directly, pass it as ``relative_heading_rad`` instead of ``theta_o``.

3-D (our generalisation): ``T_map1_map2 = T_map1_c @ T_c_o @ inverse(T_map2_o)`` with poses as
4x4 transforms (e.g. ``se3.from_xyz_rpy``) and ``T_c_o`` from range, azimuth, elevation and
the observed robot's roll/pitch/yaw relative to c (``relative_pose_3d``). Azimuth is measured
from +x towards +y, elevation from the x-y plane towards +z, in c's frame. With zero elevation,
roll and pitch it reduces exactly to the 2-D formula.

All functions are ``jax.numpy`` (jit/vmap/grad-able); angles in radians, distances in metres.
"""

from __future__ import annotations

import jax.numpy as jnp

from .. import se3

__all__ = ["pose_2d", "relative_pose_2d", "rendezvous_transform_2d", "relative_pose_3d",
           "rendezvous_transform", "lift_2d"]


def pose_2d(x, y, heading_rad):
    """3x3 homogeneous 2-D pose (the matrices of eq. 5.8)."""
    x, y, h = (jnp.asarray(v, jnp.float32) for v in (x, y, heading_rad))
    c, s = jnp.cos(h), jnp.sin(h)
    o, z = jnp.ones_like(h), jnp.zeros_like(h)
    return jnp.stack([jnp.stack([c, -s, x], -1), jnp.stack([s, c, y], -1), jnp.stack([z, z, o], -1)], -2)


def relative_pose_2d(range_m, bearing_c_rad, bearing_o_rad=None, *, relative_heading_rad=None):
    """``T_r`` (eqs. 5.9-5.11): robot o's pose in robot c's frame from the mutual observation.
    Give either the bearing ``bearing_o_rad`` at which o sees c (eq. 5.9) or o's heading in
    c's frame ``relative_heading_rad``."""
    if (bearing_o_rad is None) == (relative_heading_rad is None):
        raise ValueError("give exactly one of bearing_o_rad and relative_heading_rad")
    r = jnp.asarray(range_m, jnp.float32)
    tc = jnp.asarray(bearing_c_rad, jnp.float32)
    if relative_heading_rad is None:
        theta_r = jnp.pi - jnp.asarray(bearing_o_rad, jnp.float32) + tc  # eq. 5.9
    else:
        theta_r = jnp.asarray(relative_heading_rad, jnp.float32)
    return pose_2d(r * jnp.cos(tc), r * jnp.sin(tc), theta_r)  # eqs. 5.10, 5.11


def rendezvous_transform_2d(pose_c, pose_o, range_m, bearing_c_rad, bearing_o_rad=None, *,
                            relative_heading_rad=None):
    """Eq. 5.8: ``T_1i^2 = T_c T_r T_o^{-1}`` (3x3) mapping map-2 points into map 1.
    ``pose_c = (x, y, heading)`` of robot c in map 1, ``pose_o`` of robot o in map 2."""
    Tc = pose_2d(*pose_c)
    To = pose_2d(*pose_o)
    Tr = relative_pose_2d(range_m, bearing_c_rad, bearing_o_rad, relative_heading_rad=relative_heading_rad)
    R = jnp.swapaxes(To[..., :2, :2], -1, -2)
    To_inv = jnp.concatenate([jnp.concatenate([R, -(R @ To[..., :2, 2:])], -1), To[..., 2:, :]], -2)
    return Tc @ Tr @ To_inv


def lift_2d(T2):
    """3x3 planar transform -> 4x4 (rotation about z, z unchanged)."""
    T2 = jnp.asarray(T2, jnp.float32)
    T = jnp.zeros(T2.shape[:-2] + (4, 4), T2.dtype)
    T = T.at[..., :2, :2].set(T2[..., :2, :2]).at[..., :2, 3].set(T2[..., :2, 2])
    return T.at[..., 2, 2].set(1.0).at[..., 3, 3].set(1.0)


def relative_pose_3d(range_m, azimuth_rad, elevation_rad=0.0, roll_rad=0.0, pitch_rad=0.0,
                     yaw_rad=0.0):
    """``T_c_o`` (4x4): robot o seen from robot c at ``range_m``, ``azimuth_rad``,
    ``elevation_rad`` (c's frame), with orientation roll/pitch/yaw relative to c (OctoMap
    ``Pose6D`` convention)."""
    r = jnp.asarray(range_m, jnp.float32)
    az = jnp.asarray(azimuth_rad, jnp.float32)
    el = jnp.asarray(elevation_rad, jnp.float32)
    x = r * jnp.cos(el) * jnp.cos(az)
    y = r * jnp.cos(el) * jnp.sin(az)
    z = r * jnp.sin(el)
    return se3.from_xyz_rpy(x, y, z, roll_rad, pitch_rad, yaw_rad)


def rendezvous_transform(T_map1_c, T_map2_o, T_c_o):
    """3-D eq. 5.8: ``T_map1_map2 = T_map1_c T_c_o T_map2_o^{-1}`` (4x4)."""
    return jnp.asarray(T_map1_c, jnp.float32) @ jnp.asarray(T_c_o, jnp.float32) @ se3.inverse(T_map2_o)
