"""Multi-hypothesis ICP: ``icp`` from many initial guesses sharing one set of target grids, in
one jitted call, hypotheses one after another (``lax.map``) or as one ``vmap`` batch.

After each stage but the last, runs that left the stage close to each other (every source
point displaced less than the stage's tolerance) go on as one and share its result; one after
another, a run also stops as soon as it comes that close to where an earlier run left the
stage. The runs that go on take exactly the steps of uninterrupted ones.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from ... import se3
from ..._ops import is_traced
from ...kernel_store import stored_jit
from .. import neighbors
from ..status import Status
from ._centred import centred, centroid, uncentre_result
from ._coarse import check_coarse_matching
from ._host import check_transform, prepare_points, to_number
from ._loop import Problem, Progress, register, run_until
from ._result import IcpMultiResult, invert_result
from ._schedule import build_stage_grids, default_hypotheses, resolve_options

__all__ = ["sequential_default", "displacements", "basins", "icp_multi"]


def sequential_default() -> bool:
    """Host: run hypotheses (or stacked pairs) one after another on CPU backends, as one
    batch elsewhere."""
    return jax.default_backend() == "cpu"


def displacements(Ta, Tb, radius):
    """``(a, b)`` [m]: a bound on how far transforms ``Ta (a, 4, 4)`` and ``Tb (b, 4, 4)``
    place any point within ``radius`` [m] of the origin apart, ``angle(Ra^T Rb) * radius +
    |ta - tb|`` (no gradient)."""
    Ta, Tb = jax.lax.stop_gradient(Ta), jax.lax.stop_gradient(Tb)
    cos = (jnp.einsum("iab,jab->ij", Ta[:, :3, :3], Tb[:, :3, :3]) - 1.0) * 0.5
    angle = jnp.arccos(jnp.clip(cos, -1.0, 1.0))
    return angle * radius + jnp.linalg.norm(Ta[:, None, :3, 3] - Tb[None, :, :3, 3], axis=-1)


def basins(T, running, radius, tolerance):
    """``(k,)`` int32: for each of ``k`` transforms ``T (k, 4, 4)`` (centred frames), the first
    running one (``running (k,)`` bool) whose displacement of points within ``radius`` [m] of
    the origin (``displacements``) is below ``tolerance`` [m] among the basins' leaders (greedy
    in order, so every leader is a running transform and ``basin[j] == j``); itself for a
    stopped one."""
    close = displacements(T, T, radius) < tolerance
    k = T.shape[0]

    def step(i, basin):
        lead = (basin == jnp.arange(k)) & running & (jnp.arange(k) < i)
        hit = close[i] & lead
        return basin.at[i].set(jnp.where(running[i] & jnp.any(hit), jnp.argmax(hit), i).astype(jnp.int32))

    return jax.lax.fori_loop(0, k, step, jnp.arange(k, dtype=jnp.int32))


def _one_after_another(run, progress: Progress, stop, radius, tolerance, max_iterations: int):
    """Run each hypothesis through stage ``stop`` in turn (``lax.scan``); a run also stops
    before an iteration that starts within ``tolerance`` [m] of where an earlier run that goes
    on left the stage. Returns ``(progress (k, ...), lead (k,) int32)``: ``lead[i]`` the run
    that ``i`` stopped near, else ``i``."""
    k = progress.T.shape[0]

    def one(ends, x):  # ends: where the earlier runs left the stage, and which go on
        i, start = x
        T_ends, goes_on = ends
        near = lambda T: goes_on & (displacements(T[None], T_ends, radius)[0] < tolerance)  # noqa: E731
        out = run(start, stop, stop_when=lambda T: jnp.any(near(T)))
        early = ~out.done & (out.stage == stop) & (out.iteration < max_iterations)
        lead = jnp.where(early, jnp.argmax(near(out.T)), i).astype(jnp.int32)
        go_on = ~out.done & (out.iteration < max_iterations) & ~early
        return (T_ends.at[i].set(out.T), goes_on.at[i].set(go_on)), (out, lead)

    ends0 = (jnp.zeros_like(progress.T), jnp.zeros((k,), bool))
    _, (progress, lead) = jax.lax.scan(one, ends0, (jnp.arange(k, dtype=jnp.int32), progress))
    return progress, lead


def _through_stage(run, radius, tolerance_m, dists, max_iterations: int, sequential: bool, stop, carry):
    """Every running hypothesis through coarse stage ``stop``, then merged by basin. ``carry``:
    ``(progress (k, ...), owner (k,) int32)``, ``owner[i]`` the run whose result ``i`` takes."""
    progress, owner = carry
    k = progress.T.shape[0]
    tol = tolerance_m * dists[stop] / dists[-1]
    if sequential:
        progress, lead = _one_after_another(run, progress, stop, radius, tol, max_iterations)
    else:
        progress = jax.vmap(lambda start: run(start, stop))(progress)
        lead = jnp.arange(k, dtype=jnp.int32)
    early = lead != jnp.arange(k)
    basin = basins(progress.T, ~progress.done & (progress.iteration < max_iterations) & ~early, radius, tol)
    basin = jnp.where(early, basin[lead], basin)
    return progress._replace(done=progress.done | (basin != jnp.arange(k))), basin[owner]


def _last_stage(final, progress: Progress, merged, sequential: bool):
    """``final(start)`` for every hypothesis not ``merged`` (a merged one gets zeros: it takes
    its leader's result; its skip is real only one after another, under ``vmap`` the cond
    computes both sides)."""
    shapes = jax.eval_shape(final, jax.tree_util.tree_map(lambda x: x[0], progress))
    dummy = lambda: jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), shapes)  # noqa: E731
    f = lambda m, start: jax.lax.cond(m, dummy, lambda: final(start))  # noqa: E731
    if sequential:
        return jax.lax.map(lambda a: f(*a), (merged, progress))
    return jax.vmap(f)(merged, progress)


@stored_jit(static_argnames=("max_iterations", "cell_capacity", "table_sizes", "coarse_matching", "sequential"))
def multi_padded(source, source_count, target, target_count, hypotheses, dists, epsilon, final_epsilon,
                 min_inliers, basin_tolerance_m, *, max_iterations: int, cell_capacity: int,
                 table_sizes: tuple[int, ...], coarse_matching: str, sequential: bool = False) -> IcpMultiResult:
    """The jitted body of ``icp_multi`` on padded clouds (arguments as ``icp_padded``;
    ``hypotheses (k, 4, 4)``, ``basin_tolerance_m`` at the floor distance)."""
    source, target, hyps_c, uncentre = centred(source, source_count, target, target_count, hypotheses)
    grids = build_stage_grids(target, target_count, dists, table_sizes, cell_capacity)
    problem = Problem(grids, dists, epsilon, final_epsilon, min_inliers, coarse_matching, sequential)
    run = partial(run_until, problem, source, source_count, max_iterations=max_iterations)
    k = hyps_c.shape[0]
    radius = jnp.sqrt(jnp.max(jnp.where(jnp.arange(source.shape[0]) < source_count,
                                        jnp.sum(jax.lax.stop_gradient(source) ** 2, -1), 0.0)))
    progress = Progress(hyps_c, jnp.zeros((k,), jnp.int32), jnp.zeros((k,), jnp.int32), jnp.zeros((k,), bool),
                        jnp.full((k,), Status.MAX_ITERATIONS, jnp.int32))
    stage = partial(_through_stage, run, radius, basin_tolerance_m, dists, max_iterations, sequential)
    progress, owner = jax.lax.fori_loop(0, dists.shape[0] - 1, stage, (progress, jnp.arange(k, dtype=jnp.int32)))
    # every run is past the coarse stages: only the last stage's loop is built
    final = partial(register, problem, source, source_count, target, max_iterations=max_iterations,
                    run_coarse=False)
    merged = owner != jnp.arange(k)
    cands = _last_stage(final, progress, merged, sequential)
    iterations_run = jnp.where(merged, progress.iteration, cands.num_iterations).astype(jnp.int32)
    cands = jax.tree_util.tree_map(lambda a: a[owner] if a.ndim else a, cands)
    cands = uncentre_result(cands, uncentre)
    # every field batched along k (a constant field comes out of vmap unbatched)
    cands = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (k,)) if a.ndim == 0 else a, cands)
    scores = cands.num_close.astype(jnp.float32) - cands.rmse / dists[-1]
    best = jnp.argmax(scores).astype(jnp.int32)
    best_res = jax.tree_util.tree_map(lambda a: a[best], cands)
    return IcpMultiResult(best_res, cands, best, scores, hypotheses, owner, iterations_run)


def icp_multi(source, target, T_target_source_init, hypotheses=None, *, resolution: float,
              yaw_step_rad: float = np.pi / 6, roll_pitch_offset_rad: float = 0.1,
              max_correspondence_distance: float | None = None,
              min_correspondence_distance: float | None = None, shrink_factor: float = 0.5,
              transformation_epsilon: float | None = None, max_iterations: int = 100,
              cell_capacity: int = 8, min_inliers: int = 6, swap_larger: bool = True,
              coarse_matching: str = "centroid", source_count=None,
              target_count=None, sequential: bool | None = None,
              basin_tolerance_m: float | None = None) -> IcpMultiResult:
    """Multi-hypothesis ICP: ``icp`` from many initial guesses sharing one set of target
    grids, in one jitted call; returns the best by the number of source points within a
    quarter of the floor distance, ties broken by inlier rmse (``score = num_close - rmse /
    d_floor``), plus every candidate (``IcpMultiResult``).

    ``hypotheses``: ``(k, 4, 4)`` absolute initial guesses ``T_target_source``; by default
    ``default_hypotheses(T_target_source_init, centroid of T_init * source, yaw_step_rad,
    roll_pitch_offset_rad)`` (12 yaws + 4 roll/pitch offsets = 16). Other arguments as ``icp``.

    ``basin_tolerance_m`` [m] at the floor distance, scaled with each stage's correspondence
    distance (``None``: a quarter of the floor distance, half a voxel at the defaults; 0 turns
    merging off): after each stage but the last, hypotheses whose transforms displace every
    source point by less than the stage's tolerance from an earlier running hypothesis's
    (``angle * max source radius + translation difference``) are merged into it: only one of
    them runs on, and each reports that run's result (``basin``). Run one after another, a
    hypothesis also merges as soon as it comes that close to where an earlier one left the
    stage.

    ``sequential``: run the hypotheses one after another (``lax.map``; each stops at its own
    convergence) instead of as one ``vmap`` batch; default ``sequential_default()``. The two
    agree to float rounding on converged candidates (batched float arithmetic differs in the
    last bits, which can send a non-converging candidate elsewhere).

    Raises ``ValueError`` on bad shapes or options, as ``icp``, and on a negative or
    non-numeric ``basin_tolerance_m``.
    """
    check_coarse_matching(coarse_matching)
    dists, eps = resolve_options(resolution, max_correspondence_distance, min_correspondence_distance,
                                 shrink_factor, transformation_epsilon, max_iterations, cell_capacity)
    T0 = check_transform(T_target_source_init, "T_target_source_init")
    s, sc, s_host = prepare_points(source, source_count, "source")
    t, tc, t_host = prepare_points(target, target_count, "target")
    hyps = _hypotheses(hypotheses, T0, s, sc, yaw_step_rad, roll_pitch_offset_rad)
    swap = swap_larger and s_host is not None and t_host is not None and s_host > t_host
    if swap:
        s, sc, t, tc = t, tc, s, sc
        hyps = se3.inverse(hyps)
    tol = float(dists[-1]) / 4.0 if basin_tolerance_m is None else to_number(basin_tolerance_m)
    if not (np.isfinite(tol) and tol >= 0):
        raise ValueError(f"basin_tolerance_m must be a finite number >= 0 [m], got {basin_tolerance_m!r}")
    out = multi_padded(s, sc, t, tc, hyps, dists, eps, eps * 0.01, jnp.asarray(min_inliers, jnp.int32),
                       jnp.float32(tol), max_iterations=int(max_iterations), cell_capacity=int(cell_capacity),
                       table_sizes=neighbors.level_table_sizes(t.shape[0], np.asarray(dists)),
                       coarse_matching=coarse_matching,
                       sequential=sequential_default() if sequential is None else bool(sequential))
    if swap:
        out = IcpMultiResult(invert_result(out.best), invert_result(out.candidates), out.best_index,
                             out.scores, se3.inverse(out.hypotheses), out.basin, out.num_iterations_run)
    return out


def _hypotheses(hypotheses, T0, source, source_count, yaw_step_rad, roll_pitch_offset_rad):
    """``(k, 4, 4)`` float32: ``hypotheses`` checked, or ``default_hypotheses`` about the
    centroid of the padded ``source`` under ``T0``."""
    if hypotheses is None:
        center = se3.transform_points(T0, centroid(source, source_count)[None])[0]
        return default_hypotheses(T0, center, yaw_step_rad, roll_pitch_offset_rad)
    hyps = jnp.asarray(hypotheses, jnp.float32)
    if hyps.ndim != 3 or hyps.shape[-2:] != (4, 4):
        raise ValueError(f"hypotheses: expected shape (k, 4, 4), got {hyps.shape}")
    if not is_traced(hypotheses):
        se3.check_rigid(np.asarray(hypotheses), "hypotheses")
    return hyps
