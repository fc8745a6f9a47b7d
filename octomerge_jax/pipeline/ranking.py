"""``refine="multi"`` after its candidates (``candidates.py``): the pick by the agreement of
the two *maps* (``rank_by_map_agreement``), near and far picks weighed (``rank_and_refine``),
then the thesis's local step from the pick (``local_step``)."""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import numpy as np

from .. import registration as reg
from ..map import OccupancyMap
from ..registration import Status, usable_mask
from .candidates import dense_candidates, level_near
from .clouds import overlap_margin, select_overlap
from .config import MergeConfig
from .timings import Timings

__all__ = ["LocalStep", "MIN_AGREEMENT", "MIN_OVERLAP", "MultiPick", "local_step", "rank_and_refine",
           "rank_by_map_agreement", "scores_and_plausible"]

# the dense alignment's status thresholds (``solve_alignment``'s defaults), for ranking candidates
MIN_OVERLAP, MIN_AGREEMENT = 0.15, 0.85


class LocalStep(NamedTuple):
    """``local_step``'s outcome."""

    result: object  # IcpResult to take the transform from, or None (keep the pick)
    info: dict  # JSON-ready: used, overlap counts, map losses, optional "dense"


class MultiPick(NamedTuple):
    """``rank_and_refine``'s outcome."""

    result: object  # IcpMultiResult with best / best_index the pick
    map_loss: np.ndarray  # (k,) float64 finest-level dense loss per candidate
    local: object  # IcpResult of the local step when used, else None
    info: dict  # JSON-ready local-step info (LocalStep.info, plus the near / far choice)


def scores_and_plausible(problem, T_1_2s, min_overlap: float = MIN_OVERLAP,
                         min_agreement: float = MIN_AGREEMENT) -> tuple:
    """``(finest-level map losses (k,), pass the dense status checks (k,) bool)`` of the poses
    ``T_1_2s`` (a ``(k, 4, 4)`` array or a sequence of ``(4, 4)``), float64."""
    loss, overlap, agree = (np.asarray(a, np.float64) for a in
                            reg.score_alignment(problem, np.asarray(T_1_2s, np.float64)))
    return loss, (overlap >= min_overlap) & (agree >= min_agreement)


def rank_by_map_agreement(m1: OccupancyMap, m2: OccupancyMap, result, *, problem=None, among=None,
                          min_agreement: float = MIN_AGREEMENT, min_overlap: float = MIN_OVERLAP):
    """``icp_multi``'s result (source = map 2's points, target = map 1's) with its best candidate
    re-chosen by the occupancy agreement of the two *maps* (``registration.score_alignment``):
    the lowest finest-level dense loss among candidates with a usable status
    (``Status.usable``). Candidates that pass the dense alignment's status checks
    (``solve_alignment``: at least ``min_overlap`` of map 2's occupied points in map 1's known
    space, ``min_agreement`` of those next to map 1's surfaces) are preferred; the others
    compete only when none passes.

    ``problem``: a ``prepare_alignment(m1, m2)`` to reuse (default: prepared here);
    ``among`` ``(k,)`` bool: choose only among these candidates (default: all).
    Returns ``(result with best / best_index replaced, map losses (k,) float64)``."""
    cands = result.candidates
    T = np.asarray(cands.T_target_source, np.float64)
    problem = reg.prepare_alignment(m1, m2) if problem is None else problem
    loss, plausible = scores_and_plausible(problem, T, min_overlap, min_agreement)
    ok = usable_mask(cands.status) & np.isfinite(loss)
    if among is not None:
        ok &= np.asarray(among, bool)
    if not ok.any():
        return result, loss
    plausible &= ok
    if plausible.any():
        ok = plausible
    i = int(np.argmin(np.where(ok, loss, np.inf)))
    best = jax.tree_util.tree_map(lambda a: a[i], cands)
    return dataclasses.replace(result, best=best, best_index=np.int32(i)), loss


def rank_and_refine(m1, m2, p1, p2, result, near_guess, config: MergeConfig, icp_kwargs: dict,
                    timings: Timings, problem=None, origin=None) -> MultiPick:
    """Candidates ranked by map agreement (``rank_by_map_agreement``), then the local step
    from the pick (``local_step``), both on one prepared alignment problem.

    ``near_guess`` ``(k,)`` bool: the candidate came from the yaw grid (near the guess) rather
    than from ``correlation_search`` (anywhere); with both kinds, each group's pick gets its
    local step; when only one of the two passes the dense status checks it is taken, else the
    far one only when its map loss is lower than the near one's by more than
    ``registration.far_margin`` (relative). ``problem``: a prepared alignment to reuse;
    ``origin`` ``(k,)`` str: where each candidate came from (the pick's goes to the info as
    ``pick_origin``)."""
    if problem is None:
        with timings.stage("rank") as stage:
            problem = stage.ready(reg.prepare_alignment(m1, m2))
    near = None if near_guess is None else np.asarray(near_guess, bool)
    if near is None or near.all() or not near.any():
        with timings.stage("rank") as stage:
            result, map_loss = stage.ready(rank_by_map_agreement(m1, m2, result, problem=problem))
        local, info = local_step(p1, p2, result.best, problem, config, m1.resolution, icp_kwargs, timings)
        if origin is not None:
            info["pick_origin"] = str(origin[int(result.best_index)])
        return MultiPick(result, map_loss, local, info)
    picks = {}
    for name, among in (("near", near), ("far", ~near)):
        with timings.stage("rank") as stage:
            r, map_loss = stage.ready(rank_by_map_agreement(m1, m2, result, problem=problem, among=among))
        local, info = local_step(p1, p2, r.best, problem, config, m1.resolution, icp_kwargs, timings)
        picks[name] = (r, local, info, (local if info["used"] else r.best).T_target_source)
    # both final poses scored in one call (two poses, as in the local step: no new compile)
    (l_near, l_far), (ok_near, ok_far) = scores_and_plausible(problem, [picks["near"][3], picks["far"][3]])
    if ok_near != ok_far:  # one passes the dense status checks: it, whatever the losses
        chosen = "near" if ok_near else "far"
    else:
        chosen = "far" if l_far < l_near - config.registration.far_margin * abs(l_near) else "near"
    r, local, info = picks[chosen][:3]
    info = {**info, "chosen": chosen, "loss_near": round(float(l_near), 5), "loss_far": round(float(l_far), 5),
            "plausible_near": bool(ok_near), "plausible_far": bool(ok_far)}
    if origin is not None:
        info["pick_origin"] = str(origin[int(r.best_index)])
    return MultiPick(r, map_loss, local, info)


def local_step(p1, p2, pick, problem, config: MergeConfig, resolution: float, icp_kwargs: dict,
               timings: Timings) -> LocalStep:
    """The thesis's local step after the global one: ICP on the commonly mapped subsets
    (``registration.overlap`` under the picked candidate ``pick``, an ``IcpResult``) from that
    candidate, timed as ``icp_local``; kept only when it lowers the map loss of
    ``rank_by_map_agreement`` and its status is usable.

    When neither the pick nor its local ICP result passes the dense status checks
    (``scores_and_plausible``), the dense alignment runs from the better of the two, from the
    level nearest ``max(0.4 m, 4 res)`` on (``dense_candidates``, timed as ``dense_local``),
    and its result is used if it converged (``info["dense"]``)."""
    rc = config.registration
    T_pick = np.asarray(pick.T_target_source, np.float64)
    info = {"used": False}
    if not np.all(np.isfinite(T_pick)):
        return LocalStep(None, info)
    q1, q2 = select_overlap(p1, p2, T_pick, rc.overlap, overlap_margin(config, resolution))
    info.update(overlap_1=int(q1.shape[0]), overlap_2=int(q2.shape[0]))
    if min(q1.shape[0], q2.shape[0]) < rc.min_overlap_points:
        return LocalStep(None, info)
    with timings.stage("icp_local") as stage:
        local = stage.ready(reg.icp(q2, q1, T_pick, **icp_kwargs))
    T_local = np.asarray(local.T_target_source, np.float64)
    if not np.all(np.isfinite(T_local)) or not Status(int(local.status)).usable:
        return LocalStep(None, info)
    loss, plausible = scores_and_plausible(problem, np.stack([T_pick, T_local]))
    used = bool(loss[1] < loss[0])
    info.update(map_loss_pick=round(float(loss[0]), 5), map_loss_local=round(float(loss[1]), 5), used=used)
    if plausible[int(used)]:
        return LocalStep(local if used else None, info)
    # the dense alignment from it, padded to correlation_dense poses (that call's compiled shape)
    start = np.repeat((T_local if used else T_pick)[None], max(1, rc.correlation_dense), axis=0)
    level = level_near(problem, max(0.4, 4.0 * resolution))
    found = dense_candidates(problem, start, level, timings, "dense_local")
    dense = found.best
    if Status(int(dense.status)) is not Status.CONVERGED or not np.all(np.isfinite(np.asarray(dense.T_target_source))):
        info["dense"] = {"used": False, "status": "failed the status checks"}
        return LocalStep(local if used else None, info)
    info["dense"] = {"used": True, "map_loss": round(-float(found.scores[int(found.best_index)]), 5),
                     "num_iterations": int(dense.num_iterations)}
    info["used"] = True
    return LocalStep(dense, info)
