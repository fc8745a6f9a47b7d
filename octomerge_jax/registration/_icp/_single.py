"""ICP of one pair (thesis Alg. 3): ``icp`` on host or JAX arrays, ``icp_padded`` on padded
clouds, ``icp_padded_stack`` over stacked pairs of one capacity bucket."""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from ... import se3
from ..._ops import is_traced
from ...kernel_store import stored_jit
from ._centred import centred, uncentre_result
from ._coarse import check_coarse_matching
from ._host import as_argument, check_transform, prepare_points
from ._loop import IcpPath, Problem, register, register_with_path, start_at
from ._result import IcpResult, invert_result
from ._schedule import build_stage_grids, resolve_options, table_sizes as stage_table_sizes

__all__ = ["solve_padded", "icp_padded", "icp_padded_stack", "icp", "icp_with_path"]


@stored_jit(static_argnames=("max_iterations", "cell_capacity", "table_sizes", "coarse_matching", "two_phase"))
def solve_padded(source, source_count, target, target_count, T_target_source_init, dists, epsilon,
                 final_epsilon, min_inliers, *, max_iterations, cell_capacity, table_sizes,
                 coarse_matching, two_phase) -> IcpResult:
    """The jitted body of ``icp_padded`` (arguments as there, all given)."""
    source, target, T_init, uncentre = centred(source, source_count, target, target_count, T_target_source_init)
    grids = build_stage_grids(target, target_count, dists, table_sizes, cell_capacity)
    problem = Problem(grids, dists, epsilon, final_epsilon, min_inliers, coarse_matching, two_phase)
    r = register(problem, source, source_count, target, start_at(T_init), max_iterations=max_iterations)
    return uncentre_result(r, uncentre)


@partial(jax.jit, static_argnames=("max_iterations", "cell_capacity", "table_sizes", "coarse_matching",
                                   "two_phase"))
def solve_padded_with_path(source, source_count, target, target_count, T_target_source_init, dists, epsilon,
                           final_epsilon, min_inliers, *, max_iterations, cell_capacity, table_sizes,
                           coarse_matching, two_phase) -> tuple[IcpResult, IcpPath]:
    """``solve_padded`` that also returns the run's ``IcpPath`` (uncentred, as the result)."""
    source, target, T_init, uncentre = centred(source, source_count, target, target_count, T_target_source_init)
    grids = build_stage_grids(target, target_count, dists, table_sizes, cell_capacity)
    problem = Problem(grids, dists, epsilon, final_epsilon, min_inliers, coarse_matching, two_phase)
    r, path = register_with_path(problem, source, source_count, target, start_at(T_init),
                                 max_iterations=max_iterations)
    return uncentre_result(r, uncentre), path._replace(T=uncentre(path.T))


def icp_padded(source, source_count, target, target_count, T_target_source_init, distances_m,
               epsilon, final_epsilon=None, min_inliers=6, *, max_iterations: int = 100,
               cell_capacity: int = 8, table_sizes: tuple[int, ...] | None = None,
               coarse_matching: str = "centroid", two_phase: bool = True) -> IcpResult:
    """ICP on padded clouds, jitted.

    Traced: ``source (Ns, 3)``, ``target (Nt, 3)`` float32 [m] whose rows ``>= *_count`` are
    padding, ``T_target_source_init (4, 4)``, the stage distances ``distances_m (s,)`` [m]
    (``stage_distances``), ``epsilon`` (stage change threshold, sum of ``|dT|``),
    ``final_epsilon`` (threshold at the last stage, default ``epsilon / 100``) and
    ``min_inliers``. Static: ``max_iterations``, ``cell_capacity``, ``table_sizes`` (default
    ``neighbors.level_table_sizes(Nt, distances_m)``, needs concrete distances),
    ``coarse_matching`` (see ``icp``) and ``two_phase`` (the nearest-neighbour search,
    ``neighbors.nearest_with_points``). Pure and ``vmap``-able over stacked pairs of one bucket
    (pass ``table_sizes`` then, and ``two_phase=False``: same results, and under ``vmap`` the
    one-phase search is the cheaper). Raises ``ValueError`` on a bad ``coarse_matching``."""
    check_coarse_matching(coarse_matching)
    ts = stage_table_sizes(target.shape[0], distances_m, table_sizes)
    epsilon = as_argument(epsilon, np.float32)
    final_epsilon = epsilon * np.float32(0.01) if final_epsilon is None else as_argument(final_epsilon, np.float32)
    return solve_padded(source, source_count, target, target_count,
                        as_argument(T_target_source_init, np.float32), as_argument(distances_m, np.float32),
                        epsilon, final_epsilon, as_argument(min_inliers, np.int32),
                        max_iterations=int(max_iterations), cell_capacity=int(cell_capacity), table_sizes=ts,
                        coarse_matching=coarse_matching, two_phase=bool(two_phase))


@partial(jax.jit, static_argnames=("max_iterations", "cell_capacity", "table_sizes", "coarse_matching",
                                   "sequential"))
def icp_padded_stack(sources, source_counts, targets, target_counts, T_inits, distances_m, epsilon,
                     final_epsilon, min_inliers, *, max_iterations: int, cell_capacity: int,
                     table_sizes: tuple[int, ...], coarse_matching: str, sequential: bool) -> IcpResult:
    """``icp_padded`` over stacked pairs of one bucket (leading axis ``p`` on the clouds,
    counts and ``T_inits``; the rest shared), as one ``IcpResult`` with leading axis ``p``:
    pair after pair (``lax.map``, ``sequential=True``: each stops at its own convergence) or
    as one ``vmap`` batch (``sequential_default()`` picks by backend)."""
    def one(s, sc, t, tc, T):
        return solve_padded(s, sc, t, tc, T, distances_m, epsilon, final_epsilon, min_inliers,
                            max_iterations=max_iterations, cell_capacity=cell_capacity,
                            table_sizes=table_sizes, coarse_matching=coarse_matching, two_phase=sequential)

    xs = (sources, source_counts, targets, target_counts, T_inits)
    if sequential:
        return jax.lax.map(lambda a: one(*a), xs)
    return jax.vmap(one)(*xs)


def icp(source, target, T_target_source_init, *, resolution: float,
        max_correspondence_distance: float | None = None,
        min_correspondence_distance: float | None = None, shrink_factor: float = 0.5,
        transformation_epsilon: float | None = None, max_iterations: int = 100,
        cell_capacity: int = 8, min_inliers: int = 6, swap_larger: bool = True,
        coarse_matching: str = "centroid", source_count=None, target_count=None,
        final_transformation_epsilon: float | None = None) -> IcpResult:
    """Register ``source`` to ``target`` by point-to-point ICP (thesis Alg. 3, eq. 3.18; Besl &
    McKay 1992): returns ``IcpResult`` whose ``T_target_source`` maps source points into the
    target frame.

    ``source (Ns, 3)``, ``target (Nt, 3)`` [m]: NumPy arrays are validated and padded to
    ``bucket_capacity``; JAX arrays (e.g. inside ``jit``/``grad``/``vmap``) are used as given,
    with optional ``*_count`` valid-row counts. ``T_target_source_init (4, 4)``.
    ``resolution`` [m] sets the defaults: correspondence distances ``10 res -> 2 res``
    halving (``max_correspondence_distance``, ``min_correspondence_distance`` [m],
    ``shrink_factor``), ``transformation_epsilon`` ``res / 60`` (sum of absolute entry changes
    of T; a stage ends below it) and ``final_transformation_epsilon`` ``transformation_epsilon
    / 100`` (ICP ends below it at the last stage; a traced argument: changing it compiles
    nothing). ``max_iterations`` bounds the correspondence searches; fewer than ``min_inliers``
    correspondences stop ICP (``Status.TOO_FEW_INLIERS``). ``cell_capacity``: slots per cell
    of the hashed grids.

    ``coarse_matching``: ``"centroid"`` (default) matches coarse stages to the target's
    voxel-grid centroids at ``d / 2`` (a smoothed target, like the thesis code's VoxelGrid
    downsampling: a wider basin of convergence); ``"nearest"`` matches the exact nearest target
    point whenever one lies within the floor distance (the unsmoothed fixed point, a
    narrower basin); ``"symmetric"`` is ``"centroid"`` with the source's voxel-grid centroids at
    ``d / 2`` as the queries. Coarse stages of ``"centroid"`` and ``"nearest"`` query every
    k-th source point (k <= 4, at least 2048 queries kept). The last stage always matches the
    exact nearest target point to every source point.

    ``swap_larger``: the thesis uses the larger cloud as the model (target); with host counts,
    a larger source is swapped with the target and the result inverted (``swapped``).

    Differentiable w.r.t. the point coordinates: the derivative of the fixed point by the
    implicit function theorem (``dT*/dT_init = 0``). Raises ``ValueError`` on bad shapes,
    non-finite points, a non-rigid ``T_target_source_init`` or a bad option.
    """
    dists, eps = resolve_options(resolution, max_correspondence_distance, min_correspondence_distance,
                                 shrink_factor, transformation_epsilon, max_iterations, cell_capacity)
    T0 = check_transform(T_target_source_init, "T_target_source_init")
    s, sc, s_host = prepare_points(source, source_count, "source")
    t, tc, t_host = prepare_points(target, target_count, "target")
    kw = dict(max_iterations=int(max_iterations), cell_capacity=int(cell_capacity),
              coarse_matching=coarse_matching)
    feps = final_transformation_epsilon
    if feps is not None and not is_traced(feps) and not float(feps) > 0:
        raise ValueError(f"final_transformation_epsilon must be positive, got {feps!r}")
    if swap_larger and s_host is not None and t_host is not None and s_host > t_host:
        T0_inv = se3.inverse(T0) if is_traced(T0) else np.linalg.inv(np.float64(T0)).astype(np.float32)
        r = icp_padded(t, tc, s, sc, T0_inv, dists, eps, feps, min_inliers=min_inliers, **kw)
        return invert_result(r)
    return icp_padded(s, sc, t, tc, T0, dists, eps, feps, min_inliers=min_inliers, **kw)


def icp_with_path(source, target, T_target_source_init, *, resolution: float, **options) -> tuple[IcpResult, IcpPath]:
    """``icp`` (same arguments, host clouds) that also returns every iteration of the run as
    an ``IcpPath``: ``path.T[k]`` the transform after iteration ``k + 1`` (source into target
    frame, inverted back when the clouds were swapped), rows ``< result.num_iterations``
    recorded; its last recorded row is ``result.T_target_source``. The iterations are those of
    ``icp`` with the same arguments (recording changes no iterate); for convergence figures
    (``pipeline.icp_trace``). Raises ``ValueError`` as ``icp``."""
    o = dict(max_correspondence_distance=None, min_correspondence_distance=None, shrink_factor=0.5,
             transformation_epsilon=None, max_iterations=100, cell_capacity=8, min_inliers=6, swap_larger=True,
             coarse_matching="centroid")
    unknown = set(options) - set(o)
    if unknown:
        raise ValueError(f"icp_with_path: unknown option(s) {sorted(unknown)}")
    o.update(options)
    dists, eps = resolve_options(resolution, o["max_correspondence_distance"], o["min_correspondence_distance"],
                                 o["shrink_factor"], o["transformation_epsilon"], o["max_iterations"],
                                 o["cell_capacity"])
    check_coarse_matching(o["coarse_matching"])
    T0 = np.asarray(check_transform(T_target_source_init, "T_target_source_init"), np.float32)
    s, sc, s_host = prepare_points(np.asarray(source), None, "source")
    t, tc, t_host = prepare_points(np.asarray(target), None, "target")
    swap = bool(o["swap_larger"]) and s_host > t_host
    if swap:
        s, sc, t, tc = t, tc, s, sc
        T0 = np.linalg.inv(np.float64(T0)).astype(np.float32)
    eps = as_argument(eps, np.float32)
    r, path = solve_padded_with_path(
        s, sc, t, tc, as_argument(T0, np.float32), as_argument(dists, np.float32), eps, eps * np.float32(0.01),
        as_argument(o["min_inliers"], np.int32), max_iterations=int(o["max_iterations"]),
        cell_capacity=int(o["cell_capacity"]), table_sizes=stage_table_sizes(t.shape[0], dists, None),
        coarse_matching=o["coarse_matching"], two_phase=True)
    if swap:
        r = invert_result(r)
        path = path._replace(T=se3.inverse(path.T))
    # the last iterate is the result: the same value, uncentred (and inverted) once, not per row
    return r, path._replace(T=path.T.at[jnp.maximum(r.num_iterations - 1, 0)].set(r.T_target_source))
