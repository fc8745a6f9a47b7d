"""Transformation error metrics (thesis §7.1.3, eqs. 7.2-7.3) plus geodesic ones.

All take ``T_est (..., 4, 4)`` and ``T_true (..., 4, 4)`` (NumPy or JAX), broadcast over leading
dimensions, and return JAX scalars/arrays (each one jitted program per shape, not an eager op
each). In the thesis ``T_est = T_1i^2 T_ICP``.

- ``rotation_error`` = eps_r (eq. 7.2): sum of absolute differences of the 3x3 rotation blocks
  (unitless, in [0, ~8.5]); the thesis judged eps_r < 0.25 "coherent".
- ``translation_error`` = eps_t (eq. 7.3): sum of absolute differences of the 4th column
  (rows 1-4; the homogeneous row contributes 0), metres; coherent below 0.9.
- ``rotation_angle_error``: geodesic angle of ``R_est^T R_true`` in radians, ``[0, pi]``.
- ``translation_distance``: Euclidean distance of the translations, metres.
- ``point_displacement``: how far each of a set of points lands from where the truth puts it,
  metres. Unlike eps_t it does not depend on where the frame's origin lies: for a map 1 km from
  its origin, a 0.001 rad rotation error adds ~1 m to eps_t but moves the map's points by
  ~0.001 x their distance from the map's own rotation centre.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = ["rotation_error", "translation_error", "rotation_angle_error", "translation_distance",
           "point_displacement"]


def _pair(T_est, T_true):
    a = jnp.asarray(T_est)
    b = jnp.asarray(T_true)
    dtype = jnp.promote_types(a.dtype, b.dtype)
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = jnp.float32
    return a.astype(dtype), b.astype(dtype)


@jax.jit
def rotation_error(T_est, T_true):
    """eps_r, eq. 7.2: ``sum_jk |T_true[j,k] - T_est[j,k]|`` over the 3x3 rotation block."""
    a, b = _pair(T_est, T_true)
    return jnp.sum(jnp.abs(b[..., :3, :3] - a[..., :3, :3]), axis=(-2, -1))


@jax.jit
def translation_error(T_est, T_true):
    """eps_t, eq. 7.3: ``sum_j |T_true[j,4] - T_est[j,4]|``, j = 1..4 (metres)."""
    a, b = _pair(T_est, T_true)
    return jnp.sum(jnp.abs(b[..., :, 3] - a[..., :, 3]), axis=-1)


@jax.jit
def rotation_angle_error(T_est, T_true):
    """Geodesic rotation error [rad]: the angle of ``R_est^T R_true``, computed with
    ``atan2(|skew|, trace)`` so it stays accurate near 0 and pi."""
    a, b = _pair(T_est, T_true)
    D = jnp.swapaxes(a[..., :3, :3], -1, -2) @ b[..., :3, :3]
    tr = D[..., 0, 0] + D[..., 1, 1] + D[..., 2, 2]
    v = jnp.stack([D[..., 2, 1] - D[..., 1, 2], D[..., 0, 2] - D[..., 2, 0], D[..., 1, 0] - D[..., 0, 1]], -1)
    return jnp.arctan2(jnp.linalg.norm(v, axis=-1), tr - 1.0)


@jax.jit
def translation_distance(T_est, T_true):
    """Euclidean distance [m] between the translation parts."""
    a, b = _pair(T_est, T_true)
    return jnp.linalg.norm(a[..., :3, 3] - b[..., :3, 3], axis=-1)


@jax.jit
def point_displacement(T_est, T_true, points):
    """Distance [m] between ``T_est p`` and ``T_true p`` for ``points (n, 3)`` [m]: ``(..., n)``.

    The frame-independent error of a registration: e.g. its mean over map 2's occupied voxel
    centres (``MergeReport.displacement``) is how far the merged map 2 sits from the truth.
    """
    a, b = _pair(T_est, T_true)
    p = jnp.asarray(points, a.dtype)
    d = (jnp.einsum("...ij,nj->...ni", a[..., :3, :3] - b[..., :3, :3], p)
         + (a[..., :3, 3] - b[..., :3, 3])[..., None, :])
    return jnp.linalg.norm(d, axis=-1)
