"""The point clouds registration works on (thesis Alg. 1-2) and ICP's settings and figures:
``occupied_clouds``, ``select_overlap``, ``overlap_margin``, ``icp_kwargs``, ``icp_info``,
and ``point_stats``."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .. import registration as reg
from ..map import OccupancyMap, bucket_capacity
from ..registration import Status
from .config import MergeConfig
from .timings import Timings

__all__ = ["Clouds", "VOXEL_OVERLAP_VOXELS", "align_info", "dense_registration_info", "icp_info", "icp_kwargs",
           "occupied_clouds", "overlap_margin", "point_stats", "select_overlap", "stage_epsilon"]

VOXEL_OVERLAP_VOXELS = 3.0

class Clouds(NamedTuple):
    """The occupied-voxel centres of both maps (thesis Alg. 1), float32 [m], each in its map's frame."""

    points_1: np.ndarray  # (n1, 3)
    points_2: np.ndarray  # (n2, 3)


def occupied_clouds(m1: OccupancyMap, m2: OccupancyMap, timings: Timings) -> Clouds:
    """Both maps' occupied leaf centres (``registration.occupied_points``), timed as
    ``occupied_points``."""
    with timings.stage("occupied_points") as stage:
        p1 = stage.ready(reg.occupied_points(m1))
    with timings.stage("occupied_points") as stage:
        p2 = stage.ready(reg.occupied_points(m2))
    return Clouds(np.asarray(p1, np.float32).reshape(-1, 3), np.asarray(p2, np.float32).reshape(-1, 3))


def overlap_margin(cfg: MergeConfig, resolution: float) -> float | None:
    """The overlap slack [m]: ``registration.overlap_margin`` if set; else, for ``"voxel"``,
    ``3 * resolution`` (a point is kept if the other cloud has a point within 3 voxels under
    the guess); for ``"bbox"`` ``None`` (the thesis's 1 m, ``registration.overlap``'s default)."""
    m = cfg.registration.overlap_margin
    if m is not None:
        return float(m)
    if cfg.registration.overlap == "voxel":
        return VOXEL_OVERLAP_VOXELS * float(resolution)
    return None


def select_overlap(points_1, points_2, T_1_2, method: str, margin: float | None):
    """Overlap subsets ``(q1 (k1, 3), q2 (k2, 3))`` float32 (each in its own frame) of the two
    occupied clouds under ``T_1_2`` (``registration.overlap``, thesis Alg. 2); ``method``
    ``"none"`` returns the clouds as they are. The clouds go to the jitted kernel padded to
    their capacity buckets, so one compiled kernel serves every cloud size of a bucket."""
    if method == "none":
        return points_1, points_2
    kw = {} if margin is None else {("radius" if method == "voxel" else "margin"): margin}
    p1, n1 = reg.pad_points_host(points_1, bucket_capacity(len(points_1)), "points_1")
    p2, n2 = reg.pad_points_host(points_2, bucket_capacity(len(points_2)), "points_2")
    mask_1, mask_2, *_ = reg.overlap(p1, p2, T_1_2, method=method, count_1=n1, count_2=n2, **kw)
    return (p1[:n1][np.asarray(mask_1)[:n1]].astype(np.float32),
            p2[:n2][np.asarray(mask_2)[:n2]].astype(np.float32))


def icp_kwargs(cfg: MergeConfig, resolution: float) -> dict:
    """The keyword arguments of ``registration.icp`` / ``icp_multi`` from the config."""
    r = cfg.registration
    return dict(resolution=resolution, max_correspondence_distance=r.max_correspondence_distance,
                min_correspondence_distance=r.min_correspondence_distance,
                shrink_factor=r.shrink_factor, transformation_epsilon=r.transformation_epsilon,
                max_iterations=r.max_iterations, cell_capacity=r.cell_capacity,
                min_inliers=r.min_inliers, coarse_matching=r.coarse_matching)


def stage_epsilon(cfg: MergeConfig, resolution: float) -> float:
    """ICP's stage threshold on the change of the transform (sum of ``|dT|``): the configured
    ``transformation_epsilon``, else ``registration.icp``'s default ``resolution / 60``."""
    eps = cfg.registration.transformation_epsilon
    return float(resolution) / 60.0 if eps is None else float(eps)


def align_info(r) -> dict:
    """An ``AlignResult``'s figures for the report, as ``icp_info`` gives ICP's: ``status``
    (``int(Status)``), ``converged``, ``restarted``, ``agreement``, ``loss``,
    ``num_iterations``."""
    status = Status(int(r.status))
    return {"status": int(status), "converged": status is Status.CONVERGED, "restarted": bool(np.asarray(r.restarted)),
            "agreement": float(np.asarray(r.agreement)), "loss": float(np.asarray(r.loss)),
            "num_iterations": int(np.asarray(r.num_iterations))}


def dense_registration_info(dense: dict, stats: dict) -> dict:
    """The figures of a registration whose transform is the dense alignment's: its status in
    ICP's fields (``converged``, ``status`` as ``str(Status)``, ``num_iterations``), ICP's point
    statistics measured at it (``stats``, ``point_stats``) and the dense figures ``dense``
    (``align_info``) under ``"dense"``."""
    return {"converged": dense["converged"], "status": str(Status(dense["status"])),
            "num_iterations": dense["num_iterations"], **stats, "dense": dense}


def icp_info(r) -> dict:
    """An ``IcpResult``'s figures for the report (JSON-ready; ``status`` as ``str(Status)``)."""
    return dict(
        converged=bool(r.converged),
        status=str(Status(int(r.status))),
        num_iterations=int(r.num_iterations),
        num_inliers=int(r.num_inliers),
        rmse=float(r.rmse),
        fitness=float(r.fitness),
        correspondence_distance=float(r.correspondence_distance),
        grid_overflow=int(r.grid_overflow),
        swapped=bool(r.swapped),
    )


def point_stats(points_1, points_2, T_1_2, config: MergeConfig, resolution: float) -> dict:
    """``num_inliers``, ``rmse`` [m], ``fitness`` and ``correspondence_distance`` [m] of map 2's
    occupied points placed by ``T_1_2`` against map 1's (``registration.evaluate_registration``
    on the commonly mapped subsets under ``T_1_2``, ``registration.overlap``, within ICP's floor
    distance, 2 res by default): the figures ICP reports at its result, for a transform that
    did not come from ICP (the dense alignment)."""
    rc = config.registration
    d = float(reg.stage_distances(resolution, rc.max_correspondence_distance, rc.min_correspondence_distance,
                                  rc.shrink_factor)[-1])
    T = np.asarray(T_1_2, np.float64)
    if not np.all(np.isfinite(T)):
        return dict(num_inliers=0, rmse=float("nan"), fitness=0.0, correspondence_distance=d)
    q1, q2 = select_overlap(points_1, points_2, T, rc.overlap, overlap_margin(config, resolution))
    if min(q1.shape[0], q2.shape[0]) == 0:
        return dict(num_inliers=0, rmse=float("nan"), fitness=0.0, correspondence_distance=d)
    # padded as the whole clouds: the program of ``explained_fraction`` (guess-free), compiled once
    st = reg.evaluate_registration(q2, q1, T, d, cell_capacity=rc.cell_capacity,
                                   source_capacity=points_2.shape[0], target_capacity=points_1.shape[0])
    return dict(num_inliers=int(st.num_inliers), rmse=float(st.rmse), fitness=float(st.fitness),
                correspondence_distance=d)
