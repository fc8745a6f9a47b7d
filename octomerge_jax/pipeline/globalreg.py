"""Registration without an initial guess (``refine="global"``, the default of ``merge`` when no
guess is given): ``register_global``; and the checks of a local ICP result: ``icp_left_start``
(it slid out of its start's basin) and its verdict, ``judge_local``.

::

    occupied leaf centres ──coarse grid (one point per occupied coarse cell), normals
        level each map by its floors; yaw peaks of the wall-normal histograms (each + pi)
        per yaw: FFT cross-correlation of the coarse occupancy grids, less free-space
                 conflicts ──> six translations per yaw          ──> ~48 poses
        net agreement on the coarse cells (agree - 3 x conflict, both directions; a cell is
        free when a quarter of it is seen free and it holds no surface; each map's grid offset
        so that its floor lies mid-cell)
        ──> top distinct poses, and the best once nudged by half cells
        ──ICP on the commonly mapped subsets (thesis Alg. 2-3); where ICP slid out of a nudged
          start better than every ICP result, the dense alignment from that start instead
        ──> net agreement again: best (ICP once more from it, on the subsets at its result),
            second-best distinct pose ──> verdict, confidence

Verdict (``Registration.info["verdict"]``, the merge's ``MergeReport.status``): ``"ok"``;
``"ambiguous"`` when a distinct second pose agrees nearly as well (symmetric rooms,
corridors), the confidence is below ``MIN_CONFIDENCE``, the net shared share below
``MIN_SHARED_OK`` (so little overlap that another placement, e.g. beside map 1 sharing a wall,
is about as consistent), the surfaces both maps agree on pin the pose horizontally by fewer
than ``MIN_PINNING_CELLS`` (``horizontal_pinning``: it may slide along them) or more than
``MAX_CONFLICT_RATIO`` of its agreeing cells' count conflict with free space; ``"no_overlap"``
when the best pose explains too little of the smaller map;
``"failed"`` when its ICP did not end usable. Maps are assumed gravity-aligned to within a
few degrees (``registration.global_search``). The thresholds are calibrated on the benchmark
grid (``benchmarks/bench_global.py``); see
``docs/design.md``, "Guess-free registration: measured choice".
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import os
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import jax
import numpy as np

from .. import registration as reg
from .. import se3
from ..map import OccupancyMap, bucket_capacity
from ..registration import Status
from ..registration.features import cell_codes, coarse_cloud, coarse_voxel_size, neighbor_pairs, normals
from ..registration.global_search import (CellSets, consistency_score, correlation_grid, distinct_poses,
                                          free_space, horizontal_pinning, level_rotation, map_cell_sets,
                                          net_agreement, nudge_poses, pose_distance, rotation_z,
                                          translation_candidates_of_grids, yaw_candidates)
from .clouds import (align_info, dense_registration_info, icp_info, icp_kwargs, occupied_clouds, overlap_margin,
                     point_stats, select_overlap, stage_epsilon)
from .config import MergeConfig
from .report import MergeError, Registration
from .timings import Timings

__all__ = ["AMBIGUOUS_GAP", "CANDIDATE_EPSILON_FACTOR", "CONFLICT_WEIGHT", "MAX_CONFLICT_RATIO", "MAX_ICP_DROP",
           "MAX_LOCAL_CONFLICT_RATIO", "MIN_CONFIDENCE", "MIN_EXPLAINED", "MIN_LOCAL_FITNESS", "MIN_PINNING_CELLS",
           "MIN_SHARED", "MIN_SHARED_OK", "candidate_listener", "explained_fraction", "icp_left_start", "judge_local",
           "local_cell_sets", "register_global"]

#: a distinct second pose whose net agreement is within this share of the best's: "ambiguous"
AMBIGUOUS_GAP = 0.1
#: the best pose explains less than this share of the smaller map's occupied points: "no_overlap"
MIN_EXPLAINED = 0.12
#: a coarse cell that puts surface into the other map's free space outweighs this many that agree
CONFLICT_WEIGHT = 3.0
#: coarse cells in agreement less CONFLICT_WEIGHT x those in conflict, over the smaller map's cells, below: "no_overlap"
MIN_SHARED = 0.1
#: below this confidence a result is not "ok": little overlap leaves other placements about as good
MIN_CONFIDENCE = 0.3
#: net shared share (as MIN_SHARED) below which a result is at most "ambiguous": a placement beside map 1
#: sharing a wall conflicts with nothing and explains about as much
MIN_SHARED_OK = 0.2
#: the surfaces both maps agree on at the best pose pin it horizontally by fewer coarse cells than this
#: (``horizontal_pinning``): at most "ambiguous", it may slide (a corridor, maps side by side sharing a wall)
MIN_PINNING_CELLS = 8.0
#: conflicting over agreeing coarse cells at the best pose above which it is at most "ambiguous": right poses
#: conflict on far fewer than a room turned by pi or a map placed where it has no common region (figures:
#: docs/design.md, "Guess-free registration: measured choice")
MAX_CONFLICT_RATIO = 0.08
#: a local ICP result whose fitness (inliers over map 2's commonly mapped points) is below: "failed"
MIN_LOCAL_FITNESS = 0.3
#: a local result with more conflicting than this share of its agreeing coarse cells: "failed" (right results
#: conflict on a few per cent, docs/design.md, "ICP that leaves its start")
MAX_LOCAL_CONFLICT_RATIO = 0.2
#: a local ICP result whose net agreement falls below its start's by more than this share of the start's
#: (and by at least _MIN_DROP_CELLS) slid out of the start's basin (docs/design.md, "ICP that leaves its start")
MAX_ICP_DROP = 0.25
_MIN_DROP_CELLS = 10.0
_NORMAL_RADIUS = 2.0  # [coarse cells]
_YAW_PEAKS, _TRANSLATION_PEAKS = 4, 6  # yaw peaks (each also turned by pi) x translation peaks per yaw
_MAX_CORRELATION_CELLS = 1 << 21  # the correlation grid's cells (padded): its cell grows to fit
_NUM_REFINED = 3  # distinct poses of the highest net agreement refined by ICP (all: see docs/design.md)
#: the candidates' ICP ends each stage at this many times the stages' threshold (``stage_epsilon``): they are told
#: apart on coarse cells, and the best one's ICP runs again at the threshold itself
CANDIDATE_EPSILON_FACTOR = 6.0
_candidate_callback: contextvars.ContextVar = contextvars.ContextVar("octomerge_candidate_listener", default=None)


@contextlib.contextmanager
def candidate_listener(callback):
    """While inside, ``register_global`` of this thread / task calls ``callback(T_1_2)`` with its
    best screened pose ``(4, 4)`` float64 before refining it (the command line compiles the
    transform and fusion kernels for it meanwhile). Nothing is watched outside."""
    token = _candidate_callback.set(callback)
    try:
        yield
    finally:
        _candidate_callback.reset(token)


def explained_fraction(points_1, points_2, T_1_2, distance: float, config: MergeConfig) -> tuple[int, float]:
    """``(count, fraction)``: map 2's points ``points_2 (n2, 3)`` [m] placed by ``T_1_2`` that
    lie within ``distance`` [m] of one of map 1's ``points_1 (n1, 3)``, and that count over
    ``min(n1, n2)`` (the largest overlap the smaller map allows)."""
    n = min(points_1.shape[0], points_2.shape[0])
    if n == 0 or not np.all(np.isfinite(T_1_2)):
        return 0, 0.0
    st = reg.evaluate_registration(points_2, points_1, np.asarray(T_1_2, np.float64), distance,
                                   cell_capacity=config.registration.cell_capacity)
    k = int(st.num_inliers)
    return k, k / n




class _Refined(NamedTuple):
    """One candidate after ICP (host values)."""

    T_1_2: np.ndarray  # (4, 4) float64
    result: object  # IcpResult, AlignResult (_dense_candidate) or None (too little overlap to run ICP)
    overlap: tuple  # (q1 (k1, 3), q2 (k2, 3)) float32 commonly mapped subsets [m]
    index: int  # row of the coarse candidates

    @property
    def usable(self) -> bool:
        """ICP (or the dense alignment) ran and ended with a usable ``Status``."""
        return self.result is not None and Status(int(self.result.status)).usable

    @property
    def is_icp(self) -> bool:
        """The pose is ICP's (not the dense alignment's, ``_dense_candidate``)."""
        return isinstance(self.result, reg.IcpResult)


def _pad(q, cap: int) -> np.ndarray:
    return np.concatenate([q, np.zeros((cap - q.shape[0], 3), np.float32)])


class _Search(NamedTuple):
    """What ``_search_poses`` leaves for the verification."""

    voxel: float  # [m] the coarse cell edge
    correlation_voxel: float  # [m] the correlation grids' cell edge (>= voxel)
    free_1: tuple  # free_space(m1, correlation_voxel): (points (f, 3) [m], volumes (f,) [m^3])
    free_2: tuple  # the same for m2


def _search_poses(m1, m2, p1, p2, resolution: float, timings: Timings):
    """Coarse clouds, levelling, yaw and translation candidates (``registration.global_search``):
    ``(c1, c2, poses (k, 4, 4) T_1_2, correlation scores (k,), info, _Search)``."""
    with timings.stage("features"):
        def cells(v):
            return max(np.unique(cell_codes(np.floor(p / v))).shape[0] for p in (p1, p2))
        v = coarse_voxel_size(cells, resolution)
        c1, c2 = coarse_cloud(p1, v), coarse_cloud(p2, v)
        n1, ok1 = normals(c1, neighbor_pairs(c1, _NORMAL_RADIUS * v))
        n2, ok2 = normals(c2, neighbor_pairs(c2, _NORMAL_RADIUS * v))
        L1, L2 = level_rotation(n1, ok1), level_rotation(n2, ok2)
        yaws = yaw_candidates(n1 @ L1.T, ok1, n2 @ L2.T, ok2, num_peaks=_YAW_PEAKS)
    a = c1.points @ L1.T
    span = np.ptp(a, axis=0) + np.ptp(c2.points, axis=0) + 2 * v
    v_corr = max(v, float(np.cbrt(np.prod(span) / _MAX_CORRELATION_CELLS)))
    poses, scores = [], []
    with timings.stage("correlation"):
        f1, w1 = free_space(m1, v_corr)
        f2, w2 = free_space(m2, v_corr)
        g1 = correlation_grid(a, v_corr, f1 @ L1.T, w1)  # one for every yaw of map 2
        for yaw in yaws:
            R = rotation_z(yaw) @ L2
            t, sc = translation_candidates_of_grids(g1, correlation_grid(c2.points @ R.T, v_corr, f2 @ R.T, w2), v_corr,
                                                    num_peaks=_TRANSLATION_PEAKS)
            for ti, si in zip(t, sc):
                T = np.eye(4)
                T[:3, :3] = L1.T @ R
                T[:3, 3] = L1.T @ ti
                poses.append(T)
                scores.append(float(si))
    info = {"coarse_voxel": round(v, 4), "correlation_voxel": round(v_corr, 4),
            "coarse_points": [int(c1.points.shape[0]), int(c2.points.shape[0])],
            "yaws": [round(float(y), 4) for y in yaws], "poses": len(poses)}
    search = _Search(v, v_corr, (f1, w1), (f2, w2))
    return c1, c2, np.asarray(poses).reshape(-1, 4, 4), np.asarray(scores, np.float64), info, search


def register_global(m1: OccupancyMap, m2: OccupancyMap, config: MergeConfig | None = None,
                    T_1_2_init=None, timings: Timings | None = None) -> Registration:
    """The transform ``T_1_2`` (map 2's frame into map 1's) found without a guess, with a
    verdict, a ``confidence`` and the top ``candidates`` (module docstring).

    Args:
      m1, m2: maps of one resolution.
      config: ``MergeConfig`` (its ``registration`` section: ICP settings, ``overlap``,
        ``min_overlap_points``); default ``MergeConfig()``.
      T_1_2_init: ``(4, 4)``, optional: verified alongside the poses found (a guess narrows
        the search; it is not needed).
      timings: seconds per stage are added (``occupied_points``, ``features``, ``matching``,
        ``hypotheses``, ``verify``, ``icp``).

    Returns a ``Registration``: ``T_1_2`` the best pose after ICP (rigid), ``info`` ICP's
    figures there plus ``verdict`` (``"ok"``, ``"ambiguous"``, ``"no_overlap"``,
    ``"failed"``: the merge's status) and ``global`` (coarse voxel, counts, map losses,
    the gap to the second-best distinct pose, the horizontal ``pinning``), ``confidence`` in [0, 1], ``candidates``
    (``{"T_1_2": 4x4 list, "score": -map loss, "agreement", "explained"}``, best first).
    Raises ``MergeError("empty")`` when a map has fewer than ``min_overlap_points`` occupied
    voxels. Method: ``registration.global_search`` (orientation histograms and correlation,
    Bosse and Zlot 2008), thesis Alg. 2-3 (overlap, ICP)."""
    config = MergeConfig() if config is None else config
    timings = Timings() if timings is None else timings
    rc = config.registration
    resolution = float(m1.resolution)
    p1, p2 = occupied_clouds(m1, m2, timings)
    for name, p in (("map 1", p1), ("map 2", p2)):
        if p.shape[0] < rc.min_overlap_points:
            raise MergeError(f"{name} has only {p.shape[0]} occupied voxels: nothing to register "
                             "(use --refine none to merge with the guess as is)", "empty")
    c1, c2, T_all, corr_scores, info_g, search = _search_poses(m1, m2, p1, p2, resolution, timings)
    v = search.voxel
    if T_1_2_init is not None:
        T_all = np.concatenate([T_all, np.asarray(T_1_2_init, np.float64)[None]])
    counts = {"occupied_1": int(p1.shape[0]), "occupied_2": int(p2.shape[0])}
    if T_all.shape[0] == 0:
        return _nothing(p1, p2, T_1_2_init, counts, info_g)
    extent = max(float(np.linalg.norm(np.ptp(c2.points, axis=0))) / 2.0, v)
    with timings.stage("verify"):
        same = search.correlation_voxel == v  # then the correlation's free space serves the cell sets
        s1 = map_cell_sets(p1, m1, v, search.free_1 if same else None)
        s2 = map_cell_sets(p2, m2, v, search.free_2 if same else None)
        screened = np.array([net_agreement(s1, s2, T, CONFLICT_WEIGHT) for T in T_all], np.float64)
        picked = list(distinct_poses(T_all, screened, extent, 2.0 * v, _NUM_REFINED))
        # and the best after half-cell nudges, if another: a pose a third of a cell off ranks low
        T_nudged, nudged = nudge_poses(s1, s2, T_all, v / 2, CONFLICT_WEIGHT)
        i_nudged = int(np.argmax(nudged))
        if all(pose_distance(T_all[i_nudged], T_all[i], extent) >= 2.0 * v for i in picked):
            picked.append(i_nudged)
    callback = _candidate_callback.get()
    if callback is not None:
        callback(np.array(T_all[picked[0]], np.float64))
    refined = _refine_all(p1, p2, T_all, picked, config, resolution, timings)
    with timings.stage("verify"):
        agree_conflict = [consistency_score(s1, s2, r.T_1_2) for r in refined]
    refined, agree_conflict = _dense_where_icp_slid(m1, m2, (p1, p2), (s1, s2), T_nudged[picked], nudged[picked],
                                                    refined, agree_conflict, config, timings)
    final = np.array([a - CONFLICT_WEIGHT * c for a, c in agree_conflict], np.float64)
    rank = np.argsort(-final, kind="stable")
    i_best = int(rank[0])
    best = refined[i_best]
    # ICP again from the best, on the commonly mapped subsets at its result: those of the
    # candidate's coarse pose may hold two minima a few hundredths of a radian apart
    again = _refine(p1, p2, best.T_1_2, best.index, config, resolution, timings) if best.is_icp else None
    if again is not None and again.usable:
        with timings.stage("verify"):
            a, c = consistency_score(s1, s2, again.T_1_2)
        if a - CONFLICT_WEIGHT * c > final[i_best]:
            refined[i_best], agree_conflict[i_best], final[i_best] = again, (a, c), a - CONFLICT_WEIGHT * c
            best = again
    seconds = [int(j) for j in rank[1:] if pose_distance(refined[j].T_1_2, best.T_1_2, extent) >= 2.0 * v]
    top_score = max(final[i_best], 1.0)
    gap = float((final[i_best] - final[seconds[0]]) / top_score) if seconds else 1.0
    agree, conflict = agree_conflict[i_best]
    cells = min(s1.occupied.codes.shape[0], s2.occupied.codes.shape[0])
    shared = float(final[i_best]) / max(cells, 1)  # share of the smaller map's cells explained, net of conflicts
    with timings.stage("verify"):
        n_in, explained = explained_fraction(p1, p2, best.T_1_2, 2.0 * resolution, config)
        pinning = horizontal_pinning(s1, s2, best.T_1_2, _NORMAL_RADIUS * v)
    conflict_ratio = conflict / max(agree, 1)
    confidence = _confidence(gap, shared, pinning, conflict_ratio)
    doubts: list[str] = []
    if shared < MIN_SHARED or explained < MIN_EXPLAINED:
        verdict = "no_overlap"
    elif not best.usable:
        verdict = "failed"
    else:
        doubts = _doubts(gap, shared, pinning, conflict_ratio, confidence)
        verdict = "ambiguous" if doubts else "ok"
    info_g.update(cells=[int(s1.occupied.codes.shape[0]), int(s2.occupied.codes.shape[0])],
                  screened=[round(float(x), 1) for x in screened[picked]], agree=agree, conflict=conflict,
                  shared=round(shared, 4), explained=round(explained, 4), explained_points=n_in, gap=round(gap, 4),
                  pinning=round(pinning, 2), conflict_ratio=round(conflict_ratio, 4))
    if best.is_icp:
        figures = icp_info(best.result)
    elif best.result is not None:  # the dense alignment's pose: ICP's point figures measured there
        dense = {**align_info(best.result), "started_from": "nudged candidate (its ICP slid)"}
        figures = dense_registration_info(dense, point_stats(p1, p2, best.T_1_2, config, resolution))
    else:
        figures = _no_icp()
    info = {**figures, "verdict": verdict, "global": info_g}
    candidates = tuple({"T_1_2": np.asarray(refined[j].T_1_2).tolist(),
                        "score": round(float(final[j]) / max(cells, 1), 5), "agree": agree_conflict[j][0],
                        "conflict": agree_conflict[j][1]} for j in [i_best, *seconds])
    q1, q2 = best.overlap
    counts.update(overlap_1=int(q1.shape[0]), overlap_2=int(q2.shape[0]))
    if verdict == "ambiguous":
        warnings = ("ambiguous: " + "; ".join(doubts) + "; give a guess (--xyz/--rpy) to choose",)
    else:
        warnings = () if verdict == "ok" else (_MESSAGES[verdict].format(frac=explained, shared=shared),)
    return Registration(T_1_2=best.T_1_2, converged=bool(info["converged"]), info=info,
                        result=best.result if best.is_icp else None,
                        counts=counts, points_1=q1, points_2=q2, warnings=warnings, confidence=confidence,
                        candidates=candidates)


def _confidence(gap: float, shared: float, pinning: float, conflict_ratio: float) -> float:
    """In [0, 1]: the margin over the second-best distinct pose (saturating at 4x the
    ambiguity gap) times how far the net shared share clears its no-overlap bound (saturating
    at 3x) times how firmly the pose is pinned (0 at ``MIN_PINNING_CELLS``, 1 from twice it)
    times how little of it conflicts (1 up to half ``MAX_CONFLICT_RATIO``, 0 from it on)."""
    margin = np.clip(gap / (4.0 * AMBIGUOUS_GAP), 0.0, 1.0)
    share = np.clip((shared - MIN_SHARED) / (2.0 * MIN_SHARED), 0.0, 1.0)
    pinned = np.clip(pinning / MIN_PINNING_CELLS - 1.0, 0.0, 1.0)
    clean = np.clip(2.0 - 2.0 * conflict_ratio / MAX_CONFLICT_RATIO, 0.0, 1.0)
    return float(margin * share * pinned * clean)


def _refine(p1, p2, T, index: int, config: MergeConfig, resolution: float, timings: Timings | None,
            epsilon_factor: float = 1.0) -> _Refined:
    """ICP on the commonly mapped subsets under ``T`` (padded to the full clouds' capacities:
    one compiled ICP per pair), every stage, the last one too, ending at ``epsilon_factor``
    times the stages' change threshold (a traced argument: the same program); the result made
    rigid when usable. ``timings``: its ICP is timed as stage ``icp`` (``None``: not timed)."""
    rc = config.registration
    q1, q2 = select_overlap(p1, p2, T, rc.overlap, overlap_margin(config, resolution))
    if min(q1.shape[0], q2.shape[0]) < rc.min_overlap_points:
        return _Refined(np.asarray(T, np.float64), None, (q1, q2), index)
    cap1, cap2 = bucket_capacity(p1.shape[0]), bucket_capacity(p2.shape[0])
    kw = icp_kwargs(config, resolution)
    # the last stage ends at the stages' threshold, not a hundredth of it: on a voxel lattice it
    # creeps on for tens of iterations by millimetres (docs/design.md)
    eps = stage_epsilon(config, resolution) * float(epsilon_factor)
    kw["transformation_epsilon"] = kw["final_transformation_epsilon"] = eps
    with contextlib.nullcontext() if timings is None else timings.stage("icp"):
        r = jax.block_until_ready(reg.icp(_pad(q2, cap2), _pad(q1, cap1), np.asarray(T, np.float64),
                                          source_count=q2.shape[0], target_count=q1.shape[0], **kw))
    r = jax.tree_util.tree_map(np.asarray, r)
    T_icp = np.asarray(r.T_target_source, np.float64)
    if Status(int(r.status)).usable and np.all(np.isfinite(T_icp)):
        T = se3.project_to_rigid(T_icp)
    return _Refined(np.asarray(T, np.float64), r, (q1, q2), index)


def _refine_all(p1, p2, poses, picked: list[int], config: MergeConfig, resolution: float,
                timings: Timings) -> list[_Refined]:
    """``_refine`` of the poses ``poses[i]`` (``(k, 4, 4)``) for ``i`` in ``picked``, in that
    order, its stages ending at ``CANDIDATE_EPSILON_FACTOR`` times the threshold, up to one per
    CPU core at once (``_side_by_side``): one ICP leaves part of a CPU idle, its loop being a
    chain of small kernels; the results are those of one after another (``docs/design.md``,
    "Candidates refined side by side"). Timed as one stage ``icp``."""
    with timings.stage("icp"):
        return _side_by_side(lambda i: _refine(p1, p2, poses[i], int(i), config, resolution, None,
                                               CANDIDATE_EPSILON_FACTOR), picked)


def _side_by_side(fn, items) -> list:
    """``[fn(x) for x in items]``, up to one call per CPU core at once (threads; NumPy and JAX
    release the interpreter while they compute), each in a copy of the caller's context (its
    memory budget, listeners). A call's exception is raised here (the first in ``items`` order)."""
    items = list(items)
    workers = min(len(items), os.cpu_count() or 1)
    if workers <= 1:
        return [fn(x) for x in items]
    with ThreadPoolExecutor(workers, thread_name_prefix="octomerge-side-by-side") as pool:
        futures = [pool.submit(contextvars.copy_context().run, fn, x) for x in items]
        return [f.result() for f in futures]


def _doubts(gap: float, shared: float, pinning: float, conflict_ratio: float, confidence: float) -> list[str]:
    """Why a usable best pose is not to be trusted (empty: it is), one phrase per failed gate."""
    doubts = []
    if gap < AMBIGUOUS_GAP:
        doubts.append(f"a distinct second pose agrees with map 1 nearly as well (within {gap:.1%}; symmetric scene?)")
    if shared < MIN_SHARED_OK:
        doubts.append(f"the maps share little (net {shared:.0%} of the smaller map's coarse cells)")
    if pinning < MIN_PINNING_CELLS:
        doubts.append("the shared surfaces leave the pose free to slide horizontally (a corridor?)")
    if conflict_ratio > MAX_CONFLICT_RATIO:
        doubts.append(f"surface in the other map's free space on {conflict_ratio:.0%} as many cells as agree")
    if confidence < MIN_CONFIDENCE and not doubts:
        doubts.append(f"confidence {confidence:.2f} below {MIN_CONFIDENCE}")
    return doubts


def _dense_where_icp_slid(m1, m2, clouds, sets, starts, start_nets, refined: list, agree_conflict: list,
                          config: MergeConfig, timings: Timings) -> tuple[list, list]:
    """``(refined, agree_conflict)`` with each candidate whose ICP slid out of its start's basin
    replaced by the dense alignment from that start (``_dense_candidate``) where that agrees
    better: ICP's net agreement fell below its start's (``_dropped``) and the start beats every
    candidate's ICP result. ``starts (k, 4, 4)``, ``start_nets (k,)``: the candidates' nudged
    starts and their net agreements; ``sets``: both maps' ``CellSets`` at the coarse cell
    (``docs/design.md``, "ICP that leaves its start")."""
    s1, s2 = sets
    nets = [a - CONFLICT_WEIGHT * c for a, c in agree_conflict]
    best_icp = max(nets)
    refined, agree_conflict = list(refined), list(agree_conflict)
    for k, (start, start_net) in enumerate(zip(starts, start_nets)):
        if not (refined[k].usable and start_net > best_icp and _dropped(start_net, nets[k])):
            continue
        alt = _dense_candidate(m1, m2, clouds, start, refined[k].index, config, timings)
        if alt is None:
            continue
        with timings.stage("verify"):
            a, c = consistency_score(s1, s2, alt.T_1_2)
        if a - CONFLICT_WEIGHT * c > nets[k]:
            refined[k], agree_conflict[k] = alt, (a, c)
    return refined, agree_conflict


def _dense_candidate(m1, m2, clouds, T_start, index: int, config: MergeConfig, timings: Timings) -> _Refined | None:
    """The dense alignment (``registration.align_dense``, all its levels) from ``T_start`` as a
    candidate, for one whose ICP slid out of its start's basin; ``None`` when its status is not
    usable (``docs/design.md``, "ICP that leaves its start")."""
    with timings.stage("dense") as stage:
        r = stage.ready(reg.align_dense(m1, m2, np.asarray(T_start, np.float64)))
    if not Status(int(r.status)).usable:
        return None
    T = se3.project_to_rigid(np.asarray(r.T_1_2, np.float64))
    rc = config.registration
    q = select_overlap(*clouds, T, rc.overlap, overlap_margin(config, float(m1.resolution)))
    return _Refined(T, r, q, index)


def _no_icp() -> dict:
    return {"converged": False, "status": str(Status.TOO_FEW_INLIERS), "num_iterations": 0, "num_inliers": 0,
            "rmse": float("nan"), "fitness": 0.0, "correspondence_distance": float("nan")}


def _nothing(p1, p2, T_1_2_init, counts, info_g) -> Registration:
    T0 = np.eye(4) if T_1_2_init is None else np.asarray(T_1_2_init, np.float64)
    return Registration(T_1_2=T0, converged=False, info={**_no_icp(), "verdict": "no_overlap", "global": info_g},
                        result=None, counts=counts, points_1=p1, points_2=p2,
                        warnings=("no overlap found: no consistent correspondences between the maps",),
                        confidence=0.0, candidates=())


_MESSAGES = {
    "no_overlap": "no overlap found: the best pose explains {frac:.0%} of the smaller map's occupied voxels "
                  "(net agreement {shared:.0%} of its coarse cells)",
    "failed": "registration failed: ICP from the best pose did not end usable",
}


def local_cell_sets(m1: OccupancyMap, m2: OccupancyMap, clouds) -> tuple[CellSets, CellSets]:
    """Both maps' coarse cell sets (``map_cell_sets`` of the occupied clouds ``clouds = (p1,
    p2)``) at the cell a local registration is checked on: ``coarse_voxel_size``'s smallest,
    ``max(3 res, 0.25 m)``."""
    p1, p2 = clouds
    v = coarse_voxel_size(lambda v: 0, m1.resolution)
    return map_cell_sets(p1, m1, v), map_cell_sets(p2, m2, v)


def icp_left_start(sets: tuple[CellSets, CellSets], T_start, T_icp) -> tuple[bool, float, float]:
    """Whether ICP from ``T_start`` slid out of its basin: ``(left, net at T_start, net at
    T_icp)``, the net agreements (``net_agreement`` on ``sets``, ``local_cell_sets``) [coarse
    cells]; ``left`` when the result's is below the start's by more than ``MAX_ICP_DROP`` of
    the start's magnitude and ``_MIN_DROP_CELLS``. Point-to-point ICP on a small or partial
    overlap can slide along corridors from the very truth; the free space it then fills gives
    it away (``docs/design.md``, "ICP that leaves its start")."""
    s1, s2 = sets
    net_start = net_agreement(s1, s2, T_start, CONFLICT_WEIGHT)
    net_icp = net_agreement(s1, s2, T_icp, CONFLICT_WEIGHT)
    return _dropped(net_start, net_icp), net_start, net_icp


def _dropped(net_start: float, net_end: float) -> bool:
    """The net agreement fell from ``net_start`` to ``net_end`` by more than ``MAX_ICP_DROP`` of
    the start's magnitude and ``_MIN_DROP_CELLS``."""
    return bool(net_start - net_end > max(MAX_ICP_DROP * abs(net_start), _MIN_DROP_CELLS))


def judge_local(m1: OccupancyMap, m2: OccupancyMap, clouds, registration: Registration,
                timings: Timings | None = None, sets: tuple[CellSets, CellSets] | None = None) -> Registration:
    """The verdict on a local registration (``refine="icp"`` from a guess): ``"failed"`` when
    ICP ended in a wrong basin: its fitness is below ``MIN_LOCAL_FITNESS``, or on the coarse
    grid of ``register_global`` the map-2 surfaces it puts into map 1's free space (and back)
    outweigh the agreeing ones (``agree - CONFLICT_WEIGHT * conflict <= 0``) or exceed
    ``MAX_LOCAL_CONFLICT_RATIO`` of them. ``sets``: the
    maps' ``local_cell_sets`` when already built. Returns ``registration`` with
    ``info["verdict"]`` and ``info["consistency"]`` set and, on failure, a warning."""
    info = registration.info
    if info is None:
        return registration
    timings = Timings() if timings is None else timings
    with timings.stage("verify"):
        s1, s2 = local_cell_sets(m1, m2, clouds) if sets is None else sets
        agree, conflict = consistency_score(s1, s2, registration.T_1_2)
    v = s1.occupied.voxel
    fitness = float(info.get("fitness", 0.0))
    bad = (fitness < MIN_LOCAL_FITNESS or agree - CONFLICT_WEIGHT * conflict <= 0
           or conflict > MAX_LOCAL_CONFLICT_RATIO * agree)
    info = {**info, "verdict": "failed" if bad else "ok",
            "consistency": {"voxel": round(v, 4), "agree": agree, "conflict": conflict}}
    warnings = registration.warnings
    if bad:
        warnings = (*warnings, f"registration failed: ICP ended in a wrong basin (fitness {fitness:.2f}, "
                               f"{conflict} coarse cells in the other map's free space against {agree} agreeing); "
                               "merge without a guess (refine \"global\") or give a better guess")
    return dataclasses.replace(registration, info=info, warnings=warnings)
