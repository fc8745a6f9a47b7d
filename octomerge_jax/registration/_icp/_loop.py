"""The ICP loop (thesis Alg. 3) on padded, centred clouds with pre-built stage grids.

Each iteration matches the stage's query points to their nearest target point (or target
centroid, on coarse stages) within the stage's correspondence distance ``d``
(``neighbors.nearest_with_points``) and solves eq. 3.18 in closed form (``kabsch``). The
transform is always re-solved from the original source points, so eq. 3.20's product of
increments is implicit. Anderson acceleration extrapolates the iterates (``_anderson``); an
accelerated iterate that does not lower the truncated energy (mean of ``min(d^2, d_stage^2)``)
is replaced by the plain step.

A stage ends when the change ``sum |dT|`` falls below ``epsilon``, or when its energy has not
improved by ``STALL_REL`` for ``STALL_PATIENCE`` iterations (centroid matches jitter). The last
stage ends ICP when the change falls below ``final_epsilon`` or when its energy has not reached
a new minimum for ``STALL_PATIENCE_FINAL`` iterations (float32 cycles of match sets).

One ``while_loop`` runs every stage of a whole run: the coarse stages on the coarse query
cloud (``_coarse``, padded to the source's rows) and the last stage on the source points, so a
registration compiles one loop body. A stage change restarts the acceleration history and the
stall count. ``run_until`` runs the coarse stages alone (their own loop) until a given stage,
and ``register`` resumes from its ``Progress`` with the last stage's loop (``icp_multi``'s basin
merging). A registration's loop ends with one more pass that searches the full cloud at the
result for the report (``_iteration_then_final``), so its program holds the search once
(``docs/design.md``, "One grid build per kind of level, one search per ICP program").
"""

from __future__ import annotations

from functools import partial
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

from ... import se3
from ..._ops import count_true
from .. import neighbors
from ..status import Status
from ._anderson import History, accelerate, empty_history, restarted
from ._coarse import Queries, QueryClouds, coarse_cloud, query_clouds
from ._kabsch import implicit_step, kabsch
from ._result import IcpResult

__all__ = ["Problem", "Progress", "IcpPath", "start_at", "run_until", "register", "register_with_path"]

STALL_REL, STALL_PATIENCE = 1e-3, 3  # a coarse stage ends when its energy stalls
STALL_REL_FINAL, STALL_PATIENCE_FINAL = 0.0, 6  # the last stage: no new best at all (a cycle)


class Problem(NamedTuple):
    """What every iteration of one registration reads (closed over, never traced as a whole)."""

    grids: neighbors.HashGrid  # one level per stage over the centred target (build_stage_grids)
    dists: jax.Array  # (s,) float32 [m], the stages' correspondence distances
    epsilon: jax.Array  # () float32, a coarse stage ends when sum |dT| falls below it
    final_epsilon: jax.Array  # () float32, the last stage's (ICP's) threshold
    min_inliers: jax.Array  # () int32, fewer correspondences stop ICP (Status.TOO_FEW_INLIERS)
    coarse_matching: str  # static: one of COARSE_MATCHING
    two_phase: bool  # static: the search of neighbors.nearest_with_points (False under vmap)

    @property
    def last_stage(self) -> int:
        return self.dists.shape[0] - 1


class Progress(NamedTuple):
    """Where a run stands: what ``icp_multi`` stops after a stage, merges and resumes."""

    T: jax.Array  # (4, 4) float32, the iterate T_target_source between the centred frames
    stage: jax.Array  # () int32, index into Problem.dists
    iteration: jax.Array  # () int32, correspondence searches so far
    done: jax.Array  # () bool, stopped: converged at the last stage, or too few inliers
    status: jax.Array  # () int32, the Status of a stopped run (MAX_ITERATIONS until then)


class Matches(NamedTuple):
    """Correspondences of the query rows of one stage's cloud."""

    index: jax.Array  # (m,) int32, matched target row (0 where none)
    inlier: jax.Array  # (m,) bool, a valid query with a match within the stage distance
    point: jax.Array  # (m, 3) float32 [m], the matched target point or centroid


class LoopState(NamedTuple):
    """The carry of the ICP ``while_loop``."""

    progress: Progress
    matches: Matches  # the correspondences of T_plain
    T_plain: jax.Array  # (4, 4) float32, the last accepted plain (Kabsch) step: the result
    accelerated: jax.Array  # () bool, progress.T is an Anderson iterate not yet checked
    energy_prev: jax.Array  # () float32 [m^2], truncated energy at the last iterate (inf after a restart)
    history: History  # Anderson history of the stage
    energy_best: jax.Array  # () float32 [m^2], the stage's lowest truncated energy
    stall: jax.Array  # () int32, iterations without a new best energy
    path: IcpPath | None = None  # the iterations so far (register_with_path), else None
    final: Final | None = None  # the result's correspondences (a loop that reports), else None


class Final(NamedTuple):
    """The full cloud's correspondences at the result (``T_plain``, last stage), searched by
    the loop's last pass (``_iteration_then_final``) for the report."""

    d2: jax.Array  # (n,) float32 [m^2]
    matches: Matches
    done: jax.Array  # () bool, searched


class IcpPath(NamedTuple):
    """Every iteration of one run, as the loop took it (row ``k``: iteration ``k + 1``; rows
    ``>= num_iterations`` are NaN / 0). Recorded by ``register_with_path``."""

    T: jax.Array  # (K, 4, 4) float32, the accepted plain (Kabsch) iterate after the iteration
    rmse: jax.Array  # (K,) float32 [m], rms distance of the iteration's correspondences (inliers)
    num_inliers: jax.Array  # (K,) int32, the iteration's correspondences within its stage distance
    distance: jax.Array  # (K,) float32 [m], the iteration's stage (correspondence) distance


def empty_path(max_iterations: int) -> IcpPath:
    """An ``IcpPath`` of ``max_iterations`` unrecorded rows."""
    K = int(max_iterations)
    nan = jnp.full((K,), jnp.nan, jnp.float32)
    return IcpPath(jnp.full((K, 4, 4), jnp.nan, jnp.float32), nan, jnp.zeros((K,), jnp.int32), nan)


def _recorded(path: IcpPath | None, k, T, d2, inlier, distance) -> IcpPath | None:
    """``path`` with row ``k`` set (``None`` when the run records nothing)."""
    if path is None:
        return None
    n = count_true(inlier)
    rmse = jnp.sqrt(jnp.sum(jnp.where(inlier, d2, 0.0)) / jnp.maximum(n, 1).astype(jnp.float32))
    return IcpPath(path.T.at[k].set(T), path.rmse.at[k].set(rmse), path.num_inliers.at[k].set(n),
                   path.distance.at[k].set(distance))


class Loop(NamedTuple):
    """One ``while_loop``: the query clouds it reads and the stages it runs."""

    clouds: Queries  # leading axis E: the clouds its stages read (stage_queries)
    stages: str  # static: "all", "coarse" (stage < last) or "last" (stage == last)


def start_at(T) -> Progress:
    """A run that has not started, at ``T (4, 4)`` (no gradient)."""
    T = jax.lax.stop_gradient(jnp.asarray(T, jnp.float32))
    return Progress(T, jnp.int32(0), jnp.int32(0), jnp.bool_(False), jnp.int32(Status.MAX_ITERATIONS))


# ----------------------------------------------------------------------------- one iteration


def correspond(problem: Problem, T, stage, queries: Queries):
    """``(d2 (m,) [m^2], Matches)`` of the query cloud under ``T (4, 4)`` at ``stage``.

    Coarse stages match the nearest sub-cell centroid of the stage's grid (``"centroid"``,
    ``"symmetric"``), or the exact nearest target point when one lies within the floor
    distance and the nearest centroid otherwise (``"nearest"``); the last stage the exact
    nearest point."""
    nearest = partial(neighbors.nearest_with_points, two_phase=problem.two_phase)
    grids, last = problem.grids, problem.last_stage
    p = se3.transform_points(T, queries.points)
    if problem.coarse_matching != "nearest":  # one query; the level is data (no cond: vmap-friendly)
        return _within_stage(problem, *nearest(grids, p, stage, queries.count), stage, queries.weights)
    d2, idx, match = nearest(grids, p, last, queries.count)
    d_floor = problem.dists[last]
    fine = (idx >= 0) & (d2 <= d_floor * d_floor)

    def coarse(_):
        d2c, idxc, matchc = nearest(grids, p, stage, queries.count)
        return (jnp.where(fine, d2, d2c), jnp.where(fine, idx, idxc),
                jnp.where(fine[:, None], match, matchc))

    found = jax.lax.cond(stage == last, lambda _: (d2, idx, match), coarse, None)
    return _within_stage(problem, *found, stage, queries.weights)


def _within_stage(problem: Problem, d2, idx, match, stage, weights):
    d_max = problem.dists[stage]
    inlier = (weights > 0) & (idx >= 0) & (d2 <= d_max * d_max)
    return d2, Matches(jnp.maximum(idx, 0), inlier, match)


def truncated_energy(problem: Problem, d2, stage, weights):
    """Weighted mean over the stage's cloud of ``min(d^2, d_stage^2)`` [m^2]: comparable between
    iterates of one stage (the safeguard of the accelerated steps)."""
    d_max2 = problem.dists[stage] * problem.dists[stage]
    return (jnp.sum(weights * jnp.minimum(jnp.where(weights > 0, d2, 0.0), d_max2))
            / jnp.maximum(jnp.sum(weights), 1.0))


def _stop_rules(problem: Problem, s: LoopState, energy, change, reject, enough, last):
    """``(stall, energy_best, finish, advance)``: the stall count and best energy after this
    iteration, whether ICP stops and whether the stage ends. A stage ends when the change
    falls below its epsilon or its energy stalls (a rejected step restarts a coarse stage's
    count, not the last stage's); nothing ends on a rejected step."""
    better = energy < s.energy_best * (1.0 - jnp.where(last, STALL_REL_FINAL, STALL_REL))
    stall = jnp.where(better | (reject & ~last), 0, s.stall + 1)
    energy_best = jnp.minimum(s.energy_best, energy)
    stalled = stall >= jnp.where(last, STALL_PATIENCE_FINAL, STALL_PATIENCE)
    small = ((change < jnp.where(last, problem.final_epsilon, problem.epsilon)) | stalled) & ~reject
    finish = ((small & last) | ~enough) & ~reject
    advance = small & ~last
    return stall, energy_best, finish, advance


def _iteration(problem: Problem, loop: Loop, s: LoopState, found=None) -> LoopState:
    """One ICP iteration: match, solve, decide, accelerate. ``found``: ``(queries, d2,
    Matches)`` of the stage's search at ``progress.T`` when already done."""
    p = s.progress
    last = p.stage == problem.last_stage
    if found is None:
        queries = stage_queries(loop, p.stage, problem.last_stage)
        found = (queries, *correspond(problem, p.T, p.stage, queries))
    queries, d2, m = found
    energy = truncated_energy(problem, d2, p.stage, queries.weights)
    # safeguard (Zhang et al. 2021): an accelerated iterate that does not lower the energy is
    # replaced by the plain step it extrapolated from
    reject = s.accelerated & ~(energy < s.energy_prev)
    enough = count_true(m.inlier) >= problem.min_inliers
    G = jnp.where(enough, kabsch(queries.points, jnp.where(m.inlier[:, None], m.point, 0.0),
                                 jnp.where(m.inlier, queries.weights, 0.0)), p.T)
    stall, energy_best, finish, advance = _stop_rules(problem, s, energy, jnp.sum(jnp.abs(G - p.T)),
                                                      reject, enough, last)
    T_acc, used, history = accelerate(s.history, p.T, G)
    restart = reject | advance  # the history restarts on a rejection and at a new stage
    T_next = jnp.where(reject, s.T_plain, jnp.where(advance | finish, G, T_acc))
    status = jnp.where(~enough, Status.TOO_FEW_INLIERS, Status.CONVERGED)
    progress = Progress(T_next, jnp.where(advance, p.stage + 1, p.stage), p.iteration + 1, finish,
                        jnp.where(finish, status, p.status).astype(jnp.int32))
    keep = reject  # a rejected iterate's correspondences are not used
    T_plain = jnp.where(keep, s.T_plain, G)
    return LoopState(
        progress=progress,
        matches=Matches(*(jnp.where(keep, a, b) for a, b in zip(s.matches, m))),
        T_plain=T_plain,
        accelerated=used & ~restart & ~finish,
        energy_prev=jnp.where(restart, jnp.inf, energy),
        history=restarted(restart, T_next, history),
        energy_best=jnp.where(advance, jnp.inf, energy_best),
        stall=jnp.where(advance, 0, stall).astype(jnp.int32),
        path=_recorded(s.path, p.iteration, T_plain, d2, m.inlier, problem.dists[p.stage]),
    )


def _iteration_then_final(problem: Problem, loop: Loop, running, s: LoopState) -> LoopState:
    """One ICP iteration while ``running(s)``; then, once, the search of the full cloud at the
    result (``LoopState.final``). Both are one search in one body, so a registration compiles
    the search once."""
    go = running(s)
    last = problem.last_stage
    stage = jnp.where(go, s.progress.stage, last)
    queries = stage_queries(loop, stage, last)
    d2, m = correspond(problem, jnp.where(go, s.progress.T, s.T_plain), stage, queries)
    before = s._replace(final=None)
    stepped = _iteration(problem, loop, before, (queries, d2, m))
    out = jax.tree.map(lambda a, b: jnp.where(go, a, b), stepped, before)
    take = ~go & ~s.final.done
    matches = Matches(*(jnp.where(take, a, b) for a, b in zip(m, s.final.matches)))
    return out._replace(final=Final(jnp.where(take, d2, s.final.d2), matches, s.final.done | take))


# ----------------------------------------------------------------------------- the loops


def stage_queries(loop: Loop, stage, last_stage: int) -> Queries:
    """The query cloud ``stage`` reads in ``loop``."""
    c = loop.clouds
    num = c.points.shape[0]
    if loop.stages == "coarse":
        return coarse_cloud(c, stage)
    if num == 1:
        return Queries(c.points[0], c.weights[0], c.count[0])
    # "all" with coarse entries first and the source points last
    i = jnp.where(stage == last_stage, num - 1, jnp.minimum(stage, num - 2))
    return Queries(c.points[i], c.weights[i], c.count[i])


def _loops(clouds: QueryClouds, *, run_coarse: bool, run_last: bool) -> list[Loop]:
    """The loops of a run: one over every stage when it runs them all (the coarse clouds
    padded to the source's rows: one body to compile), else the coarse stages'
    (``run_coarse``) or the last stage's (``run_last``)."""
    full = Queries(*(x[None] for x in clouds.full))
    if clouds.coarse is None:
        return [Loop(full, "all")]
    n, m = clouds.full.points.shape[0], clouds.coarse.points.shape[1]
    if run_coarse and run_last:
        # one loop (one body to compile): the coarse clouds padded to the source's rows; the
        # search skips the padding's blocks, so it costs a few elementwise passes
        pad = [(0, 0), (0, n - m)]
        coarse = Queries(jnp.pad(clouds.coarse.points, pad + [(0, 0)]), jnp.pad(clouds.coarse.weights, pad),
                         clouds.coarse.count)
        return [Loop(Queries(*(jnp.concatenate([c, f]) for c, f in zip(coarse, full))), "all")]
    loops = [Loop(clouds.coarse, "coarse")] if run_coarse else []
    if run_last:
        loops.append(Loop(full, "last"))
    return loops


def _running(progress: Progress, max_iterations: int, stop_stage, stop_when):
    go = ~progress.done & (progress.iteration < max_iterations)
    if stop_stage is not None:
        go = go & (progress.stage <= stop_stage)
    return go if stop_when is None else go & ~stop_when(progress.T)


def _in_loop(loop: Loop, stage, last_stage: int):
    if loop.stages == "coarse":
        return stage < last_stage
    if loop.stages == "last":
        return stage == last_stage
    return True


def _iterate(problem: Problem, clouds: QueryClouds, start: Progress, *, max_iterations: int,
             run_coarse: bool = True, stop_stage=None, stop_when=None, record: bool = False,
             report: bool = False) -> LoopState:
    """Run the loops from ``start``. Each loop's correspondences are as long as its clouds and
    start empty; the rest of the state carries over. ``record`` (static): keep an ``IcpPath``;
    ``report`` (static, a run of one loop that reaches the last stage): end with the search of
    ``LoopState.final``."""
    T0 = jax.lax.stop_gradient(jnp.asarray(start.T, jnp.float32))
    state = LoopState(Progress(T0, *(jnp.asarray(x) for x in start[1:])), None, T0, jnp.bool_(False),
                      jnp.float32(jnp.inf), empty_history(T0), jnp.float32(jnp.inf), jnp.int32(0),
                      empty_path(max_iterations) if record else None)
    last = problem.last_stage
    loops = _loops(clouds, run_coarse=run_coarse, run_last=stop_stage is None)
    if report and (len(loops) != 1 or stop_stage is not None):
        raise ValueError("only a run of one loop to the last stage reports")
    for loop in loops:
        rows = loop.clouds.points.shape[1]
        state = state._replace(matches=_no_matches(rows))

        def running(st, loop=loop):
            return (_running(st.progress, max_iterations, stop_stage, stop_when)
                    & _in_loop(loop, st.progress.stage, last))

        if report:
            n = clouds.full.points.shape[0]
            state = state._replace(final=Final(jnp.zeros((n,), jnp.float32), _no_matches(n), jnp.bool_(False)))
            state = jax.lax.while_loop(lambda st, running=running: running(st) | ~st.final.done,
                                       partial(_iteration_then_final, problem, loop, running), state)
        else:
            state = jax.lax.while_loop(running, partial(_iteration, problem, loop), state)
    return state


def _no_matches(rows: int) -> Matches:
    return Matches(jnp.zeros((rows,), jnp.int32), jnp.zeros((rows,), bool), jnp.zeros((rows, 3), jnp.float32))


def run_until(problem: Problem, source, source_count, start: Progress, stop_stage, *, max_iterations: int,
              stop_when: Callable[[jax.Array], jax.Array] | None = None) -> Progress:
    """Run from ``start`` until the run leaves coarse stage ``stop_stage`` (may be traced) or
    stops; also stop before any iteration at whose start ``stop_when(T)`` holds. The last
    stage's loop is not built. ``register`` resumed from the result takes exactly the steps of
    the uninterrupted run."""
    clouds = query_clouds(source, source_count, problem.dists, problem.coarse_matching)
    return _iterate(problem, clouds, start, max_iterations=max_iterations, stop_stage=stop_stage,
                    stop_when=stop_when).progress


def register(problem: Problem, source, source_count, target, start: Progress, *, max_iterations: int,
             run_coarse: bool = True) -> IcpResult:
    """One registration of ``source (Ns, 3)`` to ``target (Nt, 3)`` [m] (padded, centred) from
    ``start`` (``start_at(T_init)``, or a ``run_until`` result with ``run_coarse=False``).
    Vmappable over ``start`` (with ``problem.two_phase=False``). The result's transform carries
    the implicit derivative of the fixed point (``implicit_step``)."""
    clouds = query_clouds(source, source_count, problem.dists, problem.coarse_matching)
    state = _iterate(problem, clouds, start, max_iterations=max_iterations, run_coarse=run_coarse, report=True)
    return _report(problem, source, source_count, target, clouds, state)


def register_with_path(problem: Problem, source, source_count, target, start: Progress, *,
                       max_iterations: int) -> tuple[IcpResult, IcpPath]:
    """``register`` from ``start_at(T_init)`` that also returns its ``IcpPath``: the same
    iterations (recording changes no iterate), so the path's last recorded transform is the
    result's ``T_target_source``."""
    clouds = query_clouds(source, source_count, problem.dists, problem.coarse_matching)
    state = _iterate(problem, clouds, start, max_iterations=max_iterations, record=True, report=True)
    return _report(problem, source, source_count, target, clouds, state), state.path


def _report(problem: Problem, source, source_count, target, clouds: QueryClouds, state: LoopState) -> IcpResult:
    """The result at ``state.T_plain``: counts and rmse at the floor distance (a common
    yardstick, so that ``icp_multi`` can rank candidates that stopped at different stages)."""
    last = problem.last_stage
    p, T = state.progress, state.T_plain
    status = jnp.where(p.done, p.status, Status.MAX_ITERATIONS).astype(jnp.int32)
    d2, m_fin = state.final.d2, state.final.matches  # at T, the last stage, the full cloud
    m = state.matches
    if clouds.coarse is not None:
        # stopped on a coarse stage (max_iterations): its correspondences name centroids of a
        # coarser query cloud; the derivative below takes the source points' nearest points
        m = Matches(*(jnp.where(p.stage == last, a, b) for a, b in zip(m, m_fin)))
    n_in = count_true(m_fin.inlier)
    rmse = jnp.sqrt(jnp.sum(jnp.where(m_fin.inlier, d2, 0.0)) / jnp.maximum(n_in, 1).astype(jnp.float32))
    n_valid = jnp.maximum(source_count, 1).astype(jnp.float32)
    d_floor2 = problem.dists[last] * problem.dists[last]
    # y has the value of the matched coordinates (T is exactly their least-squares solution)
    # and the derivative of the matched target points (exact at the finest stage; a run stopped
    # on a coarse stage by max_iterations takes the nearest points at T, of which T is not the
    # exact solution)
    y_t = jnp.asarray(target, jnp.float32)[m.index]
    y = jax.lax.stop_gradient(m.point) + (y_t - jax.lax.stop_gradient(y_t))
    return IcpResult(
        T_target_source=implicit_step(T, jnp.asarray(source, jnp.float32), y, m.inlier),
        converged=status == Status.CONVERGED,
        num_iterations=p.iteration,
        num_inliers=n_in,
        rmse=rmse,
        fitness=n_in.astype(jnp.float32) / n_valid,
        num_close=count_true(m_fin.inlier & (d2 <= d_floor2 / 16.0)),
        correspondence_distance=problem.dists[p.stage],
        status=status,
        grid_overflow=problem.grids.overflow[p.stage],
        swapped=jnp.bool_(False),
    )
