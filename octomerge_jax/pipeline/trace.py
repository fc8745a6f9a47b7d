"""``icp_trace``: every iteration of a merge's ICP run, for convergence figures."""

from __future__ import annotations

import numpy as np

from .. import registration as reg
from .clouds import icp_kwargs
from .config import MergeConfig

__all__ = ["icp_trace"]


def icp_trace(points_1, points_2, T_1_2_init, resolution: float, config: MergeConfig | None = None,
              T_1_2_true=None, max_iterations: int | None = None, result=None) -> dict:
    """The ICP run of a merge, iteration by iteration (``registration.icp_with_path``, with
    the settings the pipeline passes to ``registration.icp``): the same iterations as the run
    ``merge`` reports for these clouds, guess and ``config``, ending at its transform.

    ``points_1`` (target, map 1 frame) and ``points_2`` (source, map 2 frame): ``(n, 3)`` [m],
    the clouds ICP registered (``MergeReport.points_1`` / ``points_2``); ``T_1_2_init (4, 4)``
    its start. ``max_iterations``: overrides ``config.registration.max_iterations``.
    ``result``: the reported ``IcpResult``; when given, the run is checked to be that one.

    Returns a dict: ``T_1_2`` ``(K+1, 4, 4)`` float64 (index 0 = the initial guess, index K =
    the result); over iterations 1..K ``rmse`` [m] and ``num_inliers`` of the iteration's
    correspondences (those the iteration solved for, found at the transform it started from),
    ``distance`` [m] its stage's correspondence distance; ``num_iterations`` K and ``status``
    (``str(Status)``) as the run reports them; with ``T_1_2_true`` also ``epsilon_r`` /
    ``epsilon_t`` ``(K+1,)`` (thesis eqs. 7.2 / 7.3).

    Raises ``ValueError`` when ``result`` is given and the run is not that one (a different
    transform or number of iterations: the clouds, guess or settings differ from the merge's).
    """
    cfg = MergeConfig() if config is None else config
    if max_iterations is not None:
        cfg = cfg.replace(registration={"max_iterations": int(max_iterations)})
    p1 = np.asarray(points_1, np.float32).reshape(-1, 3)
    p2 = np.asarray(points_2, np.float32).reshape(-1, 3)
    r, path = reg.icp_with_path(p2, p1, np.asarray(T_1_2_init, np.float64), **icp_kwargs(cfg, resolution))
    K = int(r.num_iterations)
    T_end = np.asarray(r.T_target_source, np.float64)
    if result is not None:
        T_rep = np.asarray(result.T_target_source, np.float64)
        if int(result.num_iterations) != K or not np.array_equal(T_rep, T_end):
            raise ValueError(
                f"icp_trace: the run ({K} iterations) is not the reported one ({int(result.num_iterations)} "
                f"iterations, transform {np.abs(T_rep - T_end).max():.2e} apart): pass the clouds, guess and "
                "config the merge used")
    Ts = np.concatenate([np.asarray(T_1_2_init, np.float64)[None], np.asarray(path.T[:K], np.float64)])
    out = dict(T_1_2=Ts, rmse=np.asarray(path.rmse[:K], np.float64),
               num_inliers=np.asarray(path.num_inliers[:K], np.int64),
               distance=np.asarray(path.distance[:K], np.float64), num_iterations=K,
               status=str(reg.Status(int(r.status))))
    if T_1_2_true is not None:
        out["epsilon_r"] = np.asarray(reg.rotation_error(Ts, np.asarray(T_1_2_true)))
        out["epsilon_t"] = np.asarray(reg.translation_error(Ts, np.asarray(T_1_2_true)))
    return out
