"""``icp_trace``: ICP replayed one iteration at a time on the host, for convergence figures."""

from __future__ import annotations

import numpy as np

from .. import registration as reg
from ..registration import Status
from ..registration import neighbors
from .config import MergeConfig

__all__ = ["icp_trace"]


def icp_trace(points_1, points_2, T_1_2_init, resolution: float, config: MergeConfig | None = None,
              T_1_2_true=None, max_iterations: int | None = None) -> dict:
    """Replay ICP one iteration at a time (for convergence plots): the same correspondence
    schedule as ``registration.icp`` (each call is one jitted iteration at the current stage
    distance; the stage shrinks when ``sum |dT|`` falls below epsilon). The host loop rounds
    differently (float64 between iterations), which can flip a discrete correspondence, so
    the path may deviate from the jitted loop's late iterations; use it to see how ICP
    converges, and ``MergeReport.T_1_2`` for the result.

    ``points_1`` (target, map 1 frame) and ``points_2`` (source, map 2 frame): ``(n, 3)`` [m].
    Returns a dict: ``T_1_2`` ``(K+1, 4, 4)`` (index 0 = the initial guess); over iterations
    1..K ``rmse`` [m] and ``num_inliers`` at the updated transform within the stage distance
    ``distance`` [m]; with ``T_1_2_true`` also ``epsilon_r`` / ``epsilon_t`` ``(K+1,)``
    (thesis eqs. 7.2 / 7.3). One correspondence search and one grid build per iteration:
    meant for figures, not production.
    """
    cfg = MergeConfig() if config is None else config
    rc = cfg.registration
    dists = reg.stage_distances(resolution, rc.max_correspondence_distance, rc.min_correspondence_distance,
                                rc.shrink_factor)
    eps = resolution / 60.0 if rc.transformation_epsilon is None else rc.transformation_epsilon
    final_eps = eps * 0.01
    p1 = np.asarray(points_1, np.float32).reshape(-1, 3)
    p2 = np.asarray(points_2, np.float32).reshape(-1, 3)
    # as registration.icp: the larger cloud is the model; the trace is inverted back
    swap = p2.shape[0] > p1.shape[0]
    src, sc = reg.pad_points(p1 if swap else p2, name="points_2")
    tgt, tc = reg.pad_points(p2 if swap else p1, name="points_1")
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
        r = reg.icp_padded(src, sc, tgt, tc, T.astype(np.float32), dists[stage:stage + 1], thr,
                           final_epsilon=thr, min_inliers=rc.min_inliers, max_iterations=1,
                           cell_capacity=rc.cell_capacity, table_sizes=(table[stage],))
        if Status(int(r.status)) is Status.TOO_FEW_INLIERS:
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
        out["epsilon_r"] = np.asarray(reg.rotation_error(Ts, np.asarray(T_1_2_true)))
        out["epsilon_t"] = np.asarray(reg.translation_error(Ts, np.asarray(T_1_2_true)))
    return out
