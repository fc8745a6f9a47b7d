"""The registration step of a merge (thesis Alg. 1-3): ``register`` turns the initial guess
into the transform used, per ``config.registration.refine``:

- ``"icp"``: ICP on the commonly mapped subsets (``overlap`` under the guess, Alg. 2 + 3);
- ``"multi"``: candidates from ``icp_multi``'s yaw grid and / or ``correlation_search``'s poses
  (each with ICP on its overlap, the best few also with the dense alignment), picked by the
  agreement of the two *maps* (``rank_by_map_agreement``), then a local ICP step;
- ``"dense"``: ``align_dense`` (the occupancy fields, gradient-based); ``"icp+dense"``: both;
- ``"none"``: the guess as is.

Every mode reports ICP's fields (``ICP_STATUS_NAMES`` / ``DENSE_STATUS_NAMES``, inliers, rmse,
fitness); a transform that did not come from ICP gets them measured at it (``point_stats``).
Also ``icp_trace``, ICP replayed one iteration at a time for figures.
"""

from __future__ import annotations

import dataclasses
import math
import time

import jax
import numpy as np

from .config import MergeConfig
from .map import OccupancyMap, bucket_capacity
from .report import DENSE_STATUS_NAMES, ICP_STATUS_NAMES, MergeError

__all__ = ["register", "rank_by_map_agreement", "point_stats", "overlap_margin", "icp_trace",
           "VOXEL_OVERLAP_VOXELS"]


def _reg():
    from . import registration

    return registration


def _icp_modules():
    """The ``registration.icp`` and ``registration.neighbors`` modules (the package re-exports
    a function named ``icp``, so import the module by its full name)."""
    import importlib

    return (importlib.import_module(f"{__package__}.registration.icp"),
            importlib.import_module(f"{__package__}.registration.neighbors"))


def _timed(timings: dict, name: str, fn, *args, **kwargs):
    t0 = time.perf_counter()
    out = fn(*args, **kwargs)
    jax.block_until_ready(out)
    timings[name] = timings.get(name, 0.0) + time.perf_counter() - t0
    return out


def _icp_dict(result, refine: str) -> dict:
    multi = refine == "multi"
    r = result.best if multi else result
    status = int(r.status)
    out = dict(
        converged=bool(r.converged),
        status=ICP_STATUS_NAMES.get(status, str(status)),
        num_iterations=int(r.num_iterations),
        num_inliers=int(r.num_inliers),
        rmse=float(r.rmse),
        fitness=float(r.fitness),
        correspondence_distance=float(r.correspondence_distance),
        grid_overflow=int(r.grid_overflow),
        swapped=bool(r.swapped),
    )
    if multi:
        out["best_index"] = int(result.best_index)
        out["num_hypotheses"] = int(np.asarray(result.hypotheses).shape[0])
        out["num_basins"] = int(np.unique(np.asarray(result.basin)).size)
    return out


def _select_overlap(points_1, points_2, T_1_2, method: str, margin: float):
    """Overlap subsets ``(q1, q2)`` (each in its own frame) of the two occupied clouds."""
    if method == "none":
        return points_1, points_2
    kw = {} if margin is None else {("radius" if method == "voxel" else "margin"): margin}
    out = _reg().overlap(points_1, points_2, T_1_2, method=method, **kw)
    q1, q2 = out[0], out[1]
    q1, q2 = np.asarray(q1), np.asarray(q2)
    # the registration module may return boolean masks or the subsets themselves
    if q1.dtype == bool:
        q1 = np.asarray(points_1)[q1]
    if q2.dtype == bool:
        q2 = np.asarray(points_2)[q2]
    return q1.astype(np.float32), q2.astype(np.float32)


def _icp_kwargs(cfg: MergeConfig, resolution: float) -> dict:
    r = cfg.registration
    return dict(resolution=resolution, max_correspondence_distance=r.max_correspondence_distance,
                min_correspondence_distance=r.min_correspondence_distance,
                shrink_factor=r.shrink_factor, transformation_epsilon=r.transformation_epsilon,
                max_iterations=r.max_iterations, cell_capacity=r.cell_capacity,
                min_inliers=r.min_inliers, coarse_matching=r.coarse_matching)


VOXEL_OVERLAP_VOXELS = 3.0


def overlap_margin(cfg: MergeConfig, resolution: float) -> float | None:
    """The overlap slack [m]: ``registration.overlap_margin`` if set; else, for ``"voxel"``,
    ``3 * resolution`` (a point is kept if the other cloud has a point within 3 voxels under
    the guess: enough for guesses within ICP's reach, and tight enough that the edges of the
    other robot's coverage do not pull ICP sideways; measured on the test scene, a 1 m radius
    let ICP slide 0.9 m along walls, 0.3 m kept it within 5 cm); for ``"bbox"`` ``None``
    (the thesis's 1 m, ``registration.overlap``'s default)."""
    m = cfg.registration.overlap_margin
    if m is not None:
        return float(m)
    if cfg.registration.overlap == "voxel":
        return VOXEL_OVERLAP_VOXELS * float(resolution)
    return None


def register(m1: OccupancyMap, m2: OccupancyMap, T_1_2_init, config: MergeConfig,
             timings: dict, warnings: list, T_1_2_true=None):
    """Alg. 1-3 on the host: ``(T_1_2, icp_dict or None, icp_result, counts, q1, q2)``.

    Raises ``MergeError`` for empty clouds, no overlap or failed ICP (per the config)."""
    reg = _reg()
    rc = config.registration
    res = m1.resolution
    counts = {}
    p1 = _timed(timings, "occupied_points", reg.occupied_points, m1)
    p2 = _timed(timings, "occupied_points", reg.occupied_points, m2)
    p1, p2 = np.asarray(p1, np.float32).reshape(-1, 3), np.asarray(p2, np.float32).reshape(-1, 3)
    counts["occupied_1"], counts["occupied_2"] = int(p1.shape[0]), int(p2.shape[0])
    if rc.refine == "none":
        return T_1_2_init, None, None, counts, p1, p2
    if rc.refine == "dense":  # gradient-based alignment of the occupancy fields only
        T_1_2, dense_info, result = _refine_dense(m1, m2, T_1_2_init, timings, warnings)
        status = dense_info["status"]
        info = {"converged": dense_info["converged"], "status": DENSE_STATUS_NAMES.get(status, str(status)),
                "num_iterations": dense_info["num_iterations"],
                **_timed(timings, "evaluate", point_stats, p1, p2, T_1_2, config, res), "dense": dense_info}
        return T_1_2, info, result, counts, p1, p2
    for name, p in (("map 1", p1), ("map 2", p2)):
        if p.shape[0] < rc.min_overlap_points:
            raise MergeError(f"{name} has only {p.shape[0]} occupied voxels: nothing to register "
                             "(use --refine none to merge with the guess as is)", "empty")
    t0 = time.perf_counter()
    # the multi-hypothesis search must not be pre-cut by the (poor) guess: use all points
    method = "none" if rc.refine == "multi" else rc.overlap
    q1, q2 = _select_overlap(p1, p2, T_1_2_init, method, overlap_margin(config, res))
    timings["overlap"] = time.perf_counter() - t0
    counts["overlap_1"], counts["overlap_2"] = int(q1.shape[0]), int(q2.shape[0])
    if min(q1.shape[0], q2.shape[0]) < rc.min_overlap_points:
        raise MergeError(
            f"no overlap: under the initial guess only {q1.shape[0]} points of map 1 and "
            f"{q2.shape[0]} of map 2 lie in commonly mapped space (need "
            f"{rc.min_overlap_points}); check the guess (x y z roll pitch yaw, radians) or "
            f"try --refine multi", "no_overlap")
    kw = _icp_kwargs(config, res)
    if rc.refine == "multi":
        result, origin, problem = _multi_candidates(m1, m2, q1, q2, T_1_2_init, config, kw, timings)
        point_best = int(result.best_index)
        result, map_loss, local, local_info = _rank_and_refine(m1, m2, p1, p2, result, origin == "yaw_grid",
                                                               config, kw, timings, problem, origin)
        best = result.best
    else:
        result = _timed(timings, "icp", reg.icp, q2, q1, T_1_2_init, **kw)
        best = result
    info = _icp_dict(result, rc.refine)
    if rc.refine == "multi":
        info.update(point_best_index=point_best, map_loss=[round(float(v), 5) for v in map_loss])
        best = _with_local_step(info, best, local, local_info)
        _fill_point_stats(info, p1, p2, best.T_target_source, config, res, timings)
    T_icp = np.asarray(best.T_target_source, np.float64)
    if info["status"] == "too_few_inliers" or not np.all(np.isfinite(T_icp)):
        raise MergeError(
            f"ICP failed: only {info['num_inliers']} correspondences within "
            f"{info['correspondence_distance']:.3g} m (need {rc.min_inliers}); the guess is "
            f"probably too far off: try --refine multi or a better guess", "icp_failed")
    T_1_2 = T_icp
    if not info["converged"]:
        msg = (f"ICP did not converge within {info['num_iterations']} iterations (rmse "
               f"{info['rmse']:.4f} m, correspondence distance {info['correspondence_distance']:.3g} m)")
        if rc.on_not_converged == "error":
            raise MergeError(msg + "; raise registration.max_iterations or set "
                             "on_not_converged = \"warn\"", "not_converged")
        if rc.on_not_converged == "use_initial":
            warnings.append(msg + "; merged with the initial guess instead")
            T_1_2 = np.asarray(T_1_2_init, np.float64)
        else:
            warnings.append(msg + "; its last transform is used")
    if rc.refine == "icp+dense":  # ICP, then the dense alignment from its result
        retry = []
        T_icp = T_1_2
        T_1_2, dense_info, _ = _refine_dense(m1, m2, T_icp, timings, retry,
                                             within_m=info["correspondence_distance"] if info["converged"] else None)
        if dense_info["status"] not in (0, 1):
            # ICP can end in a wrong basin that dense cannot leave (it says so by its status);
            # dense from the initial guess then (measured: 15/18 -> 18/18 Table 7.1 rows)
            T_1_2, dense_info, _ = _refine_dense(m1, m2, T_1_2_init, timings, retry)
            dense_info["started_from"] = "initial guess (dense from the ICP result failed)"
            if dense_info["status"] not in (0, 1):
                T_1_2 = T_icp
                warnings.extend(retry)
        if dense_info["status"] in (0, 1):  # its result is used: the point statistics there
            dense_info.update(_timed(timings, "evaluate", point_stats, p1, p2, T_1_2, config, res))
        info = {**info, "dense": dense_info}
    # re-orthonormalise (float32 ICP output) so transform_map's rigidity check passes
    U, _, Vt = np.linalg.svd(T_1_2[:3, :3])
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    T_1_2 = T_1_2.copy()
    T_1_2[:3, :3] = R
    T_1_2[3] = (0.0, 0.0, 0.0, 1.0)
    return T_1_2, info, result, counts, q1, q2


def _multi_candidates(m1, m2, p1, p2, T_1_2_init, config: MergeConfig, icp_kwargs: dict, timings: dict):
    """``refine="multi"``'s candidates per ``registration.hypotheses`` (``merge`` and
    ``merge_batch``): ``icp_multi`` on the whole clouds from the yaw grid about map 2's
    centroid (``registration.default_hypotheses``, timed as ``icp``), and / or ICP on the
    commonly mapped subsets (``registration.overlap`` under each pose, Alg. 2 + 3; timed as
    ``icp_correlation``) from the best poses of ``registration.correlation_search`` (timed as
    ``correlation``). Whole-cloud ICP from a correlation pose slides off it on partially
    overlapping maps (it maximises overlap; measured on the tests' hall from poses within
    0.3 m of the truth: 3.2 m off).

    The search's 8 x ``correlation_hypotheses`` best poses are re-ranked by the dense loss at
    the level nearest twice its cell (0.4 m at the defaults: trilinear, so smoother than the
    search's cells) and the best ``correlation_hypotheses`` refined: on the simulated lab
    (0.05 m) the pose nearest the truth (0.2 m) was the search's 37th and the re-ranking's
    2nd (office: 1st and 1st). ICP on the lab's overlap from it stalls at 0.2 m, so the best
    ``correlation_dense`` of them also get the dense alignment from that level on
    (``_dense_candidates``; timed as ``dense_correlation``). Returns ``(IcpMultiResult, origin
    (k,) str: "yaw_grid", "correlation+icp" or "correlation+dense" per candidate, the prepared
    alignment problem or None)``."""
    reg = _reg()
    rc = config.registration
    T0 = np.asarray(T_1_2_init, np.float64)
    parts, problem = [], None
    if rc.hypotheses in ("yaw_grid", "both"):
        center = T0[:3, :3] @ np.asarray(p2, np.float64).mean(0) + T0[:3, 3]
        hyps = reg.default_hypotheses(T0, center, rc.yaw_step_rad, rc.roll_pitch_offset_rad)
        parts.append((_timed(timings, "icp", reg.icp_multi, p2, p1, T0, hyps, **icp_kwargs), "yaw_grid"))
    if rc.hypotheses in ("correlation", "both"):
        k = rc.correlation_hypotheses
        poses, cell = [], None
        for T_tilt in _search_tilts(T0):
            found = _timed(timings, "correlation", reg.correlation_search, m1, m2, T_tilt, num_hypotheses=8 * k)
            poses.append(np.asarray(found.hypotheses, np.float64))
            cell = found.cell
        poses = np.concatenate(poses)
        problem = _timed(timings, "rank", reg.prepare_alignment, m1, m2)
        level = _level_near(problem, 2.0 * cell)
        loss = np.asarray(_timed(timings, "correlation", reg.dense.level_losses, problem, poses, level=level))
        order = np.argsort(np.where(np.isfinite(loss), loss, np.inf), kind="stable")
        parts.append((_local_candidates(p1, p2, poses[order[:k]], config, m1.resolution, icp_kwargs,
                                        timings), "correlation+icp"))
        if rc.correlation_dense > 0:
            parts.append((_dense_candidates(problem, poses[order[:rc.correlation_dense]], level,
                                            timings), "correlation+dense"))
    result = parts[0][0]
    for part, _ in parts[1:]:
        result = _concat_candidates(result, part)
    origin = np.concatenate([np.full(np.asarray(part.scores).shape[0], name) for part, name in parts])
    return result, origin, problem


_LEVEL_TILT_RAD = 0.02  # a guess tilted more than this is also searched level


def _search_tilts(T0):
    """The rotations ``correlation_search`` turns about +z: the guess's (its roll and pitch
    kept), and, when the guess is tilted by more than ``_LEVEL_TILT_RAD`` (its z axis from
    map 1's), the guess levelled (its yaw kept, roll = pitch = 0), for maps that are both built
    z-up, as OctoMap maps usually are, where a tilted guess carries a tilt error: on the
    simulated lab (0.05 m), guesses tilted by 0.11-0.12 rad with 1.6-1.8 m offsets ended turned by pi
    (the search at the guess's tilt cannot reach the truth, nor can the yaw grid's ICP)."""
    T0 = np.asarray(T0, np.float64)
    tilt = math.acos(float(np.clip(T0[2, 2], -1.0, 1.0)))
    if tilt <= _LEVEL_TILT_RAD:
        return [T0]
    yaw = math.atan2(T0[1, 0], T0[0, 0])
    level = np.eye(4)
    level[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    level[:3, 3] = T0[:3, 3]
    return [T0, level]


def _level_near(problem, cell: float) -> int:
    """Index into ``problem.levels`` of the level whose cell is nearest ``cell`` [m] (log scale)."""
    cells = problem.map1.resolution * 2.0 ** np.asarray(problem.levels, np.float64)
    return int(np.argmin(np.abs(np.log2(cells / float(cell)))))


def _dense_candidates(problem, hypotheses, start_level: int, timings: dict, timing: str = "dense_correlation"):
    """``registration.solve_alignment`` (the dense, map-to-map alignment) from each pose of
    ``hypotheses (k, 4, 4)``, from the level ``start_level`` on (the one the poses were
    re-ranked at: they are within about a search cell, and the coarser levels' biased minima
    let the solver wander out of the basin), as an ``IcpMultiResult``: a result with status
    converged or max-iterations is usable (ICP status 0), any other (poor agreement, too
    little overlap) is not (status too few inliers); the point statistics are not computed
    (0 / NaN). On the simulated lab (0.05 m) ICP on the overlap stalled 0.2 m from the truth
    where this reached 0.027 m, and it reported the wrong poses that agree better than the
    truth as poor agreement."""
    reg = _reg()
    icp_mod, _ = _icp_modules()
    a = _timed(timings, timing, reg.solve_alignment, problem, np.asarray(hypotheses, np.float64),
               start_level=int(start_level))
    status = np.asarray(a.status)
    ok = np.isin(status, (0, 1))
    k = status.shape[0]
    nan = np.full(k, np.nan, np.float32)
    zero = np.zeros(k, np.int32)
    cands = reg.IcpResult(
        T_target_source=np.asarray(a.T_1_2, np.float32), converged=status == 0,
        num_iterations=np.asarray(a.num_iterations, np.int32), num_inliers=zero, rmse=nan, fitness=nan,
        num_close=zero, correspondence_distance=nan,
        status=np.where(ok, icp_mod.STATUS_CONVERGED, icp_mod.STATUS_TOO_FEW_INLIERS).astype(np.int32),
        grid_overflow=zero, swapped=np.zeros(k, bool))
    scores = -np.asarray(a.loss, np.float32)
    best = int(np.argmax(np.where(ok & np.isfinite(scores), scores, -np.inf)))
    return reg.IcpMultiResult(jax.tree_util.tree_map(lambda x: x[best], cands), cands, np.int32(best), scores,
                              np.asarray(hypotheses, np.float32), np.arange(k, dtype=np.int32))


def _local_candidates(p1, p2, hypotheses, config: MergeConfig, resolution: float, icp_kwargs: dict,
                      timings: dict):
    """ICP on the commonly mapped subsets from each pose of ``hypotheses (k, 4, 4)`` as an
    ``IcpMultiResult`` (a pose with too little overlap keeps its transform with status too
    few inliers, so ranking skips it)."""
    reg = _reg()
    icp_mod, _ = _icp_modules()
    rc = config.registration
    hyps = np.asarray(hypotheses, np.float64)
    subsets = [_select_overlap(p1, p2, T, rc.overlap, overlap_margin(config, resolution)) for T in hyps]
    # every subset padded to one capacity per cloud: one compiled ICP for all poses
    caps = [bucket_capacity(max(q[i].shape[0] for q in subsets)) for i in (0, 1)]
    pad = lambda q, cap: np.concatenate([q, np.zeros((cap - q.shape[0], 3), np.float32)])  # noqa: E731
    out = []
    for T, (q1, q2) in zip(hyps, subsets):
        if min(q1.shape[0], q2.shape[0]) >= rc.min_overlap_points:
            r = _timed(timings, "icp_correlation", reg.icp, pad(q2, caps[1]), pad(q1, caps[0]), T,
                       source_count=q2.shape[0], target_count=q1.shape[0], **icp_kwargs)
            out.append(jax.tree_util.tree_map(np.asarray, r))
            continue
        z = np.int32(0)
        out.append(reg.IcpResult(T_target_source=T.astype(np.float32), converged=np.bool_(False),
                                 num_iterations=z, num_inliers=z, rmse=np.float32(np.nan),
                                 fitness=np.float32(0), num_close=z, correspondence_distance=np.float32(np.nan),
                                 status=np.int32(icp_mod.STATUS_TOO_FEW_INLIERS), grid_overflow=z,
                                 swapped=np.bool_(False)))
    cands = jax.tree_util.tree_map(lambda *xs: np.stack(xs), *out)
    scores = cands.num_close.astype(np.float32) - cands.rmse / np.float32(2.0 * resolution)
    best = int(np.argmax(np.where(np.isfinite(scores), scores, -np.inf)))
    return reg.IcpMultiResult(jax.tree_util.tree_map(lambda a: a[best], cands), cands, np.int32(best), scores,
                              np.asarray(hypotheses, np.float32), np.arange(len(out), dtype=np.int32))


def _concat_candidates(a, b):
    """Two ``IcpMultiResult`` as one (``a``'s best stays the best; ``b``'s basins shifted)."""
    cat = lambda x, y: np.concatenate([np.asarray(x), np.asarray(y)])  # noqa: E731
    # a result made here (not by icp_multi) has no merged runs: each candidate ran its own
    ran = lambda r: r.candidates.num_iterations if r.num_iterations_run is None else r.num_iterations_run  # noqa: E731
    return dataclasses.replace(a, candidates=jax.tree_util.tree_map(cat, a.candidates, b.candidates),
                               scores=cat(a.scores, b.scores), hypotheses=cat(a.hypotheses, b.hypotheses),
                               basin=cat(a.basin, np.asarray(b.basin) + np.asarray(a.basin).shape[0]),
                               num_iterations_run=cat(ran(a), ran(b)))


def _rank_and_refine(m1, m2, p1, p2, result, near_guess, config: MergeConfig, icp_kwargs: dict,
                     timings: dict, problem=None, origin=None):
    """``refine="multi"`` after ``icp_multi`` (``merge`` and ``merge_batch``): its candidates
    ranked by map agreement (``rank_by_map_agreement``), then the local step from the pick
    (``_refine_multi_locally``), both on one prepared alignment problem.

    With candidates from both sources (``near_guess``: ``_multi_candidates``'s origin is the yaw
    grid, near the guess; the others come from ``correlation_search``, anywhere), each group's
    pick gets its local step; when only one of the two passes the dense status checks
    (``rank_by_map_agreement``) it is taken, else the far one only when its map loss is lower
    than the near one's by more than ``registration.far_margin`` (relative): maps can agree
    about as well at a wrong pose as at the truth (simulated lab at 0.05 m: a pose 6.6 m off
    -0.276, the truth -0.271), and then the guess decides. Returns ``(ranked result, map losses (k,),
    local IcpResult or None, local info dict)``. ``problem``: a prepared alignment to reuse;
    ``origin`` ``(k,)`` str: where each candidate came from (the pick's goes to the info dict
    as ``pick_origin``)."""
    if problem is None:
        problem = _timed(timings, "rank", _reg().prepare_alignment, m1, m2)
    near = None if near_guess is None else np.asarray(near_guess, bool)
    if near is None or near.all() or not near.any():
        result, map_loss = _timed(timings, "rank", rank_by_map_agreement, m1, m2, result, problem=problem)
        local, info = _refine_multi_locally(p1, p2, result.best, problem, config, m1.resolution, icp_kwargs,
                                            timings)
        if origin is not None:
            info["pick_origin"] = str(origin[int(result.best_index)])
        return result, map_loss, local, info
    picks = {}
    for name, among in (("near", near), ("far", ~near)):
        r, map_loss = _timed(timings, "rank", rank_by_map_agreement, m1, m2, result, problem=problem,
                             among=among)
        local, info = _refine_multi_locally(p1, p2, r.best, problem, config, m1.resolution, icp_kwargs,
                                            timings)
        picks[name] = (r, local, info, (local if info["used"] else r.best).T_target_source)
    # both final poses scored in one call (two poses, as in the local step: no new compile)
    (l_near, l_far), (ok_near, ok_far) = _scores_and_plausible(problem, [picks["near"][3], picks["far"][3]])
    if ok_near != ok_far:  # one passes the dense status checks: it, whatever the losses
        chosen = "near" if ok_near else "far"
    else:
        chosen = "far" if l_far < l_near - config.registration.far_margin * abs(l_near) else "near"
    r, local, info = picks[chosen][:3]
    info = {**info, "chosen": chosen, "loss_near": round(float(l_near), 5), "loss_far": round(float(l_far), 5),
            "plausible_near": bool(ok_near), "plausible_far": bool(ok_far)}
    if origin is not None:
        info["pick_origin"] = str(origin[int(r.best_index)])
    return r, map_loss, local, info


def _refine_multi_locally(p1, p2, pick, problem, config: MergeConfig, resolution: float,
                          icp_kwargs: dict, timings: dict):
    """The thesis's local step after ``icp_multi``'s global one: ICP on the commonly mapped
    subsets (``registration.overlap`` under the picked candidate) from that candidate. Whole
    clouds of partially overlapping maps bias the candidates (measured on simulated office / lab
    ``.bt`` pairs at 0.05 m: a pick 0.15 m / 0.07 rad off ended 0.013 m / 0.007 rad off). Kept
    only when it lowers the map loss of ``rank_by_map_agreement`` (the same finest-level dense
    loss) and ICP did not fail.

    When neither the pick nor its local ICP result passes the dense status checks
    (``_scores_and_plausible``), the dense alignment runs from the better of the two, from the
    level nearest ``max(0.4 m, 4 res)`` on (``_dense_candidates``, timed as ``dense_local``), and
    its result is used if it passes them (``info["dense"]``): ICP from a yaw-grid pick with a
    roll / pitch error left a pose 0.07-0.09 m off with agreement below 0.85 on the simulated
    lab (0.05 m, guesses with 0.1-0.15 rad of tilt), and a wrong far pick won by the map loss.
    Returns ``(IcpResult or None, info dict)``."""
    reg = _reg()
    rc = config.registration
    T_pick = np.asarray(pick.T_target_source, np.float64)
    info = {"used": False}
    if not np.all(np.isfinite(T_pick)):
        return None, info
    q1, q2 = _select_overlap(p1, p2, T_pick, rc.overlap, overlap_margin(config, resolution))
    info.update(overlap_1=int(q1.shape[0]), overlap_2=int(q2.shape[0]))
    if min(q1.shape[0], q2.shape[0]) < rc.min_overlap_points:
        return None, info
    local = _timed(timings, "icp_local", reg.icp, q2, q1, T_pick, **icp_kwargs)
    T_local = np.asarray(local.T_target_source, np.float64)
    if not np.all(np.isfinite(T_local)) or int(local.status) not in (0, 1):
        return None, info
    loss, plausible = _scores_and_plausible(problem, np.stack([T_pick, T_local]))
    used = bool(loss[1] < loss[0])
    info.update(map_loss_pick=round(float(loss[0]), 5), map_loss_local=round(float(loss[1]), 5), used=used)
    if plausible[int(used)]:
        return (local if used else None), info
    # the dense alignment from it, padded to correlation_dense poses (that call's compiled shape)
    start = np.repeat((T_local if used else T_pick)[None], max(1, rc.correlation_dense), axis=0)
    level = _level_near(problem, max(0.4, 4.0 * resolution))
    # its status says whether it passes the checks (solve_alignment's thresholds are _MIN_*)
    found = _dense_candidates(problem, start, level, timings, "dense_local")
    dense = found.best
    if int(dense.status) != 0 or not np.all(np.isfinite(np.asarray(dense.T_target_source))):
        info["dense"] = {"used": False, "status": "failed the status checks"}
        return (local if used else None), info
    info["dense"] = {"used": True, "map_loss": round(-float(found.scores[int(found.best_index)]), 5),
                     "num_iterations": int(dense.num_iterations)}
    info["used"] = True
    return dense, info


def _with_local_step(info: dict, pick, local, local_info: dict):
    """Record ``_refine_multi_locally``'s outcome in ``info`` (key ``local``); when its result is
    used, the top-level convergence, iterations, inliers and rmse become its own. Returns the
    result to take the transform from."""
    info["local"] = local_info
    if local is None:
        return pick
    status = int(local.status)
    info.update(converged=bool(local.converged), status=ICP_STATUS_NAMES.get(status, str(status)),
                num_iterations=int(local.num_iterations), num_inliers=int(local.num_inliers),
                rmse=float(local.rmse), fitness=float(local.fitness),
                correspondence_distance=float(local.correspondence_distance))
    return local


def point_stats(points_1, points_2, T_1_2, config: MergeConfig, resolution: float) -> dict:
    """``num_inliers``, ``rmse`` [m], ``fitness`` and ``correspondence_distance`` [m] of map 2's
    occupied points placed by ``T_1_2`` against map 1's (``registration.evaluate_registration``
    on the commonly mapped subsets under ``T_1_2``, ``registration.overlap``, within ICP's floor
    distance, 2 res by default): the figures ICP reports at its result, for a transform that
    did not come from ICP (the dense alignment)."""
    reg = _reg()
    rc = config.registration
    d = float(reg.stage_distances(resolution, rc.max_correspondence_distance, rc.min_correspondence_distance,
                                  rc.shrink_factor)[-1])
    T = np.asarray(T_1_2, np.float64)
    if not np.all(np.isfinite(T)):
        return dict(num_inliers=0, rmse=float("nan"), fitness=0.0, correspondence_distance=d)
    q1, q2 = _select_overlap(points_1, points_2, T, rc.overlap, overlap_margin(config, resolution))
    if min(q1.shape[0], q2.shape[0]) == 0:
        return dict(num_inliers=0, rmse=float("nan"), fitness=0.0, correspondence_distance=d)
    st = reg.evaluate_registration(q2, q1, T, d, cell_capacity=rc.cell_capacity)
    return dict(num_inliers=int(st.num_inliers), rmse=float(st.rmse), fitness=float(st.fitness),
                correspondence_distance=d)


def _fill_point_stats(info: dict, points_1, points_2, T_1_2, config: MergeConfig, resolution: float,
                      timings: dict):
    """``refine="multi"``: a pick born in the dense alignment (``_dense_candidates``) and kept
    (its local ICP step not used) has no ICP statistics; measure them at its transform
    (``point_stats``) so that the report's inliers / rmse / fitness always describe the result."""
    if np.isfinite(info["rmse"]):
        return
    info.update(_timed(timings, "evaluate", point_stats, points_1, points_2, T_1_2, config, resolution))
    info["stats_evaluated"] = True


# the dense alignment's status thresholds (``solve_alignment``'s defaults), for ranking candidates
_MIN_OVERLAP, _MIN_AGREEMENT = 0.15, 0.85


def _scores_and_plausible(problem, T_1_2s, min_overlap: float = _MIN_OVERLAP,
                          min_agreement: float = _MIN_AGREEMENT) -> tuple:
    """``(finest-level map losses (k,), pass the dense status checks (k,) bool)`` of the poses
    ``T_1_2s`` (a ``(k, 4, 4)`` array or a sequence of ``(4, 4)``), float64."""
    loss, overlap, agree = (np.asarray(a, np.float64) for a in
                            _reg().score_alignment(problem, np.asarray(T_1_2s, np.float64)))
    return loss, (overlap >= min_overlap) & (agree >= min_agreement)


def rank_by_map_agreement(m1: OccupancyMap, m2: OccupancyMap, result, *, problem=None, among=None,
                          min_agreement: float = _MIN_AGREEMENT, min_overlap: float = _MIN_OVERLAP):
    """``icp_multi``'s result (source = map 2's points, target = map 1's) with its best candidate
    re-chosen by the occupancy agreement of the two *maps* (``registration.score_alignment``:
    lowest finest-level dense loss among candidates whose ICP status is converged or
    max-iterations). Point inlier counts cannot see free space: on a rectangular room with a
    free interior, ``icp_multi`` alone picked the room turned by pi from 0.5, 1.7, -1.7 and 2.6
    rad yaw errors, the map loss picked the truth in all four (-0.332 vs -0.29).
    Candidates that pass the dense alignment's status checks (``solve_alignment``: at least
    ``min_overlap`` (default 0.15) of map 2's occupied points in map 1's known space,
    ``min_agreement`` (default 0.85) of those next to map 1's surfaces) are preferred; the
    others compete only when none passes.
    The loss alone can favour a wrong pose: on the simulated lab (0.05 m) poses turned by pi
    scored -0.29 to -0.32 against the truth's -0.27, with agreement 0.71-0.84 against 0.89.
    ``problem``: a ``prepare_alignment(m1, m2)`` to reuse (default: prepared here);
    ``among`` ``(k,)`` bool: choose only among these candidates (default: all).
    Returns ``(result with best / best_index replaced, map losses (k,) float64)``."""
    reg = _reg()
    cands = result.candidates
    T = np.asarray(cands.T_target_source, np.float64)
    problem = reg.prepare_alignment(m1, m2) if problem is None else problem
    loss, plausible = _scores_and_plausible(problem, T, min_overlap, min_agreement)
    status = np.asarray(cands.status)
    usable = np.isin(status, (0, 1)) & np.isfinite(loss)  # IcpResult: 0 converged, 1 max iterations
    if among is not None:
        usable &= np.asarray(among, bool)
    if not usable.any():
        return result, loss
    plausible &= usable
    if plausible.any():
        usable = plausible
    i = int(np.argmin(np.where(usable, loss, np.inf)))
    best = jax.tree_util.tree_map(lambda a: a[i], cands)
    return dataclasses.replace(result, best=best, best_index=np.int32(i)), loss


def _refine_dense(m1, m2, T_start, timings: dict, warnings: list, within_m: float | None = None):
    """``registration.align_dense`` from ``T_start``: ``(T_1_2, info dict, AlignResult)``.

    ``within_m``: the start is known to lie about this close to the answer (ICP's last
    correspondence distance), so the levels with coarser cells are skipped: their minima are
    biased by up to a cell, and from the simulated lab's ICP result (0.1 m, the demo) the
    levels from 0.8 m carried the pose 0.33 m / 0.07 rad off, into a minimum of the finer ones.
    Its result is used when it converged or ran out of iterations (status 0 / 1); on poor
    agreement, too little overlap or non-finite values the start transform is kept."""
    reg = _reg()
    start_level = 0
    if within_m is not None and np.isfinite(within_m):
        fits = m1.resolution * 2.0 ** np.asarray(reg.default_levels(m1.resolution)) <= within_m * (1 + 1e-6)
        start_level = int(np.argmax(fits)) if fits.any() else len(fits) - 1  # coarse to fine
    r = _timed(timings, "dense", reg.align_dense, m1, m2, np.asarray(T_start, np.float64),
               start_level=start_level)
    status = int(r.status)
    info = {"status": status, "converged": status == 0, "start_level": start_level,
            "restarted": bool(np.asarray(r.restarted)),
            "agreement": float(np.asarray(r.agreement)), "loss": float(np.asarray(r.loss)),
            "num_iterations": int(np.asarray(r.num_iterations))}
    if status in (0, 1):
        return np.asarray(r.T_1_2, np.float64), info, r
    warnings.append(f"dense alignment failed (status {status}, agreement {info['agreement']:.2f}); "
                    "the previous transform is kept")
    return np.asarray(T_start, np.float64), info, r


def icp_trace(points_1, points_2, T_1_2_init, resolution: float, config: MergeConfig | None = None,
              T_1_2_true=None, max_iterations: int | None = None) -> dict:
    """Replay ICP one iteration at a time (for convergence plots): the same correspondence
    schedule as ``registration.icp`` (each call is one jitted iteration at the current stage
    distance; the stage shrinks when ``sum |dT|`` falls below epsilon). The host loop rounds
    differently (float64 between iterations), which can flip a discrete correspondence, so
    the path may deviate from the jitted loop's late iterations (measured up to 0.14 m on the
    test scene); use it to see how ICP converges, and ``MergeReport.T_1_2`` for the result.

    ``points_1`` (target, map 1 frame) and ``points_2`` (source, map 2 frame): ``(n, 3)`` [m].
    Returns a dict: ``T_1_2`` ``(K+1, 4, 4)`` (index 0 = the initial guess); over iterations
    1..K ``rmse`` [m] and ``num_inliers`` at the updated transform within the stage distance
    ``distance`` [m]; with ``T_1_2_true`` also ``epsilon_r`` / ``epsilon_t`` ``(K+1,)``.
    The replay costs one correspondence search per iteration like the jitted loop plus one
    grid build per iteration (meant for figures, not production).
    """
    icp_mod, neighbors = _icp_modules()

    cfg = MergeConfig() if config is None else config
    rc = cfg.registration
    dists = icp_mod.stage_distances(resolution, rc.max_correspondence_distance,
                                    rc.min_correspondence_distance, rc.shrink_factor)
    eps = resolution / 60.0 if rc.transformation_epsilon is None else rc.transformation_epsilon
    final_eps = eps * 0.01
    p1 = np.asarray(points_1, np.float32).reshape(-1, 3)
    p2 = np.asarray(points_2, np.float32).reshape(-1, 3)
    # as registration.icp: the larger cloud is the model; the trace is inverted back
    swap = p2.shape[0] > p1.shape[0]
    src, sc = icp_mod.pad_points(p1 if swap else p2, name="points_2")
    tgt, tc = icp_mod.pad_points(p2 if swap else p1, name="points_1")
    table = neighbors.level_table_sizes(tgt.shape[0], dists)
    T = np.asarray(T_1_2_init, np.float64)
    if swap:
        T = np.linalg.inv(T)
    Ts, rmses, inl, ds = [T], [], [], []
    stage = 0
    limit = rc.max_iterations if max_iterations is None else int(max_iterations)
    for _ in range(limit):
        last = stage == len(dists) - 1
        thr = final_eps if last else eps
        # one iteration at the current stage: correspondences at T, closed-form update; the
        # returned rmse / inliers are measured at the updated transform
        r = icp_mod.icp_padded(src, sc, tgt, tc, T.astype(np.float32), dists[stage:stage + 1], thr,
                               final_epsilon=thr, min_inliers=rc.min_inliers, max_iterations=1,
                               cell_capacity=rc.cell_capacity, table_sizes=(table[stage],))
        if int(r.status) == icp_mod.STATUS_TOO_FEW_INLIERS:
            break
        T_new = np.asarray(r.T_target_source, np.float64)
        change = float(np.abs(T_new.astype(np.float32) - T.astype(np.float32)).sum())
        Ts.append(T_new)
        rmses.append(float(r.rmse))
        inl.append(int(r.num_inliers))
        ds.append(float(dists[stage]))
        T = T_new
        if change < thr:
            if last:
                break
            stage += 1
    Ts = np.stack(Ts)
    if swap:
        Ts = np.linalg.inv(Ts)
    out = dict(T_1_2=Ts, rmse=np.asarray(rmses), num_inliers=np.asarray(inl, np.int64),
               distance=np.asarray(ds))
    if T_1_2_true is not None:
        reg = _reg()
        out["epsilon_r"] = np.asarray(reg.rotation_error(Ts, np.asarray(T_1_2_true)))
        out["epsilon_t"] = np.asarray(reg.translation_error(Ts, np.asarray(T_1_2_true)))
    return out
