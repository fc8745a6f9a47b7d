"""The dense alignment's solver: coarse-to-fine minimisation of the alignment loss over an
se(3) increment, the guard restart, and the status checks.

The unknown is a 6-vector ``z``, a right increment on se(3) about the centroid ``c`` of map
2's sample points (``pose_from_increment``): translation [m] and rotation scaled to arc length
at their RMS radius [m]. ``z`` is minimised per level (L-BFGS, Nocedal & Wright ch. 7) from
coarse to fine, the levels in one ``lax.scan`` over the stacked level data, all under ``jit``;
``vmap`` runs many initial guesses (or many stacked problems) at once. A level stops on a
small gradient, on ``patience`` steps shorter than ``xtol`` (scaled to the level's cell) or
when no step along the gradient lowers the loss (a minimum at a kink of the
piecewise-trilinear loss). A last guard step compares the finest loss at the end of the path
with the start's and, if the end is worse, solves the finest level again from the start
(``AlignResult.restarted``).

**Status** (``AlignResult.status``, a ``Status`` code): ``CONVERGED``; ``MAX_ITERATIONS``, the
finest level hit ``maxiter``; ``POOR_AGREEMENT``, fewer than ``min_agreement`` of map 2's
occupied sample points that land in map 1's known space land next to map 1's surfaces (one of
the 8 voxels they interpolate from is occupied); ``LOW_OVERLAP``, fewer than ``min_overlap`` of
map 2's occupied points land in map 1's known space; ``NOT_FINITE``, a non-finite loss or
transform. Only ``CONVERGED`` sets ``converged``. The checks refute a wrong pose by map 2's
surfaces landing in map 1's *free* space, so they need free-space evidence.
"""

from __future__ import annotations

import dataclasses
from functools import partial
from typing import Literal, NamedTuple, get_args

import jax
import jax.numpy as jnp
import numpy as np

from ..._ops import to_device
from ...kernel_store import stored_jit
from ...map import OccupancyMap
from ...se3 import check_rigid_transform
from ..status import Status, usable_mask
from ._jaxopt import minimize_jaxopt
from ._lbfgs import minimize
from ._loss import pair_loss_and_checks
from ._problem import AlignProblem, both_at, pose_from_increment, prepare_alignment

__all__ = ["AlignResult", "Solver", "align_dense", "best_result", "solve_alignment", "solve_alignment_batch"]

Solver = Literal["lbfgs", "jaxopt"]  # the minimiser: _lbfgs.minimize or _jaxopt.minimize_jaxopt


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class AlignResult:
    """Result of ``align_dense`` / ``solve_alignment`` (arrays; batched under ``vmap``).

    - ``T_1_2``: ``(4, 4)`` float32, maps points of map 2's frame into map 1's.
    - ``loss``: ``()`` float32, ``problem_loss`` at the finest level (in [-1, 1], lower is better).
    - ``loss_history``: ``(L, maxiter + 1)`` float32, the loss per level (coarse to fine) at
      the start and after every iteration; NaN after a level stopped.
    - ``iterations``: ``(L,)`` int32 solver iterations per level; ``num_iterations`` ``()`` total.
    - ``overlap``: ``()`` float32, share of map 2's occupied sample weight landing in map 1's
      known space (finest level).
    - ``agreement``: ``()`` float32, of that, the share landing next to map 1's occupied space
      (one of the 8 voxels the point interpolates from is occupied).
    - ``grad_norm``: ``()`` float32, gradient norm at the end of the finest level.
    - ``status``: ``()`` int32, a ``Status`` code (module docstring); ``converged``: ``()``
      bool, ``status == Status.CONVERGED``.
    - ``restarted``: ``()`` bool, the coarse-to-fine path ended with a higher finest-level loss
      than the initial guess had, so the finest level was solved again from the guess (its
      ``loss_history`` / ``iterations`` row is that solve's; ``num_iterations`` counts both).
    """

    T_1_2: jax.Array
    loss: jax.Array
    loss_history: jax.Array
    iterations: jax.Array
    num_iterations: jax.Array
    overlap: jax.Array
    agreement: jax.Array
    grad_norm: jax.Array
    status: jax.Array
    converged: jax.Array
    restarted: jax.Array


class _Options(NamedTuple):
    """The traced options of a solve (changing them does not recompile)."""

    tol: jax.Array            # () float32, gradient norm of the loss w.r.t. z [1/m]
    xtol: jax.Array           # () float32 [m], step length at the finest level (x 2^k coarser)
    max_step: jax.Array       # () float32 [m], trust region: norm of one level's increment z
    min_overlap: jax.Array    # () float32, status threshold
    min_agreement: jax.Array  # () float32, status threshold
    start_level: jax.Array    # () int32, index of the first level solved


class _LevelOutcome(NamedTuple):
    """One level's solve (a scan output row)."""

    history: jax.Array     # (maxiter + 1,) float32 loss per iteration, NaN after the last
    iterations: jax.Array  # () int32
    converged: jax.Array   # () bool, converged within the trust region
    grad_norm: jax.Array   # () float32


def _objective(z, pair, T_start, center, radius):
    """The level's loss at the pose ``z`` makes of ``T_start``, with the status checks'
    ``(overlap, agreement)`` there as the auxiliary output (``pair_loss_and_checks``)."""
    return pair_loss_and_checks(pair, pose_from_increment(T_start, z, center, radius))


def _solve_level(problem: AlignProblem, opts: _Options, maxiter: int, solver: Solver, T, i, active=True):
    """Minimise level ``i`` (traced) from ``T``: ``(pose, _LevelOutcome, (loss, overlap,
    agreement) at the solve's last iterate)``. An inactive solve (``tol = inf``) stops at its
    first evaluation, so its figures are those of ``T`` itself, also as one member of a ``vmap``
    batch (where a ``cond`` would run both branches for every member)."""
    pair = both_at(problem, i)
    cell = problem.map1.resolution / problem.scale[i]  # this level's cell size [m]
    args = (pair, T, problem.center2, problem.radius)
    tol, xtol = jnp.where(active, opts.tol, jnp.inf), opts.xtol / problem.scale[i]
    if solver == "jaxopt":
        res = minimize_jaxopt(_objective, jnp.zeros(6, jnp.float32), *args, maxiter=maxiter, tol=tol, xtol=xtol,
                              has_aux=True)
    else:
        res = minimize(_objective, jnp.zeros(6, jnp.float32), *args, maxiter=maxiter, tol=tol, xtol=xtol,
                       init_step=0.5 * cell, has_aux=True)
    # trust region: a level may move the pose by at most max_step (norm of z, metres)
    n = jnp.linalg.norm(res.x)
    z = res.x * jnp.minimum(1.0, opts.max_step / jnp.maximum(n, 1e-12))
    T_new = pose_from_increment(T, z, problem.center2, problem.radius)
    return T_new, _LevelOutcome(res.history, res.num_iterations, res.converged & (n <= opts.max_step),
                                res.grad_norm), (res.value, *res.aux)


def _skip_level(maxiter: int, T, i):
    """A level before ``start_level``: the pose passes through, the scores are NaN."""
    nan = jnp.full((maxiter + 1,), jnp.nan, jnp.float32)
    scores = (jnp.float32(jnp.nan),) * 3
    return T, _LevelOutcome(nan, jnp.int32(0), jnp.bool_(True), jnp.float32(jnp.nan)), scores


def _level_step(problem: AlignProblem, opts: _Options, maxiter: int, solver: Solver, T0, carry, k):
    """Scan step ``k`` of ``_solve``, one solve call each, so the program holds the loss once
    (``docs/design.md``, "Coarse to fine: start level and guard"): step 0 scores the start at
    the finest level (a solve stopped at its first evaluation); steps ``1..L`` solve the levels
    ``0..L-1`` (those before ``start_level`` skipped); step ``L + 1`` scores the path's end and
    decides the guard (the end scores worse than the start: a restart); step ``L + 2`` solves the
    finest level again from the start on a restart (otherwise it stops at its first evaluation and
    its pose is dropped), and step ``L + 3`` scores the result. Only the start level skips a step:
    a skip that depended on a member's restart would make the ``cond`` batched under ``vmap``,
    which runs both branches at every step. ``carry``: ``(T, start loss, scores (loss, overlap,
    agreement), restart)``. Returns ``(carry, outcome)``."""
    T, start_loss, scores, restart = carry
    last = problem.num_levels - 1
    level_step = (k >= 1) & (k <= last + 1)
    guard, again, end = k == last + 2, k == last + 3, k == last + 4
    scoring = (k == 0) | guard | end
    # the restart's solve is gated by its activity (tol), not by the skip (see the docstring)
    skip = level_step & (k - 1 < opts.start_level)
    level = jnp.where(level_step, k - 1, last)
    solve = partial(_solve_level, problem, opts, maxiter, solver, active=~scoring & (~again | restart))
    T_out, outcome, found = jax.lax.cond(skip, partial(_skip_level, maxiter), solve,
                                         jnp.where((k == 0) | again, T0, T), level)
    start_loss = jnp.where(k == 0, found[0], start_loss)
    restart = jnp.where(guard, (opts.start_level < last) & jnp.isfinite(start_loss) & ~(found[0] <= start_loss),
                        restart)
    scores = tuple(jnp.where(scoring, a, b) for a, b in zip(found, scores))  # scoring steps never skip
    T = jnp.where(level_step | (again & restart), T_out, T)
    return (T, start_loss, scores, restart), outcome


def _status(loss, T, overlap, agree, converged, opts: _Options):
    """The ``Status`` code (int32) of a solve's end (module docstring)."""
    finite = jnp.isfinite(loss) & jnp.all(jnp.isfinite(T))
    return jnp.where(~finite, int(Status.NOT_FINITE),
           jnp.where(overlap < opts.min_overlap, int(Status.LOW_OVERLAP),
           jnp.where(agree < opts.min_agreement, int(Status.POOR_AGREEMENT),
           jnp.where(~converged, int(Status.MAX_ITERATIONS), int(Status.CONVERGED))))).astype(jnp.int32)


def _solve(problem: AlignProblem, T_init, opts: _Options, maxiter: int, solver: Solver) -> AlignResult:
    """Coarse-to-fine minimisation (one compiled step, scanned over the start's score, the
    levels, the guard and its restart, ``_level_step``), then the status."""
    T0 = jnp.asarray(T_init, jnp.float32)
    last = problem.num_levels - 1
    nan = jnp.float32(jnp.nan)
    step = partial(_level_step, problem, opts, maxiter, solver, T0)
    (T, _, (loss, overlap, agree), restart), rows = jax.lax.scan(
        step, (T0, nan, (nan, nan, nan), jnp.bool_(False)), jnp.arange(last + 5))
    num_iterations = jnp.sum(rows.iterations)  # the scoring and skipped steps' rows: 0
    # the level rows; a restart's solve replaces the finest level's
    rows = jax.tree_util.tree_map(lambda a: a[1:last + 2].at[last].set(jnp.where(restart, a[last + 3], a[last + 1])),
                                  rows)
    status = _status(loss, T, overlap, agree, rows.converged[-1], opts)
    return AlignResult(T_1_2=T, loss=loss, loss_history=rows.history, iterations=rows.iterations,
                       num_iterations=num_iterations, overlap=overlap, agreement=agree,
                       grad_norm=rows.grad_norm[-1], status=status, converged=status == int(Status.CONVERGED),
                       restarted=restart)


@stored_jit(static_argnames=("maxiter", "solver"))
def _solve_jit(problem, T_init, opts, *, maxiter, solver):
    return _solve(problem, T_init, opts, maxiter, solver)


@partial(jax.jit, static_argnames=("maxiter", "solver"))
def _solve_many_jit(problem, T_inits, opts, *, maxiter, solver):
    return jax.vmap(lambda T: _solve(problem, T, opts, maxiter, solver))(T_inits)


@partial(jax.jit, static_argnames=("maxiter", "solver"))
def _solve_pairs_jit(problems, T_inits, opts, *, maxiter, solver):
    return jax.vmap(lambda p, T: _solve(p, T, opts, maxiter, solver))(problems, T_inits)


def _options(problem, maxiter, tol, xtol, max_step, min_overlap, min_agreement, start_level,
             solver) -> _Options:
    """Validate the solve options on the host (``ValueError`` naming the argument)."""
    if int(maxiter) < 1:
        raise ValueError(f"maxiter must be >= 1, got {maxiter}")
    if solver not in get_args(Solver):
        raise ValueError(f"solver must be one of {get_args(Solver)}, got {solver!r}")
    if isinstance(start_level, bool) or not isinstance(start_level, (int, np.integer)) or not (
            0 <= start_level < problem.num_levels):
        raise ValueError(f"start_level must be an int in 0..{problem.num_levels - 1} (an index into the "
                         f"problem's levels {problem.levels}), got {start_level!r}")
    for name, v in dict(tol=tol, max_step=max_step, min_overlap=min_overlap,
                        min_agreement=min_agreement).items():
        if not (np.isfinite(v) and v >= 0):
            raise ValueError(f"{name} must be a non-negative number, got {v!r}")
    xtol = problem.map1.resolution / 100.0 if xtol is None else float(xtol)
    return _Options(*(to_device(v, np.float32) for v in (tol, xtol, max_step, min_overlap, min_agreement)),
                    to_device(start_level, np.int32))


def solve_alignment(problem: AlignProblem, T_1_2_init, *, maxiter: int = 30, tol: float = 1e-4,
                    xtol: float | None = None, max_step: float = 3.0,
                    min_overlap: float = 0.15, min_agreement: float = 0.85,
                    start_level: int = 0, solver: Solver = "lbfgs") -> AlignResult:
    """Jitted coarse-to-fine minimisation of the alignment loss on a prepared problem.

    Args:
      problem: from ``prepare_alignment``.
      T_1_2_init: ``(4, 4)`` initial guess (maps map 2's frame into map 1's, metres), or
        ``(k, 4, 4)`` guesses solved in one ``vmap`` (every result field gains a leading ``k``;
        pick one with ``best_result``). May be traced (``(4, 4)`` only).
      maxiter: iterations per level (static).
      tol: gradient norm of the loss w.r.t. the increment [1/m].
      xtol: step length [m] at the finest level (default ``res / 100``), scaled by ``2^k`` at
        coarse levels.
      max_step: trust region [m]: the norm of one level's increment ``z``; a level that wants
        more is cut back and not counted as converged.
      min_overlap: status ``LOW_OVERLAP`` below this share of map 2's occupied points in map
        1's known space.
      min_agreement: status ``POOR_AGREEMENT`` below this share of those on map 1's surfaces.
      start_level: index into ``problem.levels``: solve from this level on, the coarser ones
        skipped (``iterations`` 0, history NaN); for starts already within that level's cell
        of the answer.
      solver: ``"lbfgs"`` (``_lbfgs.minimize``) or ``"jaxopt"`` (jaxopt's ``LBFGS``, same
        loss and levels, same result type); static.

    ``tol``, ``xtol``, ``max_step``, ``min_overlap``, ``min_agreement`` and ``start_level`` are
    traced: changing them does not recompile.

    Returns:
      ``AlignResult``.

    Raises:
      ValueError: naming the argument, for a non-rigid ``T_1_2_init`` or a bad option.
    """
    opts = _options(problem, maxiter, tol, xtol, max_step, min_overlap, min_agreement, start_level, solver)
    static = dict(maxiter=int(maxiter), solver=solver)
    if isinstance(T_1_2_init, jax.core.Tracer):
        return _solve_jit(problem, T_1_2_init, opts, **static)
    T0 = np.asarray(T_1_2_init, np.float64)
    if T0.ndim == 3:
        for i, T in enumerate(T0):
            check_rigid_transform(T, f"T_1_2_init[{i}]")
        return _solve_many_jit(problem, to_device(T0, np.float32), opts, **static)
    T0 = check_rigid_transform(T0, "T_1_2_init")
    return _solve_jit(problem, to_device(T0, np.float32), opts, **static)


def solve_alignment_batch(problems: AlignProblem, T_1_2_inits, *, maxiter: int = 30,
                          tol: float = 1e-4, xtol: float | None = None, max_step: float = 3.0,
                          min_overlap: float = 0.15, min_agreement: float = 0.85,
                          start_level: int = 0, solver: Solver = "lbfgs") -> AlignResult:
    """``solve_alignment`` ``vmap``-ed over stacked pairs (``stack_problems``) with one
    initial guess each, ``T_1_2_inits (n, 4, 4)``.

    Raises:
      ValueError: naming the argument, for a wrong shape, a non-rigid guess or a bad option.
    """
    opts = _options(problems, maxiter, tol, xtol, max_step, min_overlap, min_agreement, start_level, solver)
    T0 = np.asarray(T_1_2_inits, np.float64)
    if T0.ndim != 3 or T0.shape[0] != problems.radius.shape[0]:
        raise ValueError(f"T_1_2_inits: expected shape ({problems.radius.shape[0]}, 4, 4), got {T0.shape}")
    for i, T in enumerate(T0):
        check_rigid_transform(T, f"T_1_2_inits[{i}]")
    return _solve_pairs_jit(problems, jnp.asarray(T0, jnp.float32), opts, maxiter=int(maxiter), solver=solver)


def align_dense(m1: OccupancyMap, m2: OccupancyMap, T_1_2_init, *, levels=None,
                max_points: int = 8192, free_weight: float = 0.5, seed: int = 0,
                maxiter: int = 30, tol: float = 1e-4, xtol: float | None = None,
                max_step: float = 3.0, min_overlap: float = 0.15,
                min_agreement: float = 0.85, start_level: int = 0,
                solver: Solver = "lbfgs") -> AlignResult:
    """Refine ``T_1_2`` (maps points of map 2's frame into map 1's, metres) by dense map-to-map
    alignment: ``prepare_alignment`` (host; ``levels``, ``max_points``, ``free_weight``,
    ``seed``) then ``solve_alignment`` (jitted; the other arguments). ``T_1_2_init`` may be
    ``(4, 4)`` or a ``(k, 4, 4)`` stack of initial guesses (solved in one ``vmap``; pick one
    with ``best_result``). ``start_level`` (index into ``levels``) skips the coarser levels,
    for guesses already within that level's cell of the answer (e.g. an ICP result).

    Returns:
      ``AlignResult``.

    Raises:
      ValueError: naming the argument (``prepare_alignment``, ``solve_alignment``).
    """
    problem = prepare_alignment(m1, m2, levels=levels, max_points=max_points,
                                free_weight=free_weight, seed=seed)
    return solve_alignment(problem, T_1_2_init, maxiter=maxiter, tol=tol, xtol=xtol,
                           max_step=max_step, min_overlap=min_overlap,
                           min_agreement=min_agreement, start_level=start_level, solver=solver)


def best_result(results: AlignResult) -> AlignResult:
    """From a batched ``AlignResult`` (leading ``k``), the one with the lowest final loss,
    preferring candidates whose status is usable (converged or max-iterations) over failures."""
    ok = usable_mask(results.status, xp=jnp)
    key = jnp.where(ok, results.loss, results.loss + 10.0)
    key = jnp.where(jnp.isfinite(key), key, jnp.inf)
    i = jnp.argmin(key)
    return jax.tree_util.tree_map(lambda a: a[i], results)
