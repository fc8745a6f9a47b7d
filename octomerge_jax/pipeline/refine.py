"""The registration step of a merge (thesis Alg. 1-3): ``register`` turns the initial guess
into the transform used, per ``config.registration.refine``, one function per mode:

- ``"none"``: the guess as is (``register_none``);
- ``"icp"``: ICP on the commonly mapped subsets (``overlap`` under the guess, Alg. 2 + 3;
  ``register_icp``), judged by ``accept_icp`` (the one ICP status policy), set aside where it
  slid out of the guess's basin (``globalreg.icp_left_start``);
- ``"multi"``: candidates from the yaw grid and / or the correlation search
  (``candidates.py``), picked by the agreement of the two *maps*, then a local ICP step
  (``ranking.py``; ``register_multi``);
- ``"dense"``: ``align_dense`` (the occupancy fields, gradient-based; ``register_dense``);
- ``"icp+dense"``: ICP, then the dense alignment from its result (``dense_after_icp``), then
  the GICP polish (``polish``, per ``registration.polish``);
- ``"global"``: no guess needed (``globalreg.register_global``; the default of ``merge``
  without a guess), then the dense alignment from its ICP result and the polish
  (``dense_after_global``).

The ICP modes' results are judged by ``globalreg.judge_local`` (a wrong basin: ``"failed"``).

Every mode reports ICP's fields (``status`` as ``str(Status)``, inliers, rmse, fitness); a
transform that did not come from ICP gets them measured at it (``point_stats``).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np

from .. import registration as reg
from .. import se3
from ..map import OccupancyMap, leaves_cache
from ..registration import Status
from .candidates import multi_candidates
from .clouds import (Clouds, align_info, dense_registration_info, icp_info, icp_kwargs, occupied_clouds, overlap_margin,
                     point_stats, select_overlap)
from .config import MergeConfig
from .globalreg import icp_left_start, judge_local, local_cell_sets, register_global
from .ranking import rank_and_refine
from .report import MergeError, Registration
from .timings import Timings

__all__ = ["DenseStep", "Overlap", "accept_icp", "dense_after_global", "dense_after_icp", "overlap_for_icp", "polish",
           "precompile_polish", "refine_dense", "register", "register_dense", "register_icp", "register_multi",
           "register_none"]


# the GICP polish (docs/design.md, "GICP polishes the default refinement"): correspondences within
# ICP's last distance, and a result that moves the samples farther than a voxel is no polish
GICP_DISTANCE_VOXELS, MAX_POLISH_SHIFT_VOXELS = 2.0, 1.0


class Overlap(NamedTuple):
    """The clouds ICP registers (``overlap_for_icp``), float32 [m], each in its map's frame."""

    points_1: np.ndarray  # (k1, 3) map 1's (ICP's target)
    points_2: np.ndarray  # (k2, 3) map 2's (ICP's source)
    counts: dict  # occupied_1, occupied_2, overlap_1, overlap_2 (point counts)


class DenseStep(NamedTuple):
    """``refine_dense``'s outcome."""

    T_1_2: np.ndarray  # (4, 4) float64: the dense result when usable, else the start
    info: dict  # JSON-ready: status (int Status code), converged, start_level, agreement, loss, ...
    result: object  # AlignResult


def register(m1: OccupancyMap, m2: OccupancyMap, T_1_2_init, config: MergeConfig,
             timings: Timings | None = None) -> Registration:
    """Thesis Alg. 1-3 on the host: the transform ``T_1_2`` (map 2's frame into map 1's) that
    ``config.registration.refine`` finds from ``T_1_2_init`` ``(4, 4)`` float64 (``None``
    only for ``"global"``: no guess).

    ``timings``: seconds per stage are added to it (default: a new, discarded one).
    Raises ``MergeError`` for empty clouds (``"empty"``), no overlap (``"no_overlap"``) or
    failed ICP (``"icp_failed"``, ``"not_converged"`` per ``on_not_converged``). The maps' host
    leaves are computed once for it (``map.leaves_cache``)."""
    timings = Timings() if timings is None else timings
    with leaves_cache():
        return _register(m1, m2, T_1_2_init, config, timings)


def _register(m1: OccupancyMap, m2: OccupancyMap, T_1_2_init, config: MergeConfig, timings: Timings) -> Registration:
    clouds = occupied_clouds(m1, m2, timings)
    refine = config.registration.refine
    if refine == "none":
        return register_none(clouds, T_1_2_init)
    if refine == "dense":
        return register_dense(m1, m2, clouds, T_1_2_init, config, timings)
    if refine == "multi":
        return register_multi(m1, m2, clouds, T_1_2_init, config, timings)
    if refine == "global":
        return dense_after_global(m1, m2, clouds, register_global(m1, m2, config, T_1_2_init, timings),
                                  config, timings)
    overlap = overlap_for_icp(clouds, T_1_2_init, config, m1.resolution, timings)
    with timings.stage("icp") as stage:
        result = stage.ready(reg.icp(overlap.points_2, overlap.points_1, T_1_2_init,
                                     **icp_kwargs(config, m1.resolution)))
    return register_icp(m1, m2, clouds, overlap, T_1_2_init, result, config, timings)


def register_none(clouds: Clouds, T_1_2_init) -> Registration:
    """``refine="none"``: the guess as is."""
    counts = {"occupied_1": int(clouds.points_1.shape[0]), "occupied_2": int(clouds.points_2.shape[0])}
    return Registration(T_1_2=T_1_2_init, converged=True, info=None, result=None, counts=counts,
                        points_1=clouds.points_1, points_2=clouds.points_2)


def register_dense(m1, m2, clouds: Clouds, T_1_2_init, config: MergeConfig, timings: Timings) -> Registration:
    """``refine="dense"``: the gradient-based alignment of the occupancy fields only
    (``refine_dense``), with ICP's point statistics measured at its result."""
    warnings: list[str] = []
    T_1_2, dense_info, result = refine_dense(m1, m2, T_1_2_init, timings, warnings)
    with timings.stage("evaluate"):
        stats = point_stats(clouds.points_1, clouds.points_2, T_1_2, config, m1.resolution)
    info = dense_registration_info(dense_info, stats)
    counts = {"occupied_1": int(clouds.points_1.shape[0]), "occupied_2": int(clouds.points_2.shape[0])}
    return Registration(T_1_2=T_1_2, converged=info["converged"], info=info, result=result, counts=counts,
                        points_1=clouds.points_1, points_2=clouds.points_2, warnings=tuple(warnings))


def overlap_for_icp(clouds: Clouds, T_1_2_init, config: MergeConfig, resolution: float,
                    timings: Timings) -> Overlap:
    """The commonly mapped subsets under the guess (thesis Alg. 2; ``refine="multi"``: the
    whole clouds, so that the search is not pre-cut by a poor guess), timed as ``overlap``.
    Raises ``MergeError`` ``"empty"`` / ``"no_overlap"`` below ``min_overlap_points``."""
    rc = config.registration
    p1, p2 = clouds
    for name, p in (("map 1", p1), ("map 2", p2)):
        if p.shape[0] < rc.min_overlap_points:
            raise MergeError(f"{name} has only {p.shape[0]} occupied voxels: nothing to register "
                             "(use --refine none to merge with the guess as is)", "empty")
    method = "none" if rc.refine == "multi" else rc.overlap
    with timings.stage("overlap"):
        q1, q2 = select_overlap(p1, p2, T_1_2_init, method, overlap_margin(config, resolution))
    counts = {"occupied_1": int(p1.shape[0]), "occupied_2": int(p2.shape[0]),
              "overlap_1": int(q1.shape[0]), "overlap_2": int(q2.shape[0])}
    if min(q1.shape[0], q2.shape[0]) < rc.min_overlap_points:
        raise MergeError(
            f"no overlap: under the initial guess only {q1.shape[0]} points of map 1 and "
            f"{q2.shape[0]} of map 2 lie in commonly mapped space (need "
            f"{rc.min_overlap_points}); check the guess (x y z roll pitch yaw, radians) or "
            f"leave the guess out to search without one", "no_overlap")
    return Overlap(q1, q2, counts)


def register_icp(m1, m2, clouds: Clouds, overlap: Overlap, T_1_2_init, result, config: MergeConfig,
                 timings: Timings) -> Registration:
    """``refine="icp"`` / ``"icp+dense"`` after ICP (``result``, an ``IcpResult`` with source =
    map 2's overlap points): ``accept_icp``'s policy; then a result that slid out of the
    guess's basin (``globalreg.icp_left_start``, on the maps' ``globalreg.local_cell_sets``) is
    set aside (``info["icp_left_start"]``): ``"icp"`` keeps the guess, with a warning, and
    ``"icp+dense"`` runs the dense alignment from the guess; otherwise ``"icp+dense"`` runs it
    from ICP's result (``dense_after_icp``). The transform is made rigid
    (``se3.project_to_rigid``) and judged on the same cell sets (``globalreg.judge_local``: a
    wrong basin is ``"failed"``)."""
    info = icp_info(result)
    T_1_2, warnings = accept_icp(result, info, T_1_2_init, config)
    with timings.stage("verify"):
        sets = local_cell_sets(m1, m2, clouds)
        left, net_start, net_icp = icp_left_start(sets, T_1_2_init, T_1_2)
    if left:
        info["icp_left_start"] = {"net_start": net_start, "net_icp": net_icp}
        T_1_2 = np.asarray(T_1_2_init, np.float64)
        warnings.clear()  # they speak of ICP's transform, which is not used
        if config.registration.refine != "icp+dense":
            warnings.append(f"ICP slid out of the guess's basin (net agreement {net_start:g} -> {net_icp:g} "
                            "coarse cells); the guess is kept: try --refine icp+dense")
    if config.registration.refine == "icp+dense":
        T_1_2, info = dense_after_icp(m1, m2, clouds, T_1_2, T_1_2_init, info, config, timings, warnings,
                                      from_guess=left)
        T_1_2, info = polish(m1, m2, clouds.points_1, clouds.points_2, T_1_2, info, config, timings, warnings)
    registration = Registration(T_1_2=se3.project_to_rigid(T_1_2), converged=info["converged"], info=info,
                                result=result, counts=overlap.counts, points_1=overlap.points_1,
                                points_2=overlap.points_2, warnings=tuple(warnings))
    return judge_local(m1, m2, clouds, registration, timings, sets)


# the top-level figures that the local step's result replaces when it is used
_LOCAL_FIELDS = ("converged", "status", "num_iterations", "num_inliers", "rmse", "fitness", "correspondence_distance")


def register_multi(m1, m2, clouds: Clouds, T_1_2_init, config: MergeConfig, timings: Timings) -> Registration:
    """``refine="multi"``: candidates (``multi_candidates``), the pick by map agreement and
    the local step (``rank_and_refine``), ICP's statistics measured at a pick born in the dense
    alignment, ``accept_icp``'s policy; the transform made rigid."""
    overlap = overlap_for_icp(clouds, T_1_2_init, config, m1.resolution, timings)
    kw = icp_kwargs(config, m1.resolution)
    q1, q2 = overlap.points_1, overlap.points_2
    found = multi_candidates(m1, m2, q1, q2, T_1_2_init, config, kw, timings)
    point_best = int(found.result.best_index)
    pick = rank_and_refine(m1, m2, q1, q2, found.result, found.origin == "yaw_grid", config, kw,
                           timings, found.problem, found.origin)
    result = pick.result
    info = {**icp_info(result.best), "best_index": int(result.best_index),
            "num_hypotheses": int(np.asarray(result.hypotheses).shape[0]),
            "num_basins": int(np.unique(np.asarray(result.basin)).size),
            "point_best_index": point_best, "map_loss": [round(float(v), 5) for v in pick.map_loss],
            "local": pick.info}
    best = result.best
    if pick.local is not None:  # the local step's result is used: its figures are reported
        best = pick.local
        local_fields = icp_info(best)
        info.update({key: local_fields[key] for key in _LOCAL_FIELDS})
    if not np.isfinite(info["rmse"]):  # a pick from the dense alignment has no ICP statistics
        with timings.stage("evaluate"):
            info.update(point_stats(q1, q2, best.T_target_source, config, m1.resolution))
        info["stats_evaluated"] = True
    T_1_2, warnings = accept_icp(best, info, T_1_2_init, config)
    return Registration(T_1_2=se3.project_to_rigid(T_1_2), converged=info["converged"], info=info,
                        result=result, counts=overlap.counts, points_1=overlap.points_1,
                        points_2=overlap.points_2, warnings=tuple(warnings))


def accept_icp(best, info: dict, T_1_2_init, config: MergeConfig) -> tuple[np.ndarray, list[str]]:
    """The ICP status policy: ``(T_1_2 (4, 4) float64, warnings)`` from ICP's result ``best``
    (``info``: its figures, ``icp_info``). Too few inliers or a non-finite transform raise
    ``MergeError("icp_failed")``; a result that did not converge follows
    ``registration.on_not_converged`` (``"error"`` raises ``MergeError("not_converged")``,
    ``"use_initial"`` returns the guess, ``"warn"`` the result), with a warning."""
    rc = config.registration
    T_icp = np.asarray(best.T_target_source, np.float64)
    if Status(int(best.status)) is Status.TOO_FEW_INLIERS or not np.all(np.isfinite(T_icp)):
        raise MergeError(
            f"ICP failed: only {info['num_inliers']} correspondences within "
            f"{info['correspondence_distance']:.3g} m (need {rc.min_inliers}); the guess is "
            f"probably too far off: try --refine multi or a better guess", "icp_failed")
    if info["converged"]:
        return T_icp, []
    msg = (f"ICP did not converge within {info['num_iterations']} iterations (rmse "
           f"{info['rmse']:.4f} m, correspondence distance {info['correspondence_distance']:.3g} m)")
    if rc.on_not_converged == "error":
        raise MergeError(msg + "; raise registration.max_iterations or set "
                         "on_not_converged = \"warn\"", "not_converged")
    if rc.on_not_converged == "use_initial":
        return np.asarray(T_1_2_init, np.float64), [msg + "; merged with the initial guess instead"]
    return T_icp, [msg + "; its last transform is used"]


def dense_after_icp(m1, m2, clouds: Clouds, T_icp, T_1_2_init, info: dict, config: MergeConfig,
                    timings: Timings, warnings: list[str], from_guess: bool = False) -> tuple[np.ndarray, dict]:
    """``refine="icp+dense"``: the dense alignment from ICP's transform ``T_icp``, from the
    level of ICP's last correspondence distance on when ICP converged or ran out of iterations
    (it was still refining at that distance; ``from_guess``: ``T_icp`` is the guess, all
    levels); if its result is not usable, from the initial guess; if that fails too, ``T_icp``
    is kept and both failures go to ``warnings``. Returns ``(T_1_2, info with the dense
    figures under "dense")``."""
    retry: list[str] = []
    within = info["correspondence_distance"] if Status[info["status"].upper()].usable and not from_guess else None
    T_1_2, dense_info, _ = refine_dense(m1, m2, T_icp, timings, retry, within_m=within)
    if not Status(dense_info["status"]).usable:
        T_1_2, dense_info, _ = refine_dense(m1, m2, T_1_2_init, timings, retry)
        dense_info["started_from"] = "initial guess (dense from the ICP result failed)"
        if not Status(dense_info["status"]).usable:
            T_1_2 = T_icp
            warnings.extend(retry)
    _add_point_stats(dense_info, clouds, T_1_2, config, m1.resolution, timings)
    return T_1_2, {**info, "dense": dense_info}


def dense_after_global(m1, m2, clouds: Clouds, found: Registration, config: MergeConfig,
                       timings: Timings) -> Registration:
    """``refine="global"``'s last step: the dense alignment from the pose ``register_global``
    found (``found``), at the levels within its ICP's last correspondence distance, as
    ``"icp+dense"`` ends (``docs/design.md``, "Dense alignment ends the guess-free mode").
    Run when the verdict is ``"ok"`` or ``"ambiguous"`` and ICP ended usable (otherwise
    ``found`` is returned as is). Its figures go to ``info["dense"]``; its result is used when
    usable (with ICP's point statistics measured there), else ``found``'s pose is kept and a
    warning added. Verdict, confidence and candidates stay ``found``'s."""
    info = found.info or {}
    if info.get("verdict") not in ("ok", "ambiguous") or found.result is None \
            or not Status[info["status"].upper()].usable:
        return found
    warnings = list(found.warnings)
    T_1_2, dense_info, _ = refine_dense(m1, m2, found.T_1_2, timings, warnings,
                                        within_m=info["correspondence_distance"])
    _add_point_stats(dense_info, clouds, T_1_2, config, m1.resolution, timings)
    T_1_2, info = polish(m1, m2, clouds.points_1, clouds.points_2, T_1_2, {**info, "dense": dense_info}, config,
                         timings, warnings)
    return dataclasses.replace(found, T_1_2=se3.project_to_rigid(T_1_2), info=info, warnings=tuple(warnings))


def polish(m1, m2, points_1, points_2, T_start, info: dict, config: MergeConfig, timings: Timings,
           warnings: list[str]) -> tuple[np.ndarray, dict]:
    """The last step of ``"icp+dense"`` and ``"global"`` (``registration.polish = "gicp"``):
    ``registration.gicp`` from ``T_start`` of map 2's ``points_2`` onto map 1's ``points_1``
    (``(n, 3)`` [m], all the occupied voxels of each map: the thesis's bounding-box overlap
    leaves out matching points, which the rotation needs as lever arms), correspondences within
    ``GICP_DISTANCE_VOXELS`` (timed as ``gicp``). Its result (finite: ``gicp`` returns the
    start otherwise) is used when it matched at least ``min_inliers`` samples and moved them
    less than ``MAX_POLISH_SHIFT_VOXELS`` on average (a polish, not a search); otherwise
    ``T_start`` is kept with a warning. Returns
    ``(T_1_2 (4, 4) float64, info with the figures under "gicp")``
    (``docs/design.md``, "GICP polishes the default refinement")."""
    if not _polishes(config, points_1, points_2):
        return np.asarray(T_start, np.float64), info
    res = m1.resolution
    with timings.stage("gicp"):
        r = reg.gicp(m1, m2, points_1, points_2, T_start, max_correspondence_distance=GICP_DISTANCE_VOXELS * res)
    used = r.num_inliers >= config.registration.min_inliers and r.shift < MAX_POLISH_SHIFT_VOXELS * res
    figures = {"used": used, "converged": r.converged, "num_iterations": r.num_iterations,
               "num_inliers": r.num_inliers, "num_samples": r.num_samples, "rmse": r.rmse, "shift": r.shift}
    if not used:
        warnings.append(f"GICP polish set aside (moved the pose {r.shift:.3g} m, {r.num_inliers} of {r.num_samples} "
                        "samples matched); the previous transform is kept")
    return np.asarray(r.T_1_2 if used else T_start, np.float64), {**info, "gicp": figures}


def _polishes(config: MergeConfig, points_1, points_2) -> bool:
    """``polish`` runs GICP on these clouds: the config asks for it and both clouds hold at least
    ``min_inliers`` (and ``GICP_MIN_POINTS``) points."""
    fewest = max(config.registration.min_inliers, reg.GICP_MIN_POINTS)
    return config.registration.polish == "gicp" and min(len(points_1), len(points_2)) >= fewest


def precompile_polish(m1, m2, T_start, config: MergeConfig) -> bool:
    """Make ready the GICP program ``polish`` would run from ``T_start`` on the maps' occupied
    clouds (``registration.precompile_gicp``) without running it: ``False`` when the config runs
    no polish (then no cloud is computed), the clouds are too small or no kernel store is open
    (``cli.compile_ahead``)."""
    if config.registration.refine not in ("icp+dense", "global") or config.registration.polish != "gicp":
        return False
    clouds = occupied_clouds(m1, m2, Timings())
    if not _polishes(config, clouds.points_1, clouds.points_2):
        return False
    return reg.precompile_gicp(m1, m2, clouds.points_1, clouds.points_2, T_start,
                               max_correspondence_distance=GICP_DISTANCE_VOXELS * m1.resolution)


def _add_point_stats(dense_info: dict, clouds: Clouds, T_1_2, config: MergeConfig, resolution: float,
                     timings: Timings) -> None:
    """When the dense result is used (its status usable), ICP's point statistics measured at
    it (``point_stats``, timed as ``evaluate``) go into ``dense_info``."""
    if Status(dense_info["status"]).usable:
        with timings.stage("evaluate"):
            dense_info.update(point_stats(clouds.points_1, clouds.points_2, T_1_2, config, resolution))


def refine_dense(m1, m2, T_start, timings: Timings, warnings: list[str],
                 within_m: float | None = None) -> DenseStep:
    """``registration.align_dense`` from ``T_start`` (timed as ``dense``).

    ``within_m`` [m]: the start is known to lie about this close to the answer (ICP's last
    correspondence distance), so the levels with coarser cells are left out (neither prepared
    nor solved; ``docs/design.md``, "Dense alignment ends the default refinement"). Its result
    is used when its status is usable (``Status.usable``); otherwise the start is kept and a
    warning appended to ``warnings``."""
    levels = tuple(reg.default_levels(m1.resolution))
    start_level = 0
    if within_m is not None and np.isfinite(within_m):
        fits = m1.resolution * 2.0 ** np.asarray(levels) <= within_m * (1 + 1e-6)
        start_level = int(np.argmax(fits)) if fits.any() else len(fits) - 1  # coarse to fine
    with timings.stage("dense") as stage:
        r = stage.ready(reg.align_dense(m1, m2, np.asarray(T_start, np.float64), levels=levels[start_level:]))
    info = {**align_info(r), "start_level": start_level}
    status = Status(info["status"])
    if status.usable:
        return DenseStep(np.asarray(r.T_1_2, np.float64), info, r)
    warnings.append(f"dense alignment failed (status {int(status)}, agreement {info['agreement']:.2f}); "
                    "the previous transform is kept")
    return DenseStep(np.asarray(T_start, np.float64), info, r)
