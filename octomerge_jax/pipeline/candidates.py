"""``refine="multi"``'s candidate transforms (thesis Alg. 3 from many starts): ICP from the
yaw grid about the guess (``registration.icp_multi``), and ICP on the commonly mapped subsets
and the dense alignment from the best poses of ``registration.correlation_search``, gathered
into one ``IcpMultiResult`` for ranking (``ranking.py``)."""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import numpy as np

from .. import registration as reg
from ..map import OccupancyMap, bucket_capacity
from ..registration import Status, usable_mask
from .clouds import overlap_margin, select_overlap
from .config import MergeConfig
from .timings import Timings

__all__ = ["Candidates", "LEVEL_TILT_RAD", "concat_candidates", "dense_candidates", "level_near",
           "local_candidates", "multi_candidates", "search_tilts"]

LEVEL_TILT_RAD = 0.02  # a guess tilted more than this is also searched level


class Candidates(NamedTuple):
    """``multi_candidates``' output."""

    result: object  # IcpMultiResult over all k candidates
    origin: np.ndarray  # (k,) str: "yaw_grid", "correlation+icp" or "correlation+dense"
    problem: object  # the AlignProblem prepared for the correlation candidates, or None


def multi_candidates(m1: OccupancyMap, m2: OccupancyMap, p1, p2, T_1_2_init, config: MergeConfig,
                     icp_kwargs: dict, timings: Timings) -> Candidates:
    """``refine="multi"``'s candidates per ``registration.hypotheses``: ``icp_multi`` on the
    whole clouds ``p1`` / ``p2`` ``(n, 3)`` from the yaw grid about map 2's centroid
    (``registration.default_hypotheses``, timed as ``icp``), and / or ICP on the commonly
    mapped subsets (``registration.overlap`` under each pose, Alg. 2 + 3; timed as
    ``icp_correlation``) from the best poses of ``registration.correlation_search`` (timed as
    ``correlation``).

    The search's ``8 x correlation_hypotheses`` best poses are re-ranked by the dense loss at
    the level nearest twice its cell and the best ``correlation_hypotheses`` refined by ICP;
    the best ``correlation_dense`` of them also get the dense alignment from that level on
    (``dense_candidates``; timed as ``dense_correlation``)."""
    rc = config.registration
    T0 = np.asarray(T_1_2_init, np.float64)
    parts, problem = [], None
    if rc.hypotheses in ("yaw_grid", "both"):
        center = T0[:3, :3] @ np.asarray(p2, np.float64).mean(0) + T0[:3, 3]
        hyps = reg.default_hypotheses(T0, center, rc.yaw_step_rad, rc.roll_pitch_offset_rad)
        with timings.stage("icp") as stage:
            parts.append((stage.ready(reg.icp_multi(p2, p1, T0, hyps, **icp_kwargs)), "yaw_grid"))
    if rc.hypotheses in ("correlation", "both"):
        k = rc.correlation_hypotheses
        poses, cell = [], None
        for T_tilt in search_tilts(T0):
            with timings.stage("correlation") as stage:
                found = stage.ready(reg.correlation_search(m1, m2, T_tilt, num_hypotheses=8 * k))
            poses.append(np.asarray(found.hypotheses, np.float64))
            cell = found.cell
        poses = np.concatenate(poses)
        with timings.stage("rank") as stage:
            problem = stage.ready(reg.prepare_alignment(m1, m2))
        level = level_near(problem, 2.0 * cell)
        with timings.stage("correlation") as stage:
            loss = np.asarray(stage.ready(reg.dense.level_losses(problem, poses, level=level)))
        order = np.argsort(np.where(np.isfinite(loss), loss, np.inf), kind="stable")
        parts.append((local_candidates(p1, p2, poses[order[:k]], config, m1.resolution, icp_kwargs, timings),
                      "correlation+icp"))
        if rc.correlation_dense > 0:
            parts.append((dense_candidates(problem, poses[order[:rc.correlation_dense]], level, timings),
                          "correlation+dense"))
    result = parts[0][0]
    for part, _ in parts[1:]:
        result = concat_candidates(result, part)
    origin = np.concatenate([np.full(np.asarray(part.scores).shape[0], name) for part, name in parts])
    return Candidates(result, origin, problem)


def search_tilts(T0) -> list[np.ndarray]:
    """The rotations ``correlation_search`` turns about +z, each ``(4, 4)`` float64: the
    guess's (its roll and pitch kept), and, when the guess is tilted by more than
    ``LEVEL_TILT_RAD`` (its z axis from map 1's), the guess levelled (its yaw and translation
    kept, roll = pitch = 0), for maps that are both built z-up, as OctoMap maps usually are."""
    T0 = np.asarray(T0, np.float64)
    tilt = math.acos(float(np.clip(T0[2, 2], -1.0, 1.0)))
    if tilt <= LEVEL_TILT_RAD:
        return [T0]
    yaw = math.atan2(T0[1, 0], T0[0, 0])
    level = np.eye(4)
    level[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    level[:3, 3] = T0[:3, 3]
    return [T0, level]


def level_near(problem, cell: float) -> int:
    """Index into ``problem.levels`` of the level whose cell is nearest ``cell`` [m] (log scale)."""
    cells = problem.map1.resolution * 2.0 ** np.asarray(problem.levels, np.float64)
    return int(np.argmin(np.abs(np.log2(cells / float(cell)))))


def _multi_result(cands, scores, hypotheses, eligible=True):
    """An ``IcpMultiResult`` of stacked candidates (host arrays, ``k`` rows), its best the
    highest finite score among the ``eligible`` ones (``(k,)`` bool or ``True``)."""
    best = int(np.argmax(np.where(eligible & np.isfinite(scores), scores, -np.inf)))
    k = np.asarray(scores).shape[0]
    return reg.IcpMultiResult(jax.tree_util.tree_map(lambda a: a[best], cands), cands, np.int32(best), scores,
                              np.asarray(hypotheses, np.float32), np.arange(k, dtype=np.int32))


def dense_candidates(problem, hypotheses, start_level: int, timings: Timings,
                     timing: str = "dense_correlation"):
    """``registration.solve_alignment`` (the dense, map-to-map alignment) from each pose of
    ``hypotheses (k, 4, 4)``, from the level ``start_level`` on, as an ``IcpMultiResult``: a
    usable dense status (``Status.usable``) becomes ``Status.CONVERGED``, any other
    ``Status.TOO_FEW_INLIERS``, so that ranking skips it; the point statistics are not computed
    (0 / NaN). Scores are the negated losses. Timed as ``timing``."""
    with timings.stage(timing) as stage:
        a = stage.ready(reg.solve_alignment(problem, np.asarray(hypotheses, np.float64),
                                            start_level=int(start_level)))
    status = np.asarray(a.status)
    ok = usable_mask(status)
    k = status.shape[0]
    nan = np.full(k, np.nan, np.float32)
    zero = np.zeros(k, np.int32)
    cands = reg.IcpResult(
        T_target_source=np.asarray(a.T_1_2, np.float32), converged=status == Status.CONVERGED,
        num_iterations=np.asarray(a.num_iterations, np.int32), num_inliers=zero, rmse=nan, fitness=nan,
        num_close=zero, correspondence_distance=nan,
        status=np.where(ok, Status.CONVERGED, Status.TOO_FEW_INLIERS).astype(np.int32),
        grid_overflow=zero, swapped=np.zeros(k, bool))
    scores = -np.asarray(a.loss, np.float32)
    return _multi_result(cands, scores, hypotheses, eligible=ok)


def _no_overlap_candidate(T) -> object:
    """A candidate that kept its pose for lack of overlap: ``Status.TOO_FEW_INLIERS``."""
    z = np.int32(0)
    return reg.IcpResult(T_target_source=T.astype(np.float32), converged=np.bool_(False), num_iterations=z,
                         num_inliers=z, rmse=np.float32(np.nan), fitness=np.float32(0), num_close=z,
                         correspondence_distance=np.float32(np.nan), status=np.int32(Status.TOO_FEW_INLIERS),
                         grid_overflow=z, swapped=np.bool_(False))


def local_candidates(p1, p2, hypotheses, config: MergeConfig, resolution: float, icp_kwargs: dict,
                     timings: Timings):
    """ICP on the commonly mapped subsets from each pose of ``hypotheses (k, 4, 4)`` as an
    ``IcpMultiResult`` (a pose with too little overlap keeps its transform with status
    ``TOO_FEW_INLIERS``, so ranking skips it); scored by close points minus rmse / (2 res).
    Timed as ``icp_correlation``."""
    rc = config.registration
    hyps = np.asarray(hypotheses, np.float64)
    subsets = [select_overlap(p1, p2, T, rc.overlap, overlap_margin(config, resolution)) for T in hyps]
    # every subset padded to one capacity per cloud: one compiled ICP for all poses
    caps = [bucket_capacity(max(q[i].shape[0] for q in subsets)) for i in (0, 1)]
    out = []
    for T, (q1, q2) in zip(hyps, subsets):
        if min(q1.shape[0], q2.shape[0]) < rc.min_overlap_points:
            out.append(_no_overlap_candidate(T))
            continue
        with timings.stage("icp_correlation") as stage:
            r = stage.ready(reg.icp(_pad(q2, caps[1]), _pad(q1, caps[0]), T, source_count=q2.shape[0],
                                    target_count=q1.shape[0], **icp_kwargs))
        out.append(jax.tree_util.tree_map(np.asarray, r))
    cands = jax.tree_util.tree_map(lambda *xs: np.stack(xs), *out)
    scores = cands.num_close.astype(np.float32) - cands.rmse / np.float32(2.0 * resolution)
    return _multi_result(cands, scores, hypotheses)


def _pad(q, cap: int) -> np.ndarray:
    """``q (n, 3)`` with zero rows up to ``cap`` rows."""
    return np.concatenate([q, np.zeros((cap - q.shape[0], 3), np.float32)])


def concat_candidates(a, b):
    """Two ``IcpMultiResult`` as one (``a``'s best stays the best; ``b``'s basins shifted)."""
    cat = lambda x, y: np.concatenate([np.asarray(x), np.asarray(y)])  # noqa: E731
    # a result made here (not by icp_multi) has no merged runs: each candidate ran its own
    ran = lambda r: r.candidates.num_iterations if r.num_iterations_run is None else r.num_iterations_run  # noqa: E731
    return dataclasses.replace(a, candidates=jax.tree_util.tree_map(cat, a.candidates, b.candidates),
                               scores=cat(a.scores, b.scores), hypotheses=cat(a.hypotheses, b.hypotheses),
                               basin=cat(a.basin, np.asarray(b.basin) + np.asarray(a.basin).shape[0]),
                               num_iterations_run=cat(ran(a), ran(b)))
