"""The merge pipeline (thesis Ch. 6): ``merge`` and ``merge_many``.

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
overlap, ICP without enough inliers, a NaN guess), a ``MergeError`` whose ``kind`` says which
(``report.py``). The registration step (``register``, all refine modes) is ``refine.py``.

The ICP result is judged on the host by ``config.registration.on_not_converged``: ICP that ran
out of iterations is usually close (it is still shrinking its correspondence distance), so the
default is to use it and say so in ``report.warnings``; too few inliers means the guess put the
maps where they do not overlap, which is always an error (refine ``"multi"`` or a better guess
helps).
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Sequence

import numpy as np

from .config import MergeConfig, validate
from .map import OccupancyMap
from .refine import _reg, _timed, icp_trace, point_stats, rank_by_map_agreement, register
from .report import MergeError, MergeReport

__all__ = [
    "MergeError",
    "MergeReport",
    "merge",
    "merge_many",
    "icp_trace",
    "resample_to_resolution",
    "transform_from_xyz_rpy",
    # the registration step (refine.py), also here: used with merge's config and report
    "register",
    "rank_by_map_agreement",
    "point_stats",
]


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

