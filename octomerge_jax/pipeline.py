"""The merge pipeline (thesis Ch. 6): ``merge``, ``merge_many`` and ``MergeReport``.

::

    map 1 ──occupied_points──┐                       (Alg. 1)
    map 2 ──occupied_points──┴─ overlap(T_1_2_init)    (Alg. 2, "voxel" or thesis "bbox")
                                 └─ icp / icp_multi -> T_1_2          (Alg. 3)
    map 2 ──transform_map(T_1_2)──> map 2 in frame 1                  (Alg. 4-7)
    map 1, map 2 in frame 1 ──fuse──> merged                          (Alg. 8)

Frames: ``T_1_2`` maps points of map 2's frame into map 1's frame (``T_m1_m2``); the merged map
is in map 1's frame with map 1's parameters. Every stage is a jitted function from the modules
it names; this module plans on the host, times each stage (``block_until_ready``) and turns
statuses into a ``MergeReport`` or, for problems the user must fix (mixed resolutions, no
overlap, ICP without enough inliers, a NaN guess), a ``MergeError`` whose ``kind`` says which.

The ICP result is judged on the host by ``config.registration.on_not_converged``: ICP that ran
out of iterations is usually close (it is still shrinking its correspondence distance), so the
default is to use it and say so in ``report.warnings``; too few inliers means the guess put the
maps where they do not overlap, which is always an error (refine ``"multi"`` or a better guess
helps).
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
import time
from typing import Sequence

import jax
import numpy as np

from .config import MergeConfig, validate
from .map import OccupancyMap, bucket_capacity

__all__ = [
    "MergeError",
    "MergeReport",
    "merge",
    "merge_many",
    "icp_trace",
    "resample_to_resolution",
    "transform_from_xyz_rpy",
]

_NUM_LIST = re.compile(r"\[\s*((?:-?[0-9.eE+-]+|null)(?:,\s*(?:-?[0-9.eE+-]+|null))*)\s*\]")

ICP_STATUS_NAMES = {0: "converged", 1: "max_iterations", 2: "too_few_inliers"}
DENSE_STATUS_NAMES = {0: "converged", 1: "max_iterations", 2: "poor_agreement", 3: "low_overlap", 4: "not_finite"}


class MergeError(ValueError):
    """A merge the pipeline refuses, with ``kind`` one of ``"resolution"``, ``"transform"``,
    ``"empty"``, ``"no_overlap"``, ``"icp_failed"``, ``"not_converged"`` (the CLI maps kinds
    to exit codes). ``report`` holds the partial ``MergeReport`` when there is one."""

    def __init__(self, message: str, kind: str, report: "MergeReport | None" = None):
        super().__init__(message)
        self.kind = kind
        self.report = report


@dataclasses.dataclass(frozen=True)
class MergeReport:
    """What a merge did (host values; ``to_json()`` writes the fields below by these names).

    - ``T_1_2_init``, ``T_1_2``: ``(4, 4)`` float64, the initial guess and the transform used
      (after refinement), mapping map 2's frame into map 1's [m].
    - ``T_1_2_true``: ground truth if given, else ``None``.
    - ``refine``: ``"icp"``, ``"multi"``, ``"dense"``, ``"icp+dense"`` or ``"none"``.
    - ``icp``: the ICP result as a dict (``converged``, ``status``, ``num_iterations``,
      ``num_inliers``, ``rmse`` [m], ``fitness``, ``correspondence_distance`` [m], ...; for
      ``"dense"`` the same keys for the dense alignment (status names ``DENSE_STATUS_NAMES``,
      the point statistics measured at its transform by ``point_stats``) and its own figures
      under ``dense`` (for ``"icp+dense"``: ICP's fields, and under ``dense`` the dense
      alignment's with the point statistics at the transform used); for
      ``"multi"`` also ``best_index`` (the candidate chosen by map agreement,
      ``rank_by_map_agreement``), ``point_best_index`` (``icp_multi``'s own choice),
      ``map_loss`` per candidate, ``num_hypotheses``, ``num_basins``: the ICP runs left after
      merging hypotheses that reached one basin, and ``local``: the local ICP on the commonly
      mapped subsets from the chosen candidate, ``used`` when it lowered the map loss, whose
      convergence, iterations, inliers and rmse the top-level fields then report; a pick
      from the dense alignment has its point statistics measured at its transform,
      ``stats_evaluated``),
      ``None`` for ``refine="none"``.
    - ``epsilon_r_init``, ``epsilon_t_init``, ``epsilon_r``, ``epsilon_t``: thesis eqs. 7.2 /
      7.3 before / after refinement when ``T_1_2_true`` is given (else ``None``).
    - ``displacement_init``, ``displacement``: mean distance [m] between map 2's occupied leaf
      centres placed by the guess / the result and by ``T_1_2_true`` (else ``None``). Unlike
      eps_t it does not grow with the distance of the map from its frame's origin.
    - ``counts``: leaves of both inputs and of the result, occupied and overlap points, fuse
      case counts (``FuseReport.host()``).
    - ``timings``: seconds per stage (``occupied_points``, ``overlap``, ``icp``, ``transform``,
      ``fuse``, ``total``; the CLI adds ``load`` and ``save``).
    - ``resolution`` [m], ``warnings`` (human-readable), ``status`` (``"ok"`` or
      ``"not_converged"``).
    Not serialised: ``icp_result`` (the ``IcpResult`` / ``IcpMultiResult`` pytree) and the
    overlap clouds ``points_1`` / ``points_2`` (``(n, 3)`` float32, each map's frame) used
    for figures.
    """

    T_1_2_init: np.ndarray
    T_1_2: np.ndarray
    refine: str
    icp: dict | None
    epsilon_r_init: float | None
    epsilon_t_init: float | None
    epsilon_r: float | None
    epsilon_t: float | None
    counts: dict
    timings: dict
    resolution: float
    T_1_2_true: np.ndarray | None = None
    warnings: tuple[str, ...] = ()
    status: str = "ok"
    displacement_init: float | None = None
    displacement: float | None = None
    icp_result: object = dataclasses.field(default=None, repr=False, compare=False)
    points_1: np.ndarray | None = dataclasses.field(default=None, repr=False, compare=False)
    points_2: np.ndarray | None = dataclasses.field(default=None, repr=False, compare=False)

    _JSON_FIELDS = ("status", "refine", "resolution", "T_1_2_init", "T_1_2", "T_1_2_true", "icp",
                    "epsilon_r_init", "epsilon_t_init", "epsilon_r", "epsilon_t", "displacement_init",
                    "displacement", "counts", "timings", "warnings")

    def to_dict(self) -> dict:
        """JSON-ready dict (matrices as nested lists, row-major)."""
        out = {}
        for name in self._JSON_FIELDS:
            out[name] = _jsonable(getattr(self, name))
        return out

    def to_json(self, path=None, indent: int = 2) -> str:
        """The report as JSON text; also written (atomically) to ``path`` if given."""
        text = json.dumps(self.to_dict(), indent=indent)
        # one line per matrix row / short number list, instead of one line per number
        text = _NUM_LIST.sub(lambda m: "[" + ", ".join(x.strip() for x in m.group(1).split(",")) + "]",
                             text) + "\n"
        if path is not None:
            from ._fileutil import atomic_write_bytes

            atomic_write_bytes(path, text.encode())
        return text

    def with_timings(self, **extra) -> "MergeReport":
        return dataclasses.replace(self, timings={**self.timings, **extra})

    def summary(self) -> str:
        """A few human-readable lines (what the CLI prints)."""
        lines = []
        if self.icp is not None:
            i = self.icp
            what = "dense alignment" if self.refine == "dense" else f"ICP ({self.refine})"
            lines.append(f"{what}: {i['status']} after {i['num_iterations']} iterations, "
                         f"{i['num_inliers']} inliers, rmse {i['rmse']:.4f} m, fitness {i['fitness']:.2f}")
        if self.epsilon_r_init is not None:
            lines.append(f"epsilon_r {self.epsilon_r_init:.4f} -> {self.epsilon_r:.4f}   "
                         f"epsilon_t {self.epsilon_t_init:.4f} -> {self.epsilon_t:.4f} m  (thesis eqs. 7.2/7.3)")
        if self.displacement_init is not None:
            lines.append(f"map 2 occupied voxels off the truth by {self.displacement_init:.4f} -> "
                         f"{self.displacement:.4f} m (mean)")
        c = self.counts
        lines.append(f"leaves: map1 {c.get('leaves_1', 0):,} + map2 {c.get('leaves_2', 0):,} "
                     f"-> merged {c.get('leaves_merged', 0):,}")
        lines.append("time: " + ", ".join(f"{k} {v:.2f}s" for k, v in self.timings.items()))
        lines.extend(f"warning: {w}" for w in self.warnings)
        return "\n".join(lines)


def _jsonable(v):
    if v is None or isinstance(v, (bool, str)):
        return v
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, (np.ndarray, jax.Array)):
        return _jsonable(np.asarray(v).tolist())
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        f = float(v)
        return f if math.isfinite(f) else None
    return v


# ----------------------------------------------------------------------------- helpers


def transform_from_xyz_rpy(x: float = 0.0, y: float = 0.0, z: float = 0.0, roll_rad: float = 0.0,
                           pitch_rad: float = 0.0, yaw_rad: float = 0.0) -> np.ndarray:
    """``(4, 4)`` float64 from a translation [m] and roll/pitch/yaw [rad] (``R = Rz Ry Rx``,
    OctoMap's ``Pose6D``), as the thesis's command line ``x y z roll pitch yaw``. Raises
    ``ValueError`` naming the value if one is NaN or infinite."""
    vals = dict(x=x, y=y, z=z, roll=roll_rad, pitch=pitch_rad, yaw=yaw_rad)
    for name, v in vals.items():
        if not math.isfinite(float(v)):
            raise MergeError(f"initial guess: {name} = {v} is not a finite number", "transform")
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    R = np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                  [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                  [-sp, cp * sr, cp * cr]])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = (x, y, z)
    return T


def _check_T(T, name: str) -> np.ndarray:
    from .resample import check_rigid_transform

    try:
        return check_rigid_transform(T, name)
    except ValueError as err:
        raise MergeError(str(err), "transform") from None


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


def _epsilons(T_est, T_true):
    reg = _reg()
    return float(reg.rotation_error(T_est, T_true)), float(reg.translation_error(T_est, T_true))


def _displacements(m2: OccupancyMap, T_true, *Ts, max_points: int = 100_000) -> tuple:
    """Mean ``point_displacement`` [m] of map 2's occupied leaf centres (an even subsample of
    at most ``max_points``) under each of ``Ts`` against ``T_true``; ``None``s without truth."""
    if T_true is None:
        return (None,) * len(Ts)
    L = m2.leaves()
    p = L.centers[L.log_odds > m2.params.occupancy_threshold_log_odds]
    if len(p) == 0:
        p = L.centers
    p = p[:: max(1, -(-len(p) // max_points))]
    if len(p) == 0:
        return (None,) * len(Ts)
    # NumPy float64 (registration.point_displacement on the host): map coordinates can be
    # kilometres from the origin, where float32 would lose ~1e-4 m
    Ts, T_true = np.asarray(Ts, np.float64), np.asarray(T_true, np.float64)
    d = (Ts[:, None, :3, :3] - T_true[:3, :3]) @ p[..., None]
    d = np.linalg.norm(d[..., 0] + (Ts[:, None, :3, 3] - T_true[:3, 3]), axis=-1)
    return tuple(float(x) for x in d.mean(axis=-1))


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


def check_resolutions(maps: Sequence[OccupancyMap], names: Sequence[str], allow_resample: bool):
    r0 = maps[0].resolution
    for m, name in zip(maps[1:], names[1:]):
        if not math.isclose(m.resolution, r0, rel_tol=1e-9) and not allow_resample:
            raise MergeError(
                f"resolutions differ: {names[0]} is {r0:g} m, {name} is {m.resolution:g} m; "
                f"rebuild the maps at one resolution or pass --resample (resamples {name} onto "
                f"{names[0]}'s {r0:g} m grid, which blurs it)", "resolution")


def resample_to_resolution(m: OccupancyMap, resolution: float, *, chunk: int = 1 << 18) -> OccupancyMap:
    """Map ``m`` resampled onto a grid of ``resolution`` [m] in the same frame.

    Every finest voxel centre of the new grid inside ``m``'s leaf extent is sampled with
    ``resample.sample`` (trilinear in probability, unknown neighbours left out); voxels whose
    centre lies in unknown space stay unknown. Dense over the bounding box (chunked), so cost
    grows with the box volume / ``resolution^3``: meant for maps of moderate extent.
    """
    from . import morton
    from .resample import sample
    from .tree import from_voxels

    if m.num_leaves == 0:
        from .map import empty

        return empty(resolution, m.params)
    lv = m.leaves()
    lo = (lv.keys.astype(np.float64) - morton.KEY_OFFSET) * m.resolution
    hi = lo + lv.sizes[:, None]
    k0 = np.floor(lo.min(0) / resolution).astype(np.int64)
    k1 = np.ceil(hi.max(0) / resolution).astype(np.int64)
    axes = [np.arange(a, b) for a, b in zip(k0, k1)]
    n_total = int(np.prod([len(a) for a in axes]))
    if n_total > 200_000_000:
        raise MergeError(f"resampling would sample {n_total:,} voxels; the map's extent is too "
                         f"large for resolution {resolution:g} m", "resolution")
    gx, gy, gz = np.meshgrid(*axes, indexing="ij")
    keys = np.stack([gx.ravel(), gy.ravel(), gz.ravel()], -1)
    centers, values = [], []
    for s in range(0, keys.shape[0], chunk):
        c = ((keys[s:s + chunk] + 0.5) * resolution).astype(np.float32)
        pad = np.zeros((chunk, 3), np.float32)
        pad[: c.shape[0]] = c
        lo_val, known = sample(m, pad, space="log_odds")
        known = np.asarray(known)[: c.shape[0]]
        centers.append(c[known])
        values.append(np.asarray(lo_val)[: c.shape[0]][known])
    return from_voxels(np.concatenate(centers), np.concatenate(values), resolution, params=m.params)


# ----------------------------------------------------------------------------- registration


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
        T_1_2, dense_info, _ = _refine_dense(m1, m2, T_icp, timings, retry)
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
        found = _timed(timings, "correlation", reg.correlation_search, m1, m2, T0, num_hypotheses=8 * k)
        problem = _timed(timings, "rank", reg.prepare_alignment, m1, m2)
        cells = m1.resolution * 2.0 ** np.asarray(problem.levels, np.float64)
        level = int(np.argmin(np.abs(np.log2(cells / (2.0 * found.cell)))))
        loss = np.asarray(_timed(timings, "correlation", reg.dense.level_losses, problem, found.hypotheses,
                                 level=level))
        order = np.argsort(np.where(np.isfinite(loss), loss, np.inf), kind="stable")
        parts.append((_local_candidates(p1, p2, found.hypotheses[order[:k]], config, m1.resolution, icp_kwargs,
                                        timings), "correlation+icp"))
        if rc.correlation_dense > 0:
            parts.append((_dense_candidates(problem, found.hypotheses[order[:rc.correlation_dense]], level,
                                            timings), "correlation+dense"))
    result = parts[0][0]
    for part, _ in parts[1:]:
        result = _concat_candidates(result, part)
    origin = np.concatenate([np.full(np.asarray(part.scores).shape[0], name) for part, name in parts])
    return result, origin, problem


def _dense_candidates(problem, hypotheses, start_level: int, timings: dict):
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
    a = _timed(timings, "dense_correlation", reg.solve_alignment, problem, np.asarray(hypotheses, np.float64),
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
    return dataclasses.replace(a, candidates=jax.tree_util.tree_map(cat, a.candidates, b.candidates),
                               scores=cat(a.scores, b.scores), hypotheses=cat(a.hypotheses, b.hypotheses),
                               basin=cat(a.basin, np.asarray(b.basin) + np.asarray(a.basin).shape[0]))


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
    loss) and ICP did not fail. Returns ``(IcpResult or None, info dict)``."""
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
    loss = np.asarray(reg.score_alignment(problem, np.stack([T_pick, T_local]))[0], np.float64)
    info.update(map_loss_pick=round(float(loss[0]), 5), map_loss_local=round(float(loss[1]), 5),
                used=bool(loss[1] < loss[0]))
    return (local if info["used"] else None), info


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


def _refine_dense(m1, m2, T_start, timings: dict, warnings: list):
    """``registration.align_dense`` from ``T_start``: ``(T_1_2, info dict, AlignResult)``.

    Its result is used when it converged or ran out of iterations (status 0 / 1); on poor
    agreement, too little overlap or non-finite values the start transform is kept."""
    r = _timed(timings, "dense", _reg().align_dense, m1, m2, np.asarray(T_start, np.float64))
    status = int(r.status)
    info = {"status": status, "converged": status == 0,
            "agreement": float(np.asarray(r.agreement)), "loss": float(np.asarray(r.loss)),
            "num_iterations": int(np.asarray(r.num_iterations))}
    if status in (0, 1):
        return np.asarray(r.T_1_2, np.float64), info, r
    warnings.append(f"dense alignment failed (status {status}, agreement {info['agreement']:.2f}); "
                    "the previous transform is kept")
    return np.asarray(T_start, np.float64), info, r


# ----------------------------------------------------------------------------- merge


def merge(m1: OccupancyMap, m2: OccupancyMap, T_1_2_init=None, refine: str | None = None,
          overlap: str | None = None, interpolation: str | None = None, rule: str | None = None,
          T_1_2_true=None, *, config: MergeConfig | None = None, resample: bool | None = None):
    """Merge map 2 into map 1's frame (thesis Ch. 6): returns ``(merged, MergeReport)``.

    Args:
      m1, m2: ``OccupancyMap`` s of one resolution (else ``MergeError(kind="resolution")``
        unless ``resample=True``, which resamples ``m2`` onto ``m1``'s grid first).
      T_1_2_init: ``(4, 4)`` initial guess mapping map 2's frame into map 1's [m]
        (``None``: identity; see ``transform_from_xyz_rpy``).
      refine: ``"icp"``, ``"multi"`` (multi-hypothesis ICP for poor guesses), ``"dense"``
        (``align_dense``: gradient-based alignment of the occupancy fields), ``"icp+dense"``
        or ``"none"``.
      overlap: ``"bbox"`` (thesis Alg. 2, default) or ``"voxel"`` subsets fed to ICP, or
        ``"none"`` (see ``config.RegistrationConfig``).
      interpolation: ``transform_map`` method (``"trilinear"``, ``"nearest"``, ``"thesis"``).
      rule: ``fuse`` rule (``"sum"``, ``"max"``, ``"weighted"``).
      T_1_2_true: ground truth ``(4, 4)``; adds thesis eqs. 7.2/7.3 errors to the report.
      config: all other parameters (``MergeConfig``); the keyword arguments above override it.

    Raises ``MergeError`` (a ``ValueError``) with ``kind`` for inputs the user must fix.
    """
    cfg = _with_overrides(config, refine, overlap, interpolation, rule, resample)
    timings: dict = {}
    warnings: list = []
    t_start = time.perf_counter()
    check_resolutions([m1, m2], ["map 1", "map 2"], cfg.transform.resample_resolution)
    if not math.isclose(m1.resolution, m2.resolution, rel_tol=1e-9):
        m2 = _timed(timings, "resample", resample_to_resolution, m2, m1.resolution)
        warnings.append(f"map 2 was resampled to map 1's resolution {m1.resolution:g} m")
    T_init = np.eye(4) if T_1_2_init is None else _check_T(T_1_2_init, "T_1_2_init")
    T_true = None if T_1_2_true is None else _check_T(T_1_2_true, "T_1_2_true")
    if m1.num_leaves == 0 and m2.num_leaves == 0:
        raise MergeError("both maps are empty", "empty")

    T_1_2, info, result, counts, q1, q2 = register(m1, m2, T_init, cfg, timings, warnings)
    counts = {"leaves_1": m1.num_leaves, "leaves_2": m2.num_leaves, **counts}
    merged, more = _transform_and_fuse(m1, m2, T_1_2, cfg, timings)
    counts.update(more)
    timings["total"] = time.perf_counter() - t_start
    eps = (None, None, None, None)
    if T_true is not None:
        eps = (*_epsilons(T_init, T_true), *_epsilons(T_1_2, T_true))
    report = MergeReport(
        T_1_2_init=T_init, T_1_2=T_1_2, refine=cfg.registration.refine, icp=info,
        epsilon_r_init=eps[0], epsilon_t_init=eps[1], epsilon_r=eps[2], epsilon_t=eps[3],
        counts=counts, timings=timings, resolution=m1.resolution, T_1_2_true=T_true,
        warnings=tuple(warnings), status="ok" if info is None or info["converged"] else "not_converged",
        icp_result=result, points_1=q1, points_2=q2)
    d = _displacements(m2, T_true, T_init, T_1_2)
    return merged, dataclasses.replace(report, displacement_init=d[0], displacement=d[1])


def _with_overrides(config, refine, overlap, interpolation, rule, resample) -> MergeConfig:
    cfg = MergeConfig() if config is None else config
    reg, tr, fu = {}, {}, {}
    if refine is not None:
        reg["refine"] = refine
    if overlap is not None:
        reg["overlap"] = overlap
    if interpolation is not None:
        tr["interpolation"] = interpolation
    if resample is not None:
        tr["resample_resolution"] = bool(resample)
    if rule is not None:
        fu["rule"] = rule
    if reg or tr or fu:
        cfg = cfg.replace(registration=reg, transform=tr, fuse=fu)
    validate(cfg)
    return cfg


def _transform_and_fuse(m1, m2, T_1_2, cfg: MergeConfig, timings: dict):
    from .fuse import fuse
    from .resample import transform_map

    tc = cfg.transform
    try:
        m2_in_1 = _timed(timings, "transform", transform_map, m2, T_1_2, tc.interpolation,
                         space=tc.space, chunk_bricks=tc.chunk_bricks)
    except ValueError as err:
        raise MergeError(f"transforming map 2: {err}", "transform") from None
    weights = tuple(cfg.fuse.weights[:2]) if len(cfg.fuse.weights) >= 2 else (1.0, 1.0)
    merged, frep = _timed(timings, "fuse", fuse, m1, m2_in_1, cfg.fuse.rule, weights=weights,
                          return_report=True)
    counts = {"leaves_2_transformed": m2_in_1.num_leaves, "leaves_merged": merged.num_leaves,
              "fuse": frep.host()}
    return merged, counts


def merge_many(maps: Sequence[OccupancyMap], T_inits=None, *, pairs=None, refine: str | None = None,
               rule: str | None = None, T_trues=None, config: MergeConfig | None = None):
    """Merge ``m`` maps into the first map's frame and fuse them all in one pass (``fuse_many``).

    Args:
      maps: ``[m_0, m_1, ...]`` of one resolution.
      T_inits: ``m - 1`` guesses ``T_0_k`` (k = 1..m-1) mapping map k into map 0's frame
        (``None``: identity). Each map k is registered to map 0.
      pairs: instead of ``T_inits``, pairwise guesses ``{(i, k): T_i_k}`` forming a spanning
        tree rooted at 0 (e.g. a chain ``(0,1), (1,2)``: robots that met one after another).
        Map k is registered to its parent i (refined ``T_i_k``), and the refined transforms are
        chained into ``T_0_k = T_0_i T_i_k``.
      T_trues: optional ground truths ``T_0_k`` (``m - 1``) for the thesis errors.

    Returns ``(merged, reports)``: one ``MergeReport`` per non-root map (its ``T_1_2`` is
    ``T_parent_k`` and ``counts["leaves_merged"]`` the final map's), plus the ``fuse_many``
    counts in ``reports[0].counts["fuse_many"]``.
    """
    from .fuse import fuse_many
    from .resample import transform_map

    maps = list(maps)
    if len(maps) < 2:
        raise ValueError("merge_many needs at least two maps")
    cfg = _with_overrides(config, refine, None, None, rule, None)
    check_resolutions(maps, [f"maps[{i}]" for i in range(len(maps))], False)
    n = len(maps)
    if pairs is None:
        T_inits = [None] * (n - 1) if T_inits is None else list(T_inits)
        if len(T_inits) != n - 1:
            raise ValueError(f"T_inits has {len(T_inits)} transforms for {n} maps (need {n - 1})")
        parent = {k: 0 for k in range(1, n)}
        guess = {k: T_inits[k - 1] for k in range(1, n)}
    else:
        parent, guess = {}, {}
        for (i, k), T in dict(pairs).items():
            if k in parent or k == 0:
                raise ValueError(f"pairs: map {k} has two parents (or is the root); give a tree")
            parent[k], guess[k] = int(i), T
        if sorted(parent) != list(range(1, n)):
            raise ValueError(f"pairs must give every map 1..{n - 1} one parent, got {sorted(parent)}")
    order, seen = [], {0}
    while len(order) < n - 1:  # breadth-first from the root so parents are refined first
        grew = False
        for k in range(1, n):
            if k not in seen and parent[k] in seen:
                order.append(k)
                seen.add(k)
                grew = True
        if not grew:
            raise ValueError("pairs do not connect every map to map 0 (cycle or gap)")
    T_trues = [None] * (n - 1) if T_trues is None else list(T_trues)
    T_0 = {0: np.eye(4)}
    reports = {}
    for k in order:
        timings, warnings = {}, []
        t0 = time.perf_counter()
        i = parent[k]
        T_init = np.eye(4) if guess[k] is None else _check_T(guess[k], f"T_{i}_{k}")
        T_i_k, info, result, counts, q1, q2 = register(maps[i], maps[k], T_init, cfg, timings, warnings)
        T_0[k] = T_0[i] @ T_i_k
        timings["total"] = time.perf_counter() - t0
        eps, disp = (None, None, None, None), (None, None)
        if T_trues[k - 1] is not None:
            T_true = _check_T(T_trues[k - 1], f"T_trues[{k - 1}]")
            eps = (*_epsilons(T_0[i] @ T_init, T_true), *_epsilons(T_0[k], T_true))
            disp = _displacements(maps[k], T_true, T_0[i] @ T_init, T_0[k])
        reports[k] = MergeReport(
            T_1_2_init=T_init, T_1_2=T_i_k, refine=cfg.registration.refine, icp=info,
            epsilon_r_init=eps[0], epsilon_t_init=eps[1], epsilon_r=eps[2], epsilon_t=eps[3],
            counts={"leaves_1": maps[i].num_leaves, "leaves_2": maps[k].num_leaves, **counts},
            timings=timings, resolution=maps[0].resolution, warnings=tuple(warnings),
            status="ok" if info is None or info["converged"] else "not_converged",
            displacement_init=disp[0], displacement=disp[1], icp_result=result, points_1=q1, points_2=q2)
    tc = cfg.transform
    moved = [maps[0]]
    t_tr = {}
    for k in range(1, n):
        moved.append(_timed(t_tr, "transform", transform_map, maps[k], T_0[k], tc.interpolation,
                            space=tc.space, chunk_bricks=tc.chunk_bricks))
    weights = list(cfg.fuse.weights) if cfg.fuse.rule == "weighted" else None
    if weights is not None and len(weights) != n:
        raise ValueError(f"fuse.weights has {len(weights)} entries for {n} maps")
    merged, frep = _timed(t_tr, "fuse", fuse_many, moved, cfg.fuse.rule, weights=weights,
                          return_report=True)
    out = []
    for k in range(1, n):
        r = reports[k]
        counts = {**r.counts, "leaves_merged": merged.num_leaves,
                  "leaves_2_transformed": moved[k].num_leaves}
        if k == 1:
            counts["fuse_many"] = frep.host()
        timings = {**r.timings, "transform_all": t_tr["transform"], "fuse_all": t_tr["fuse"]}
        out.append(dataclasses.replace(r, counts=counts, timings=timings))
    return merged, out


# ----------------------------------------------------------------------------- ICP trace


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
