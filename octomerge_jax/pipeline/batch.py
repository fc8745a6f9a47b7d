"""Many merges: ``merge_batch`` (pairs grouped by capacity bucket, one jitted call per group).

``merge_batch(pairs)`` plans on the host, then runs the jittable stages batched, with the
stage functions of ``merge`` (``refine.py``, ``transform_to_frame_1``, ``fuse_with_report``):

1. per pair: resolution / guess checks, occupied clouds and overlap (host, cheap); a pair that
   fails gets ``status="error"`` and a message, the others go on;
2. ICP (``refine="icp"``, ``"icp+dense"``): pairs grouped by (resolution, source bucket, target bucket) and each
   group registered by **one** jitted call of ``registration.icp_padded_stack``, then judged
   pair by pair (``register_icp``: the one ICP status policy, a result that slid out of the
   guess's basin set aside, the dense step, and a wrong basin ``"failed"``, as in ``merge``);
   other refine modes register pair by pair (``register``);
3. ``transform_map`` per pair (pairs of one bucket share the compiled kernel);
4. fusion: pairs grouped by (map-1 capacity, transformed map-2 capacity) and each group fused
   by one ``vmap`` of ``fuse`` with a static output capacity and gap-cell list; a pair whose
   refinement or gap cells overflowed them is re-fused alone (its result is never truncated).
"""

from __future__ import annotations

import dataclasses
import time
from typing import NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from .. import registration as reg
from ..fusion import default_gap_capacity, fuse_with_report
from ..map import OccupancyMap, bucket_capacity
from ..registration import neighbors
from .clouds import icp_kwargs, occupied_clouds, stage_epsilon
from .config import MergeConfig
from .merging import check_resolutions, check_transform, merge, pair_report, transform_to_frame_1
from .refine import Overlap, overlap_for_icp, register, register_icp
from .report import MergeError, MergeReport, Registration
from .timings import Timings

__all__ = ["BatchResult", "merge_batch"]


@dataclasses.dataclass(frozen=True)
class BatchResult:
    """One pair of a batch: ``status`` ``"ok"`` or ``"error"`` (with ``message`` and the
    ``MergeError`` kind in ``kind``); ``merged`` and ``report`` are ``None`` on error."""

    status: str
    merged: OccupancyMap | None = None
    report: MergeReport | None = None
    message: str = ""
    kind: str = ""


class _Job(NamedTuple):
    """One checked pair on its way through the batch."""

    m1: OccupancyMap
    m2: OccupancyMap
    T_1_2_init: np.ndarray  # (4, 4) float64
    T_1_2_true: np.ndarray | None  # (4, 4) float64
    timings: Timings


def _as_pair(p, i):
    if isinstance(p, dict):
        return p["m1"], p["m2"], p.get("T_1_2_init"), p.get("T_1_2_true")
    p = tuple(p)
    if len(p) == 2:
        return p[0], p[1], None, None
    if len(p) == 3:
        return p[0], p[1], p[2], None
    if len(p) == 4:
        return p
    raise ValueError(f"pairs[{i}]: expected (m1, m2[, T_1_2_init[, T_1_2_true]]), got {len(p)} items")


def _error(err: ValueError) -> BatchResult:
    return BatchResult("error", message=str(err), kind=getattr(err, "kind", "input"))


def _merge_one(p, i, cfg: MergeConfig) -> BatchResult:
    try:
        m1, m2, T_init, T_true = _as_pair(p, i)
        merged, report = merge(m1, m2, T_init, T_1_2_true=T_true, config=cfg)
        return BatchResult("ok", merged, report)
    except ValueError as err:  # MergeError included
        return _error(err)


def _check(p, i) -> _Job:
    m1, m2, T_init, T_true = _as_pair(p, i)
    check_resolutions([m1, m2], [f"pairs[{i}].m1", f"pairs[{i}].m2"], False)
    T_init = np.eye(4) if T_init is None else check_transform(T_init, f"pairs[{i}].T_1_2_init")
    T_true = None if T_true is None else check_transform(T_true, f"pairs[{i}].T_1_2_true")
    return _Job(m1, m2, T_init, T_true, Timings())


def merge_batch(pairs: Sequence, *, config: MergeConfig | None = None) -> list[BatchResult]:
    """Merge many pairs; returns one ``BatchResult`` per pair, in order.

    ``pairs``: items ``(m1, m2)``, ``(m1, m2, T_1_2_init)`` or ``(m1, m2, T_1_2_init,
    T_1_2_true)`` (or dicts with keys ``m1, m2, T_1_2_init, T_1_2_true``). Results equal
    ``merge`` pair by pair (same kernels); a bad pair never stops the batch. ``refine="multi"``
    runs its hypotheses batched per pair (already one ``vmap``); ``"dense"`` and
    ``"icp+dense"`` merge pair by pair.
    """
    cfg = MergeConfig() if config is None else config
    if cfg.registration.refine in ("dense", "icp+dense"):  # the dense solver runs per pair (vmapped inside)
        return [_merge_one(p, i, cfg) for i, p in enumerate(pairs)]
    results: list[BatchResult | None] = [None] * len(pairs)
    jobs: dict[int, _Job] = {}
    for i, p in enumerate(pairs):
        try:
            jobs[i] = _check(p, i)
        except ValueError as err:
            results[i] = _error(err)
    registrations = _register_all(jobs, cfg, results)
    moved = {}
    for i, registration in registrations.items():
        try:
            moved[i] = transform_to_frame_1(jobs[i].m2, registration.T_1_2, cfg, jobs[i].timings)
        except MergeError as err:
            results[i] = _error(err)
    for i, (merged, frep) in _fuse_all(jobs, moved, cfg).items():
        job, registration = jobs[i], registrations[i]
        counts = {"leaves_1": job.m1.num_leaves, "leaves_2": job.m2.num_leaves, **registration.counts,
                  "leaves_2_transformed": moved[i].num_leaves, "leaves_merged": merged.num_leaves,
                  "fuse": frep.host()}
        timings = {**job.timings, "total": sum(job.timings.values())}
        report = pair_report(job.m1, job.m2, registration, job.T_1_2_init, job.T_1_2_true, cfg, counts, timings,
                             registration.warnings)
        results[i] = BatchResult("ok", merged=merged, report=report)
    return results


def _register_all(jobs: dict[int, _Job], cfg: MergeConfig, results: list) -> dict[int, Registration]:
    """Each job's ``Registration`` (a failed one's ``BatchResult`` goes to ``results[i]``):
    ``refine="icp"`` / ``"icp+dense"`` with the ICP of each capacity bucket in one call
    (``_icp_bucket``; the dense step then pair by pair, ``register_icp``)."""
    out = {}
    if cfg.registration.refine not in ("icp", "icp+dense"):
        for i, job in jobs.items():
            try:
                out[i] = register(job.m1, job.m2, job.T_1_2_init, cfg, job.timings)
            except MergeError as err:
                results[i] = _error(err)
        return out
    prepared, groups = {}, {}
    for i, job in jobs.items():
        try:
            clouds = occupied_clouds(job.m1, job.m2, job.timings)
            overlap = overlap_for_icp(clouds, job.T_1_2_init, cfg, job.m1.resolution, job.timings)
        except MergeError as err:
            results[i] = _error(err)
            continue
        prepared[i] = (clouds, overlap)
        # ICP uses the larger cloud as the model (target), as registration.icp does
        swap = overlap.points_2.shape[0] > overlap.points_1.shape[0]
        src, tgt = (overlap.points_1, overlap.points_2) if swap else (overlap.points_2, overlap.points_1)
        key = (job.m1.resolution, bucket_capacity(src.shape[0]), bucket_capacity(tgt.shape[0]))
        groups.setdefault(key, []).append(i)
    for (resolution, cap_source, cap_target), members in groups.items():
        t0 = time.perf_counter()
        icp_results = _icp_bucket([prepared[i][1] for i in members], [jobs[i].T_1_2_init for i in members],
                                  resolution, cap_source, cap_target, cfg)
        dt = (time.perf_counter() - t0) / len(members)
        for i, result in zip(members, icp_results):
            job = jobs[i]
            job.timings["icp"] = dt
            clouds, overlap = prepared[i]
            try:
                # ICP out of the guess's basin set aside, a wrong basin "failed": as merge
                out[i] = register_icp(job.m1, job.m2, clouds, overlap, job.T_1_2_init, result, cfg, job.timings)
            except MergeError as err:
                results[i] = _error(err)
    return out


def _icp_bucket(overlaps: Sequence[Overlap], T_inits: Sequence[np.ndarray], resolution: float, cap_source: int,
                cap_target: int, cfg: MergeConfig) -> list:
    """ICP (map 2's overlap points onto map 1's, from each ``T_1_2_init``) for the pairs of one
    capacity bucket in one jitted ``registration.icp_padded_stack`` call: ``IcpResult`` per
    pair, as ``registration.icp`` returns it (the larger cloud is the model; a swapped pair's
    result is inverted back)."""
    kw = icp_kwargs(cfg, resolution)
    dists = reg.stage_distances(resolution, kw["max_correspondence_distance"], kw["min_correspondence_distance"],
                                kw["shrink_factor"])
    eps = stage_epsilon(cfg, resolution)
    sources, source_counts, targets, target_counts, starts, swaps = [], [], [], [], [], []
    for overlap, T_init in zip(overlaps, T_inits):
        swap = overlap.points_2.shape[0] > overlap.points_1.shape[0]
        src, tgt = (overlap.points_1, overlap.points_2) if swap else (overlap.points_2, overlap.points_1)
        s_p, s_c = reg.pad_points(src, cap_source)
        t_p, t_c = reg.pad_points(tgt, cap_target)
        sources.append(s_p), source_counts.append(s_c), targets.append(t_p), target_counts.append(t_c)
        starts.append(np.linalg.inv(T_init) if swap else T_init)
        swaps.append(swap)
    out = reg.icp_padded_stack(
        jnp.stack(sources), jnp.stack(source_counts), jnp.stack(targets), jnp.stack(target_counts),
        jnp.asarray(np.stack(starts), jnp.float32), jnp.asarray(dists, jnp.float32), jnp.float32(eps),
        jnp.float32(eps * 0.01), jnp.int32(kw["min_inliers"]), max_iterations=int(kw["max_iterations"]),
        cell_capacity=int(kw["cell_capacity"]), table_sizes=neighbors.level_table_sizes(cap_target, dists),
        coarse_matching=kw["coarse_matching"], sequential=reg.sequential_default())
    jax.block_until_ready(out)
    results = []
    for j, swap in enumerate(swaps):
        r = _unstack(out, j)
        results.append(reg.invert_result(r) if swap else r)
    return results


def _fuse_all(jobs: dict[int, _Job], moved: dict[int, OccupancyMap], cfg: MergeConfig) -> dict:
    """``{i: (merged, FuseReport)}`` for the pairs in ``moved`` (map 2 in map 1's frame):
    grouped by (resolution, map-1 capacity, transformed map-2 capacity), each group fused by
    one ``vmap`` of ``fuse_with_report`` at a static output capacity and gap-cell list; a pair
    that overflowed them is re-fused alone. Each pair's ``fuse`` timing is its group's share."""
    maps_1 = {i: jobs[i].m1 for i in moved}
    groups: dict = {}
    for i, m2_in_1 in moved.items():
        m1 = maps_1[i]
        key = (m1.resolution, bucket_capacity(m1.num_leaves), bucket_capacity(m2_in_1.num_leaves))
        groups.setdefault(key, []).append(i)
    rule, weights = cfg.fuse.rule, tuple(cfg.fuse.weights[:2])
    out = {}
    for (_, cap_1, cap_2), members in groups.items():
        t0 = time.perf_counter()
        cap = bucket_capacity(max(2 * (maps_1[i].num_leaves + moved[i].num_leaves) for i in members))
        gap_cap = default_gap_capacity(cap)  # more gap cells: overflow, re-fused alone below
        A = _stack([maps_1[i].with_capacity(cap_1) for i in members])
        B = _stack([moved[i].with_capacity(cap_2) for i in members])
        merged, reports = jax.vmap(lambda a, b: fuse_with_report(a, b, rule, weights=weights, capacity=cap,
                                                                 gap_capacity=gap_cap))(A, B)
        jax.block_until_ready(merged)
        dt = (time.perf_counter() - t0) / len(members)
        for j, i in enumerate(members):
            m_j, r_j = _unstack(merged, j), _unstack(reports, j)
            if bool(r_j.overflow):  # rare: re-fuse alone with planned capacities
                m_j, r_j = fuse_with_report(maps_1[i], moved[i], rule, weights=weights)
            m_j = _trim(m_j)
            jobs[i].timings["fuse"] = dt
            out[i] = (m_j, dataclasses.replace(r_j, capacity=m_j.capacity))
    return out


def _stack(trees):
    return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *trees)


def _unstack(tree, i):
    return jax.tree_util.tree_map(lambda a: a[i], tree)


def _trim(m: OccupancyMap) -> OccupancyMap:
    """``m`` with its capacity cut to ``bucket_capacity(num_leaves)`` when that is smaller."""
    cap = bucket_capacity(m.num_leaves)
    if cap >= m.capacity:
        return m
    return OccupancyMap(m.code[:cap], m.depth[:cap], m.log_odds[:cap], m.count, m.params,
                        m.resolution, m.tree_depth)
