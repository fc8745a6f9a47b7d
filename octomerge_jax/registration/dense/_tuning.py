"""Differentiable occupancy under a traced transform, for tuning a pose by gradient through
a downstream loss: ``transform_map``'s per-voxel value (thesis eq. 5.13) and the fusion rule
of Alg. 8, evaluated at points (``transform_map`` plans its output on the host, so it cannot
be traced in the transform)."""

from __future__ import annotations

import jax.numpy as jnp

from ... import se3
from ...map import OccupancyMap
from ...resample import sample

__all__ = ["fused_log_odds", "transformed_occupancy"]


def transformed_occupancy(m_src: OccupancyMap, T_dst_src, points_dst, *,
                          method: str = "trilinear", space: str = "probability"):
    """``transform_map``'s value at destination points, with a traceable transform.

    For ``points_dst (..., 3)`` [m] in frame ``dst``, samples ``m_src`` at
    ``T_dst_src^-1 points_dst`` (eq. 5.13) with ``sample``: returns ``(value (...,), known
    (...,))`` as ``sample`` does. Differentiable w.r.t. ``T_dst_src (4, 4)`` and the points
    (``"trilinear"`` / ``"thesis"``), so a downstream loss on a transformed map's occupancy
    can be descended in the transform.
    """
    T_src_dst = se3.inverse(jnp.asarray(T_dst_src, jnp.float32))
    p = se3.transform_points(T_src_dst, jnp.asarray(points_dst, jnp.float32).reshape(-1, 3))
    v, k = sample(m_src, p, method=method, space=space)
    shape = jnp.shape(points_dst)[:-1]
    return v.reshape(shape), k.reshape(shape)


def fused_log_odds(m1: OccupancyMap, m2: OccupancyMap, T_1_2, points_1):
    """Alg. 8's fusion rule at points ``points_1 (..., 3)`` [m] of frame 1: the sum of map 1's
    log-odds and map 2's (moved by ``T_1_2``, trilinear in log-odds) where both know the point,
    the one known value where only one does, clamped to map 1's bounds; ``(log_odds (...,),
    known (...,))``. Differentiable w.r.t. ``T_1_2`` -- e.g. to tune a map pose or a sensor
    extrinsic so the merged occupancy agrees with a reference map."""
    l1, k1 = sample(m1, points_1, space="log_odds")
    l2, k2 = transformed_occupancy(m2, T_1_2, points_1, space="log_odds")
    lo = jnp.where(k1, l1, 0.0) + jnp.where(k2, l2, 0.0)
    lo = jnp.clip(lo, m1.params.clamp_min_log_odds, m1.params.clamp_max_log_odds)
    return lo, k1 | k2
