"""Point statistics of a registration at a given transform, without iterating (Open3D's
``registration.evaluate_registration``): how many source points have a target point within a
correspondence distance, and how far those are.

``icp`` reports the same statistics at its own result (at its floor distance); this measures
them at any transform, e.g. one from the dense alignment or a hand-made guess, so that results
of different methods compare on one yardstick.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from . import neighbors
from .. import se3
from .._ops import bucket_capacity, count_true, to_device
from ..kernel_store import stored_jit
from ._icp import pad_points_host

__all__ = ["RegistrationStats", "evaluate_registration"]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class RegistrationStats:
    """``evaluate_registration``'s result (all ``()`` arrays; batched under ``vmap``).

    - ``num_inliers``: int32, source points with a target point within the distance.
    - ``rmse``: float32 [m], root mean square distance of the inliers to their nearest target
      point (NaN without inliers; Open3D reports 0 there).
    - ``fitness``: float32, ``num_inliers / source points`` (0 for no source points).
    - ``grid_overflow``: int32, target points the search grid dropped (0: the search was exact).
    """

    num_inliers: jax.Array
    rmse: jax.Array
    fitness: jax.Array
    grid_overflow: jax.Array


@stored_jit(static_argnames=("table_size", "cell_capacity"))
def _evaluate(source, source_count, target, target_count, T, distance, *, table_size, cell_capacity):
    grid = neighbors.build_grid(target, target_count, distance, table_size=table_size,
                                cell_capacity=cell_capacity)
    q = source @ T[:3, :3].T + T[:3, 3]
    d2, index, _ = neighbors.nearest_with_points(grid, q, count=source_count)
    valid = jnp.arange(q.shape[0]) < source_count
    inlier = valid & (index >= 0) & (d2 <= distance * distance)
    n = count_true(inlier)
    rmse = jnp.sqrt(jnp.sum(jnp.where(inlier, d2, 0.0)) / n.astype(jnp.float32))
    fitness = n.astype(jnp.float32) / jnp.maximum(source_count, 1).astype(jnp.float32)
    return RegistrationStats(num_inliers=n, rmse=jnp.where(n > 0, rmse, jnp.nan), fitness=fitness,
                             grid_overflow=grid.overflow[0])


def _capacity(points, at_least: int | None) -> int | None:
    """The padded rows of host ``points``: ``None`` (their own bucket) or the bucket of ``at_least``
    rows when that is larger."""
    if at_least is None:
        return None
    return bucket_capacity(max(int(at_least), int(np.shape(points)[0]) if np.ndim(points) == 2 else 0))


def evaluate_registration(source, target, T_target_source, max_correspondence_distance: float, *,
                          source_count=None, target_count=None, cell_capacity: int = 8,
                          source_capacity: int | None = None,
                          target_capacity: int | None = None) -> RegistrationStats:
    """Correspondence statistics of ``source (Ns, 3)`` placed by ``T_target_source (4, 4)``
    against ``target (Nt, 3)`` [m]: the nearest target point of each source point counts when
    it lies within ``max_correspondence_distance`` [m] (exact unless ``grid_overflow > 0``).

    NumPy inputs are checked (shapes, finite values, a rigid transform; ``ValueError`` naming
    the argument), padded to ``bucket_capacity`` and evaluated about the target's centroid in
    float64 on the host before the float32 search (map coordinates can be kilometres from the
    origin); JAX arrays (e.g. under ``jit`` / ``vmap``) are used as given, with optional
    ``*_count`` valid-row counts. ``source_capacity`` / ``target_capacity`` (host inputs): pad
    to the bucket of at least that many rows, so that subsets of one pair's clouds share the
    whole clouds' compiled program.
    """
    d = float(max_correspondence_distance)
    if not (np.isfinite(d) and d > 0):
        raise ValueError(f"max_correspondence_distance must be a positive number of metres, got "
                         f"{max_correspondence_distance!r}")
    if int(cell_capacity) < 1:
        raise ValueError(f"cell_capacity must be >= 1, got {cell_capacity!r}")
    host = not any(isinstance(x, jax.Array)  # tracers included
                   for x in (source, target, T_target_source, source_count, target_count))
    if host:
        T = se3.check_rigid(T_target_source, "T_target_source").astype(np.float64)
        s, ns = pad_points_host(source, _capacity(source, source_capacity), "source")
        t, nt = pad_points_host(target, _capacity(target, target_capacity), "target")
        src = np.asarray(source, np.float64).reshape(-1, 3)
        tgt = np.asarray(target, np.float64).reshape(-1, 3)
        ref = tgt.mean(0) if nt else np.zeros(3)
        s[:ns] = src @ T[:3, :3].T + (T[:3, 3] - ref)  # placed and centred in float64
        t[:nt] = tgt - ref
        T_eval, source_count, target_count = np.eye(4, dtype=np.float32), np.int32(ns), np.int32(nt)
    else:
        s, t = jnp.asarray(source, jnp.float32), jnp.asarray(target, jnp.float32)
        T_eval = jnp.asarray(T_target_source, jnp.float32)
        source_count = s.shape[0] if source_count is None else source_count
        target_count = t.shape[0] if target_count is None else target_count
    table = neighbors.grid_table_size(t.shape[0], 4.0)
    return _evaluate(s, to_device(source_count, np.int32), t, to_device(target_count, np.int32),
                     T_eval, to_device(d, np.float32), table_size=table, cell_capacity=int(cell_capacity))
