"""ICP's plan, fixed on the host before the jitted loop: the correspondence-distance stages
(thesis §6.3 / Appendix A.1), the stop thresholds, the hash-table sizes of the stages' grids,
and the initial guesses of ``icp_multi``.

The correspondence distance starts at ``10 res`` and halves down to ``2 res``; a stage ends
when the change between consecutive transforms, ``sum |T_k - T_{k-1}|`` over the 16 entries
(the thesis's transformation epsilon), falls below ``res / 60``. The number of stages is static
(one grid per stage), their distances traced.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ... import se3
from ..._ops import is_traced
from .. import neighbors

__all__ = ["stage_distances", "resolve_options", "table_sizes", "build_stage_grids", "default_hypotheses"]


def stage_distances(resolution: float, max_correspondence_distance: float | None = None,
                    min_correspondence_distance: float | None = None,
                    shrink_factor: float = 0.5) -> np.ndarray:
    """Host: the correspondence-distance schedule ``(s,)`` float32 [m]: ``d_max, shrink*d_max,
    ...`` clipped at ``d_min`` (defaults ``10 res`` and ``2 res``; at most 32 stages).
    Raises ``ValueError`` on a non-positive ``resolution`` [m], distances outside ``0 < d_min
    <= d_max`` or ``shrink_factor`` outside ``(0, 1)``."""
    res = float(resolution)
    if not (np.isfinite(res) and res > 0):
        raise ValueError(f"resolution must be a positive number of metres, got {resolution!r}")
    d_max = 10.0 * res if max_correspondence_distance is None else float(max_correspondence_distance)
    d_min = min(2.0 * res, d_max) if min_correspondence_distance is None else float(min_correspondence_distance)
    if not (np.isfinite(d_max) and d_max > 0):
        raise ValueError(f"max_correspondence_distance must be positive, got {max_correspondence_distance!r}")
    if not (np.isfinite(d_min) and 0 < d_min <= d_max):
        raise ValueError(f"min_correspondence_distance must lie in (0, max_correspondence_distance="
                         f"{d_max:g}], got {min_correspondence_distance!r}")
    if not 0.0 < float(shrink_factor) < 1.0:
        raise ValueError(f"shrink_factor must lie in (0, 1), got {shrink_factor!r}")
    out = [d_max]
    while out[-1] > d_min * (1 + 1e-9) and len(out) < 32:
        out.append(max(out[-1] * float(shrink_factor), d_min))
    return np.asarray(out, np.float32)


def resolve_options(resolution, max_correspondence_distance, min_correspondence_distance, shrink_factor,
                    transformation_epsilon, max_iterations, cell_capacity):
    """Host: ``(stage distances (s,) [m], epsilon float32)`` of ``icp``'s keyword arguments
    (epsilon defaults to ``resolution / 60``). Raises ``ValueError`` on a bad argument."""
    dists = stage_distances(resolution, max_correspondence_distance, min_correspondence_distance,
                            shrink_factor)
    eps = float(resolution) / 60.0 if transformation_epsilon is None else float(transformation_epsilon)
    if not eps > 0:
        raise ValueError(f"transformation_epsilon must be positive, got {transformation_epsilon!r}")
    if int(max_iterations) < 1:
        raise ValueError(f"max_iterations must be >= 1, got {max_iterations!r}")
    if int(cell_capacity) < 1:
        raise ValueError(f"cell_capacity must be >= 1, got {cell_capacity!r}")
    return dists, np.float32(eps)


def table_sizes(capacity: int, dists, given=None) -> tuple[int, ...]:
    """Static hash-table sizes of the stages' grids for a target of ``capacity`` rows:
    ``given`` as ints, else ``neighbors.level_table_sizes(capacity, dists)``. Raises
    ``ValueError`` if ``dists`` is traced and nothing is given."""
    if given is not None:
        return tuple(int(t) for t in given)
    if is_traced(dists):
        raise ValueError("table_sizes must be given when the stage distances are traced")
    return neighbors.level_table_sizes(capacity, np.asarray(dists))


def build_stage_grids(target, target_count, dists, sizes: tuple[int, ...], cell_capacity: int):
    """One hashed grid per stage over ``target (Nt, 3)`` [m] (no gradient), cell = the stage's
    distance: the coarse stages' grids hold the voxel-grid centroids at ``d / 2`` (at most 8 per
    cell, so ``cell_capacity`` drops nothing there), the last stage's the target points."""
    centroid_levels = (True,) * (len(sizes) - 1) + (False,)
    return neighbors.build_grids(jax.lax.stop_gradient(jnp.asarray(target, jnp.float32)), target_count,
                                 dists, table_sizes=sizes, cell_capacity=cell_capacity,
                                 centroid_levels=centroid_levels)


def default_hypotheses(T_target_source_init, center, yaw_step_rad: float = np.pi / 6,
                       roll_pitch_offset_rad: float = 0.1):
    """Initial guesses ``(k, 4, 4)``: ``T_init`` pre-multiplied by rotations about ``center``
    (a target-frame point [m], e.g. the centroid of the initially transformed source): every
    ``yaw_step_rad`` of yaw about +z (``2 pi / yaw_step`` guesses, the first being ``T_init``
    itself), plus ``+-roll_pitch_offset_rad`` of roll and of pitch at zero yaw (4 more; none if 0).
    Raises ``ValueError`` unless ``yaw_step_rad`` lies in ``(0, 2 pi]``.
    """
    k = int(round(2 * np.pi / float(yaw_step_rad)))
    if k < 1:
        raise ValueError(f"yaw_step_rad must lie in (0, 2 pi], got {yaw_step_rad!r}")
    T0 = jnp.asarray(T_target_source_init, jnp.float32)
    c = jnp.asarray(center, jnp.float32)
    yaws = np.arange(k) * (2 * np.pi / k)
    rpy = [(0.0, 0.0, float(y)) for y in yaws]
    a = float(roll_pitch_offset_rad)
    if a != 0.0:
        rpy += [(a, 0.0, 0.0), (-a, 0.0, 0.0), (0.0, a, 0.0), (0.0, -a, 0.0)]
    rpy = np.asarray(rpy, np.float32)
    z = jnp.zeros((rpy.shape[0],), jnp.float32)
    D = se3.from_xyz_rpy(z, z, z, rpy[:, 0], rpy[:, 1], rpy[:, 2])
    C = se3.from_rotation_translation(jnp.eye(3, dtype=jnp.float32), c)
    return C @ D @ se3.inverse(C) @ T0
