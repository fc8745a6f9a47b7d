"""The merge pipeline (thesis Ch. 6): ``merge`` (N maps: ``many.py``).

::

    map 1 ──occupied_points──┐                       (Alg. 1)
    map 2 ──occupied_points──┴─ overlap(T_1_2_init)    (Alg. 2, "voxel" or thesis "bbox")
                                 └─ icp / icp_multi -> T_1_2          (Alg. 3)
    map 2 ──transform_map(T_1_2)──> map 2 in frame 1                  (Alg. 4-7)
    map 1, map 2 in frame 1 ──fuse──> merged                          (Alg. 8)

Frames: ``T_1_2`` maps points of map 2's frame into map 1's frame (``T_m1_m2``); the merged map
is in map 1's frame with map 1's parameters. Every stage is a jitted function from the modules
it names; this module plans on the host, times each stage and turns statuses into a
``MergeReport`` or, for problems the user must fix (mixed resolutions, no overlap, ICP without
enough inliers, a NaN guess), a ``MergeError`` whose ``kind`` says which. The registration
step is ``refine.py``; ICP's result is judged there (``accept_icp``) by
``config.registration.on_not_converged``.
"""

from __future__ import annotations

import math
import time
from typing import Sequence

import numpy as np

from .. import morton
from .. import registration as reg
from .. import se3
from ..fusion import fuse_with_report
from ..map import OccupancyMap, empty
from ..resample import sample, transform_map
from ..se3 import check_rigid_transform
from ..tree import from_voxels
from .config import MergeConfig, RegistrationConfig, validate
from .refine import register
from .report import MergeError, MergeReport, Registration
from .timings import Timings

__all__ = ["check_resolutions", "check_transform", "config_with_overrides", "fuse_in_frame_1", "merge", "pair_report",
           "resample_to_resolution", "transform_and_fuse", "transform_from_xyz_rpy", "transform_to_frame_1"]


def transform_from_xyz_rpy(x: float = 0.0, y: float = 0.0, z: float = 0.0, roll_rad: float = 0.0,
                           pitch_rad: float = 0.0, yaw_rad: float = 0.0) -> np.ndarray:
    """``(4, 4)`` float64 from a translation [m] and roll/pitch/yaw [rad] (``R = Rz Ry Rx``,
    OctoMap's ``Pose6D``; ``se3.from_xyz_rpy``), as the thesis's command line
    ``x y z roll pitch yaw``. Raises ``MergeError("transform")`` naming the value if one is NaN
    or infinite."""
    vals = dict(x=x, y=y, z=z, roll=roll_rad, pitch=pitch_rad, yaw=yaw_rad)
    for name, v in vals.items():
        if not math.isfinite(float(v)):
            raise MergeError(f"initial guess: {name} = {v} is not a finite number", "transform")
    return se3.from_xyz_rpy(x, y, z, roll_rad, pitch_rad, yaw_rad, xp=np)


def check_transform(T, name: str) -> np.ndarray:
    """``T`` as a rigid ``(4, 4)`` float64 (``se3.check_rigid_transform``); raises
    ``MergeError("transform")`` naming ``name`` otherwise."""
    try:
        return check_rigid_transform(T, name)
    except ValueError as err:
        raise MergeError(str(err), "transform") from None


def _epsilons(T_est, T_true) -> tuple[float, float]:
    """Thesis eqs. 7.2 / 7.3: ``(epsilon_r, epsilon_t)`` of ``T_est`` against ``T_true``."""
    return float(reg.rotation_error(T_est, T_true)), float(reg.translation_error(T_est, T_true))


def _displacements(m2: OccupancyMap, T_true, *Ts, max_points: int = 100_000) -> tuple:
    """Mean displacement [m] of map 2's occupied leaf centres (an even subsample of at most
    ``max_points``) under each of ``Ts`` against ``T_true``; ``None``s without truth."""
    if T_true is None:
        return (None,) * len(Ts)
    L = m2.leaves()
    p = L.centers[L.log_odds > m2.params.occupancy_threshold_host]
    if len(p) == 0:
        p = L.centers
    p = p[:: max(1, -(-len(p) // max_points))]
    if len(p) == 0:
        return (None,) * len(Ts)
    # NumPy float64: map coordinates can be kilometres from the origin, where float32 would
    # lose ~1e-4 m
    Ts, T_true = np.asarray(Ts, np.float64), np.asarray(T_true, np.float64)
    d = (Ts[:, None, :3, :3] - T_true[:3, :3]) @ p[..., None]
    d = np.linalg.norm(d[..., 0] + (Ts[:, None, :3, 3] - T_true[:3, 3]), axis=-1)
    return tuple(float(x) for x in d.mean(axis=-1))


def check_resolutions(maps: Sequence[OccupancyMap], names: Sequence[str], allow_resample: bool) -> None:
    """Raise ``MergeError("resolution")`` naming the maps when their resolutions differ and
    ``allow_resample`` is false."""
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
    grows with the box volume / ``resolution^3``: meant for maps of moderate extent. Raises
    ``MergeError("resolution")`` above 2e8 samples.
    """
    if m.num_leaves == 0:
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


def transform_to_frame_1(m2: OccupancyMap, T_1_2, config: MergeConfig, timings: Timings) -> OccupancyMap:
    """Map 2 resampled into map 1's frame (``transform_map``, thesis Alg. 4-7), timed as
    ``transform``. Raises ``MergeError("transform")``."""
    tc = config.transform
    try:
        with timings.stage("transform") as stage:
            return stage.ready(transform_map(m2, T_1_2, tc.interpolation, space=tc.space,
                                             chunk_bricks=tc.chunk_bricks))
    except ValueError as err:
        raise MergeError(f"transforming map 2: {err}", "transform") from None


def transform_and_fuse(m1: OccupancyMap, m2: OccupancyMap, T_1_2, config: MergeConfig, timings: Timings):
    """The merge after its registration (thesis Alg. 4-8): map 2 resampled into map 1's frame by
    ``T_1_2`` ((4, 4), map 2's frame into map 1's [m]; stage ``transform``) and fused into map 1
    (stage ``fuse``). Returns ``(map 2 in frame 1, merged map, FuseReport)``. Raises
    ``MergeError("transform")``."""
    m2_in_1 = transform_to_frame_1(m2, T_1_2, config, timings)
    return (m2_in_1, *fuse_in_frame_1(m1, m2_in_1, config, timings))


def fuse_in_frame_1(m1: OccupancyMap, m2_in_1: OccupancyMap, config: MergeConfig, timings: Timings):
    """Map 2, already in map 1's frame, fused into map 1 by ``config.fuse`` (thesis Alg. 8;
    stage ``fuse``): ``(merged map, FuseReport)``."""
    weights = tuple(config.fuse.weights[:2]) if len(config.fuse.weights) >= 2 else (1.0, 1.0)
    with timings.stage("fuse") as stage:
        return tuple(stage.ready(fuse_with_report(m1, m2_in_1, config.fuse.rule, weights=weights)))


def pair_report(m1: OccupancyMap, m2: OccupancyMap, registration: Registration, T_1_2_init, T_1_2_true,
                config: MergeConfig, counts: dict, timings: dict, warnings: Sequence[str]) -> MergeReport:
    """The ``MergeReport`` of one merged pair: ``registration`` with the thesis errors
    (eqs. 7.2 / 7.3) and displacements against ``T_1_2_true`` when given."""
    T_1_2 = registration.T_1_2
    eps = (None, None, None, None)
    if T_1_2_true is not None:
        eps = (*_epsilons(T_1_2_init, T_1_2_true), *_epsilons(T_1_2, T_1_2_true))
    disp = _displacements(m2, T_1_2_true, T_1_2_init, T_1_2)
    return MergeReport(
        T_1_2_init=T_1_2_init, T_1_2=T_1_2, refine=config.registration.refine, icp=registration.info,
        epsilon_r_init=eps[0], epsilon_t_init=eps[1], epsilon_r=eps[2], epsilon_t=eps[3],
        counts=counts, timings=dict(timings), resolution=m1.resolution, T_1_2_true=T_1_2_true,
        warnings=tuple(warnings), status=_status(registration),
        displacement_init=disp[0], displacement=disp[1], icp_result=registration.result,
        points_1=registration.points_1, points_2=registration.points_2,
        confidence=registration.confidence, candidates=registration.candidates)


# --- global
def _status(registration: Registration) -> str:
    """``MergeReport.status``: the registration's verdict (``info["verdict"]``) when it is not
    ``"ok"``, else ``"ok"`` / ``"not_converged"`` by convergence."""
    verdict = (registration.info or {}).get("verdict")
    if verdict not in (None, "ok"):
        return str(verdict)
    return "ok" if registration.converged else "not_converged"


def merge(m1: OccupancyMap, m2: OccupancyMap, T_1_2_init=None, refine: str | None = None,
          overlap: str | None = None, interpolation: str | None = None, rule: str | None = None,
          T_1_2_true=None, *, config: MergeConfig | None = None, resample: bool | None = None):
    """Merge map 2 into map 1's frame (thesis Ch. 6): returns ``(merged, MergeReport)``.

    Args:
      m1, m2: ``OccupancyMap`` s of one resolution (else ``MergeError(kind="resolution")``
        unless ``resample=True``, which resamples ``m2`` onto ``m1``'s grid first).
      T_1_2_init: ``(4, 4)`` initial guess mapping map 2's frame into map 1's [m]
        (``None``: no guess: unless ``refine`` is given or the config sets another mode than
        the default ``"icp+dense"`` or ``"icp"``, the transform is searched for,
        ``refine="global"``; see ``transform_from_xyz_rpy``).
      refine: ``"global"`` (no guess needed, ending with the dense alignment; status
        ``"ambiguous"`` / ``"no_overlap"`` /
        ``"failed"`` when the result is not to be trusted), ``"icp+dense"`` (the default from a
        guess: ICP, then the dense alignment; sub-voxel), ``"icp"``, ``"multi"``
        (multi-hypothesis search for poor guesses), ``"dense"``
        (``align_dense``: gradient-based alignment of the occupancy fields) or ``"none"``.
      overlap: ``"bbox"`` (thesis Alg. 2, default) or ``"voxel"`` subsets fed to ICP, or
        ``"none"`` (see ``config.RegistrationConfig``).
      interpolation: ``transform_map`` method (``"trilinear"``, ``"nearest"``, ``"thesis"``).
      rule: ``fuse`` rule (``"sum"``, ``"max"``, ``"weighted"``).
      T_1_2_true: ground truth ``(4, 4)``; adds thesis eqs. 7.2/7.3 errors to the report.
      config: all other parameters (``MergeConfig``); the keyword arguments above override it.

    Raises ``MergeError`` (a ``ValueError``) with ``kind`` for inputs the user must fix.
    """
    cfg = config_with_overrides(config, refine, overlap, interpolation, rule, resample)
    default_refine = RegistrationConfig().refine
    if T_1_2_init is None and refine is None and cfg.registration.refine in ("icp", default_refine):
        cfg = cfg.replace(registration={"refine": "global"})  # no guess: search for the transform
    timings = Timings()
    warnings: list[str] = []
    t_start = time.perf_counter()
    check_resolutions([m1, m2], ["map 1", "map 2"], cfg.transform.resample_resolution)
    if not math.isclose(m1.resolution, m2.resolution, rel_tol=1e-9):
        with timings.stage("resample") as stage:
            m2 = stage.ready(resample_to_resolution(m2, m1.resolution))
        warnings.append(f"map 2 was resampled to map 1's resolution {m1.resolution:g} m")
    T_init = np.eye(4) if T_1_2_init is None else check_transform(T_1_2_init, "T_1_2_init")
    T_true = None if T_1_2_true is None else check_transform(T_1_2_true, "T_1_2_true")
    if m1.num_leaves == 0 and m2.num_leaves == 0:
        raise MergeError("both maps are empty", "empty")

    # refine="global" without a guess: no guess to verify among its candidates
    guess = None if T_1_2_init is None and cfg.registration.refine == "global" else T_init
    registration = register(m1, m2, guess, cfg, timings)
    m2_in_1, merged, frep = transform_and_fuse(m1, m2, registration.T_1_2, cfg, timings)
    counts = {"leaves_1": m1.num_leaves, "leaves_2": m2.num_leaves, **registration.counts,
              "leaves_2_transformed": m2_in_1.num_leaves, "leaves_merged": merged.num_leaves,
              "fuse": frep.host()}
    timings["total"] = time.perf_counter() - t_start
    return merged, pair_report(m1, m2, registration, T_init, T_true, cfg, counts, timings,
                               [*warnings, *registration.warnings])


def config_with_overrides(config, refine=None, overlap=None, interpolation=None, rule=None,
                          resample=None) -> MergeConfig:
    """``config`` (default ``MergeConfig()``) with the keyword overrides of ``merge`` applied
    (``None``: keep), validated."""
    cfg = MergeConfig() if config is None else config
    reg_, tr, fu = {}, {}, {}
    if refine is not None:
        reg_["refine"] = refine
    if overlap is not None:
        reg_["overlap"] = overlap
    if interpolation is not None:
        tr["interpolation"] = interpolation
    if resample is not None:
        tr["resample_resolution"] = bool(resample)
    if rule is not None:
        fu["rule"] = rule
    if reg_ or tr or fu:
        cfg = cfg.replace(registration=reg_, transform=tr, fuse=fu)
    validate(cfg)
    return cfg
