"""Point-cloud insertion with OctoMap's ``insertPointCloud`` semantics (discretize=false).

For one scan (points in the map frame, one sensor origin), OctoMap's ``computeUpdate``
(``OccupancyOcTreeBase.hxx``) collects

- **free keys**: the voxels each ray traverses, by the 3-D DDA of ``computeRayKeys``
  (Amanatides & Woo; ``OcTreeBaseImpl.hxx``): the origin voxel, then every voxel entered
  before the end voxel, stopping early if the travelled distance exceeds the ray length;
- **occupied keys**: the end voxel of every ray no longer than ``max_range``; rays longer
  than ``max_range`` are cut to ``origin + dir * max_range`` and give free keys only;

as two sets (each voxel once per scan), drops free keys that are also occupied ("occupied wins"),
then applies ``updateNode(key, false)`` (miss) / ``updateNode(key, true)`` (hit) with clamping.

How we do it in JAX (``compute_update``):

1. **Host plan**: bucket the point count (power of two) and find the box of 8^3-voxel
   bricks (= depth-13 octree nodes) enclosing every ray; its brick count is bucketed to a
   power of two (static), its dims and the step budget are traced, so scans of one sensor
   share one compiled function.
2. **Jitted DDA** (``_trace``): all rays step together in a ``while_loop`` (until every ray
   has ended), exactly mirroring ``computeRayKeys`` (same tie-breaking, same early stop);
   each step marks its voxel in a dense ``int8`` box (1 = free); then the end voxels get 2
   (occupied wins). The dense box dedupes in O(1) per key instead of sorting tens of millions
   of ray keys (the "dense where it pays" of DESIGN.md §2). Bricks are laid out in Morton
   order of their codes and voxels inside a brick in local Morton order, so the box's cell
   order *is* global Morton order.
3. **Jitted extraction** (``_extract``): the marked cells of the non-empty bricks (counts
   known after step 2) become Morton code words, already sorted: no sort needed.
4. ``tree.apply_voxel_updates`` adds hit/miss log-odds with per-update clamping, expanding
   pruned leaves locally, and prunes maximally.

Precision: OctoMap does the DDA in ``double`` on ``float`` points; we do it in float32 (we do
not enable x64). Voxel sets agree up to rare DDA ties; ``tests/test_insert.py`` checks it
against pyoctomap's ``insertPointCloud`` (identical occupied voxels, free voxels up to DDA
ties, bit-identical log-odds on the common voxels).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import morton
from ._ops import any_of, bucket_capacity, nonzero_rows, quarter_octave_capacity, to_device
from .budget import check_allocation
from .kernel_store import stored_jit
from .map import OccupancyMap
from .tree import apply_voxel_updates

__all__ = ["ScanUpdate", "CapacityPlan", "compute_update", "insert_point_cloud",
           "insert_point_clouds", "MAX_BOX_CELLS"]

_OFFSET = morton.KEY_OFFSET
MAX_BOX_CELLS = 1 << 28  # dense dedupe box limit (int8 cells, 256 MiB)


class ScanUpdate(NamedTuple):
    """The voxels one scan updates (``compute_update``), sorted by Morton code.

    Rows past ``count`` are padding (sentinel code, ``occupied`` False).
    """

    words: jax.Array  # (K, 2) int32 Morton code words of finest voxels
    occupied: jax.Array  # (K,) bool: True = hit (end point), False = miss (traversed)
    count: jax.Array  # () int32 number of valid rows


def _ends(points, origin, max_range):
    """Per ray: (end point used for the DDA, whether the end voxel is a hit). float32 like
    OctoMap's ``point3d`` arithmetic (``computeUpdate``)."""
    diff = points - origin
    norm = jnp.sqrt(jnp.sum(diff * diff, axis=-1))
    within = (max_range < 0.0) | (norm <= max_range)
    direction = diff / jnp.where(norm > 0, norm, 1.0)[:, None]
    cut = origin + direction * max_range
    return jnp.where(within[:, None], points, cut), within


_BRICK_BITS = 3  # bricks of 8^3 voxels: exactly the depth-13 octree nodes
_BRICK = 1 << _BRICK_BITS
_BRICK_CELLS = _BRICK ** 3


@dataclasses.dataclass
class CapacityPlan:
    """High-water marks of the static sizes used by ``compute_update`` and by the tree update
    that applies it (``tree.apply_voxel_updates``); mutable, host only.

    Pass one plan to every scan of a run (``sim.make_two_robot_maps`` shares one between its
    two robots, ``octomerge build`` one per map): each static size only grows, so the jitted
    stages compile a handful of times per run instead of once per distinct scan shape.
    ``reserve`` pre-sizes from scans known in advance.
    """

    points: int = 0
    bricks: int = 0
    marked: int = 0
    marked_bricks: int = 0
    split_rows: int = 0  # the tree update's (``tree.apply_voxel_updates``)
    fill_rows: int = 0
    leaves: int = 0  # map capacity with headroom: a later map of the run starts at this size

    def grow(self, name: str, n: int, minimum: int) -> int:
        bucket = quarter_octave_capacity if name == "points" else bucket_capacity
        value = max(getattr(self, name), bucket(n, minimum))
        setattr(self, name, value)
        return value

    def reserve(self, points, sensor_origin, resolution: float, max_range: float = -1.0) -> None:
        """Grow the point and brick capacities to fit this scan (host work only)."""
        pts, origin = _check_scan(points, sensor_origin, resolution)
        if len(pts):
            self.grow("points", len(pts), 256)
            self.grow("bricks", _host_plan(pts, origin, float(max_range), resolution)[3], 64)


def _check_scan(points, sensor_origin, resolution):
    pts = np.asarray(points, dtype=np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points: expected shape (n, 3), got {pts.shape}")
    origin = np.asarray(sensor_origin, dtype=np.float32).reshape(-1)
    if origin.shape != (3,) or not np.all(np.isfinite(origin)):
        raise ValueError(f"sensor_origin: expected 3 finite coordinates, got {sensor_origin!r}")
    morton.coords_to_keys(origin, resolution, name="sensor_origin")
    return pts[np.all(np.isfinite(pts), axis=1)], origin


def _brick_ranks(brick_min, brick_dims, n_bricks, cap_b: int):
    """Rank of every brick of the box in Morton order of its code (padding ranks last).

    Bricks are numbered row-major over ``brick_dims`` (traced); returns ``(rank (cap_b,),
    brick_words_by_rank (cap_b, 2))``."""
    b = jnp.arange(cap_b, dtype=jnp.int32)
    dy, dz = brick_dims[1], brick_dims[2]
    ijk = jnp.stack([b // (dy * dz), (b // dz) % dy, b % dz], axis=-1)
    keys = jnp.clip((brick_min + ijk) * _BRICK, 0, 2 * _OFFSET - 1)
    words = morton.keys_to_words(keys)
    ok = b < n_bricks
    hi = jnp.where(ok, words[:, 0], morton.SENTINEL_HI)
    lo = jnp.where(ok, words[:, 1], 0)
    hi, lo, perm = jax.lax.sort((hi, lo, b), num_keys=2)
    rank = jnp.zeros((cap_b,), jnp.int32).at[perm].set(b)
    return rank, jnp.stack([hi, lo], axis=-1)


def _local_morton_table() -> np.ndarray:
    """``table[x | y << 3 | z << 6]`` = Morton index (0..511) of voxel ``(x, y, z)`` of a brick."""
    out = np.zeros(_BRICK_CELLS, np.int32)
    for i in range(_BRICK_CELLS):
        x, y, z = i & 7, (i >> 3) & 7, i >> 6
        out[i] = sum((((v >> bit) & 1) << (3 * bit + axis)) for bit in range(_BRICK_BITS)
                     for axis, v in enumerate((x, y, z)))
    return out


_LOCAL_MORTON = _local_morton_table()


def _local_morton(local):
    """Morton index (0..511) of a voxel inside its 8^3 brick (``local (..., 3)`` in 0..7), x in
    the lowest bit: one lookup in a 512-entry table."""
    return jnp.asarray(_LOCAL_MORTON)[local[..., 0] | (local[..., 1] << 3) | (local[..., 2] << 6)]


@stored_jit(static_argnames=("resolution", "cap_b"))
def _trace(points, valid, origin, max_range, brick_min, brick_dims, n_bricks, max_steps, *,
           resolution: float, cap_b: int):
    """DDA of every ray into a dense box of 8^3 bricks laid out in Morton order.

    ``brick_min (3,)`` / ``brick_dims (3,)`` (traced) give the box in brick units; it holds
    ``n_bricks <= cap_b`` bricks. Returns ``(grid (cap_b * 512,) int8`` with 0 unknown /
    1 free / 2 occupied, cells in global Morton order; ``brick_words (cap_b, 2)`` by rank;
    ``num_marked``; ``num_bricks_marked``; ``overflow``) where ``overflow`` counts keys
    outside the box and unfinished rays (0 unless the host plan is wrong).
    """
    points = points.astype(jnp.float32)
    origin = origin.astype(jnp.float32)
    rank, brick_words = _brick_ranks(brick_min, brick_dims, n_bricks, cap_b)
    ends, hit = _ends(points, origin, max_range)
    key_o, ok_o = morton.points_to_keys(origin, resolution)
    key_e, ok_e = morton.points_to_keys(ends, resolution)
    key_p, ok_p = morton.points_to_keys(points, resolution)
    n_cells = cap_b * _BRICK_CELLS
    box_lo = brick_min * _BRICK

    def flat(key, mask):
        local = key - box_lo
        brick = local >> _BRICK_BITS
        inside = jnp.all((local >= 0) & (brick < brick_dims), axis=-1)
        b = (brick[..., 0] * brick_dims[1] + brick[..., 1]) * brick_dims[2] + brick[..., 2]
        b = jnp.clip(b, 0, cap_b - 1)
        idx = rank[b] * _BRICK_CELLS + _local_morton(local & (_BRICK - 1))
        return jnp.where(mask & inside, idx, n_cells), mask & ~inside

    # computeRayKeys returns false (no free keys) unless both ends are in range; equal keys
    # give an empty ray.
    ray_ok = valid & ok_o & ok_e & jnp.any(key_o != key_e, axis=-1)
    direction = ends - origin
    length = jnp.sqrt(jnp.sum(direction * direction, axis=-1))
    direction = direction / jnp.where(length > 0, length, 1.0)[:, None]
    step = jnp.sign(direction).astype(jnp.int32)
    # keyToCoord(key) + step * res / 2: the voxel border the ray crosses next.
    border = ((key_o - _OFFSET).astype(jnp.float32) + 0.5) * resolution \
        + step.astype(jnp.float32) * (0.5 * resolution)
    safe_dir = jnp.where(step != 0, direction, 1.0)
    t_max = jnp.where(step != 0, (border - origin) / safe_dir, jnp.inf)
    t_delta = jnp.where(step != 0, resolution / jnp.abs(safe_dir), jnp.inf)

    grid = jnp.zeros((n_cells,), jnp.int8)
    idx0, bad0 = flat(jnp.broadcast_to(key_o, key_e.shape), ray_ok)
    grid = grid.at[idx0].set(jnp.int8(1), mode="drop")
    axes = jnp.arange(3, dtype=jnp.int32)

    def body(_, carry):
        grid, key, t_max, active, bad = carry
        t0, t1, t2 = t_max[:, 0], t_max[:, 1], t_max[:, 2]
        # OctoMap's argmin: ties go to the later axis
        dim = jnp.where(t0 < t1, jnp.where(t0 < t2, 0, 2), jnp.where(t1 < t2, 1, 2))
        onehot = axes[None, :] == dim[:, None]
        key = key + jnp.where(onehot, step, 0)
        t_max = t_max + jnp.where(onehot, t_delta, 0.0)
        reached = jnp.all(key == key_e, axis=-1)
        too_far = jnp.min(t_max, axis=-1) > length
        add = active & ~reached & ~too_far
        idx, bad_step = flat(key, add)
        grid = grid.at[idx].set(jnp.int8(1), mode="drop")
        return grid, key, t_max, add, bad | bad_step

    def cond(carry):
        i, (_, _, _, active, _) = carry
        return (i < max_steps) & any_of(active)

    init = (grid, jnp.broadcast_to(key_o, key_e.shape), t_max, ray_ok, bad0)
    _, (grid, _, _, active, bad) = jax.lax.while_loop(
        cond, lambda c: (c[0] + 1, body(c[0], c[1])), (jnp.int32(0), init))
    # Occupied end points (genKey(p) of the uncut point), written last: occupied wins.
    occ = valid & hit & ok_p
    idx_e, bad_e = flat(key_p, occ)
    grid = grid.at[idx_e].set(jnp.int8(2), mode="drop")
    overflow = jnp.sum(active | bad | bad_e, dtype=jnp.int32)
    per_brick = jnp.sum((grid > 0).reshape(cap_b, _BRICK_CELLS), axis=1, dtype=jnp.int32)
    return (grid, brick_words, jnp.sum(per_brick), jnp.sum(per_brick > 0, dtype=jnp.int32),
            overflow)


@stored_jit(static_argnames=("capacity", "brick_capacity"))
def _extract(grid, brick_words, *, capacity: int, brick_capacity: int) -> ScanUpdate:
    """Marked cells -> Morton words (already sorted: bricks by rank, cells by local Morton)."""
    cap_b = brick_words.shape[0]
    cells = grid.reshape(cap_b, _BRICK_CELLS)
    bricks = nonzero_rows(jnp.max(cells, axis=1) > 0, brick_capacity, cap_b)
    sub = jnp.take(cells, bricks, axis=0, mode="fill", fill_value=0)  # (brick_capacity, 512)
    idx = nonzero_rows(sub.reshape(-1) > 0, capacity, -1)
    ok = idx >= 0
    safe = jnp.maximum(idx, 0)
    slot, local = safe // _BRICK_CELLS, safe % _BRICK_CELLS
    bw = brick_words[jnp.clip(bricks[slot], 0, cap_b - 1)]
    hi = jnp.where(ok, bw[:, 0], morton.SENTINEL_HI)
    lo = jnp.where(ok, bw[:, 1] | local, 0)
    occupied = ok & (sub.reshape(-1)[safe] == 2)
    return ScanUpdate(jnp.stack([hi, lo], axis=-1), occupied, jnp.sum(ok, dtype=jnp.int32))


def _host_plan(points: np.ndarray, origin: np.ndarray, max_range: float, resolution: float):
    """Static sizes for a scan, in float64 with margins: ``(max_steps, brick_min (3,),
    brick_dims (3,), cap_b)``."""
    p = points.astype(np.float64)
    o = origin.astype(np.float64)
    if max_range >= 0:
        diff = p - o
        norm = np.linalg.norm(diff, axis=1)
        scale = np.where(norm > max_range, max_range / np.where(norm > 0, norm, 1.0), 1.0)
        ends = o + diff * scale[:, None]
        # the uncut end voxel of in-range rays is also written
        ends = np.concatenate([ends, p[norm <= max_range]], axis=0)
    else:
        ends = p
    factor = 1.0 / resolution
    k_o = np.floor(o * factor)
    k_e = np.floor(ends * factor)
    lo = np.clip(np.minimum(k_e.min(axis=0), k_o) - 2 + _OFFSET, 0, 2 * _OFFSET - 1)
    hi = np.clip(np.maximum(k_e.max(axis=0), k_o) + 2 + _OFFSET, 0, 2 * _OFFSET - 1)
    brick_min = (lo.astype(np.int64) >> _BRICK_BITS).astype(np.int32)
    brick_dims = ((hi.astype(np.int64) >> _BRICK_BITS) - brick_min + 1).astype(np.int32)
    n_bricks = int(np.prod(brick_dims, dtype=np.int64))
    l1 = np.abs(k_e - k_o).sum(axis=1).max() if len(ends) else 0
    # a DDA visits at most L1 + 1 voxels (+ margin for float ties)
    max_steps = int(l1) + 4
    return max_steps, brick_min, brick_dims, n_bricks


def compute_update(points, sensor_origin, resolution: float, max_range: float = -1.0, *,
                   plan: CapacityPlan | None = None) -> ScanUpdate:
    """OctoMap ``computeUpdate`` for one scan: the voxels to mark free and occupied.

    Args:
      points: ``(n, 3)`` end points [m] in the map frame (rounded to float32 like OctoMap's
        ``point3d``); non-finite points are dropped.
      sensor_origin: ``(3,)`` sensor position [m] in the map frame.
      resolution: voxel edge [m].
      max_range: rays longer than this [m] are cut and their end is not a hit; < 0: no limit.
      plan: optional ``CapacityPlan`` shared by the scans of a run (fewer compilations).

    Returns:
      ``ScanUpdate`` with code words sorted, capacity a power of two.
    Raises ``ValueError`` for malformed arguments or rays spanning more than
    ``MAX_BOX_CELLS`` voxels of bounding box (pass a ``max_range``).
    """
    pts, origin = _check_scan(points, sensor_origin, resolution)
    max_range = float(max_range)
    plan = CapacityPlan() if plan is None else plan
    n = pts.shape[0]
    cap = plan.grow("points", n, 256)
    if n == 0:
        words = np.zeros((cap, 2), np.int32)
        words[:, 0] = morton.SENTINEL_HI
        return ScanUpdate(jnp.asarray(words), jnp.zeros((cap,), bool), jnp.asarray(0, jnp.int32))
    max_steps, brick_min, brick_dims, n_bricks = _host_plan(pts, origin, max_range, resolution)
    if bucket_capacity(n_bricks, 64) * _BRICK_CELLS > MAX_BOX_CELLS:
        raise ValueError(
            f"points: the rays span {(brick_dims * _BRICK).tolist()} voxels (> {MAX_BOX_CELLS} "
            "cells); pass a smaller max_range or split the scan")
    cap_b = plan.grow("bricks", n_bricks, 64)
    # the box's int8 cells and their int32 work arrays, and the points' ray state
    check_allocation(cap_b * _BRICK_CELLS * 9 + cap * 96,
                     f"insert: a scan of {n} points needs a box of {n_bricks} bricks")
    padded = np.zeros((cap, 3), np.float32)
    padded[:n] = pts
    valid = np.arange(cap) < n
    grid, brick_words, marked, bricks, overflow = _trace(
        to_device(padded), to_device(valid), to_device(origin), to_device(max_range, np.float32),
        to_device(brick_min), to_device(brick_dims), to_device(n_bricks, np.int32),
        to_device(max_steps, np.int32), resolution=float(resolution), cap_b=cap_b)
    if int(overflow):
        raise RuntimeError(f"internal: {int(overflow)} rays left the planned box or step budget")
    return _extract(grid, brick_words, capacity=plan.grow("marked", int(marked), 256),
                    brick_capacity=min(plan.grow("marked_bricks", int(bricks), 64), cap_b))


def insert_point_cloud(m: OccupancyMap, points, sensor_origin, max_range: float = -1.0, *,
                       plan: CapacityPlan | None = None) -> OccupancyMap:
    """Insert one scan as OctoMap's ``insertPointCloud(cloud, origin, maxrange)`` does.

    Args:
      m: the map to update (its ``resolution`` and ``params`` are used).
      points: ``(n, 3)`` end points [m] in the map frame.
      sensor_origin: ``(3,)`` sensor position [m] in the map frame.
      max_range: maximum ray length [m]; longer rays are cut and not counted as hits.
      plan: optional ``CapacityPlan`` shared by the scans of a run (fewer compilations; the
        map then grows with headroom, as in ``insert_point_clouds``).

    Returns the updated map (pruned maximally; capacity grows to the next bucket if needed).
    Every traversed voxel gets one ``miss_log_odds``, every end voxel one ``hit_log_odds``
    per scan, clamped after each update.
    """
    upd = compute_update(points, sensor_origin, m.resolution, max_range, plan=plan)
    p = m.params
    deltas = jnp.where(upd.occupied, p.hit_log_odds, p.miss_log_odds).astype(jnp.float32)
    valid = jnp.arange(upd.occupied.shape[0]) < upd.count
    return apply_voxel_updates(m, upd.words, deltas, valid, sizes=plan)


def insert_point_clouds(m: OccupancyMap, clouds, sensor_origins, max_range: float = -1.0, *,
                        batch_size: int = 8, plan: CapacityPlan | None = None) -> OccupancyMap:
    """Insert a sequence of scans, equal to calling ``insert_point_cloud`` on each in order.

    The per-scan voxel updates of up to ``batch_size`` scans are concatenated (scan order)
    and applied in one ``apply_voxel_updates`` call, whose per-row clamping in row order
    gives exactly the sequential result (pruning in between never changes finest values).

    Args:
      clouds: sequence of ``(n_i, 3)`` point arrays [m] in the map frame.
      sensor_origins: ``(N, 3)`` sensor positions [m] in the map frame.
      max_range: as ``insert_point_cloud``'s.
      batch_size: scans whose updates are applied together.
      plan: optional ``CapacityPlan`` shared with other calls of the run (default: one sized
        from these scans). The map starts at the capacity the run reached and grows with
        headroom while the scans go in. Without a ``plan`` the result is trimmed to
        ``bucket_capacity`` of its leaves (never below the capacity it came with); with one it
        keeps the run's capacity, so the run's next call neither copies nor recompiles (trim
        with ``m.trimmed()`` at the end of the run).

    Returns the updated map. Raises ``ValueError`` for malformed arguments.
    """
    clouds = list(clouds)
    origins = np.asarray(sensor_origins, dtype=np.float32).reshape(-1, 3)
    if len(clouds) != len(origins):
        raise ValueError(f"clouds and sensor_origins differ in length: {len(clouds)} vs {len(origins)}")
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    own_plan = plan is None
    if own_plan:
        plan = CapacityPlan()
        for pts, o in zip(clouds, origins):
            plan.reserve(pts, o, m.resolution, max_range)
    p = m.params
    capacity = m.capacity
    if plan.leaves > m.capacity:  # a later map of the run starts at the size the earlier ones reached
        m = m.with_capacity(plan.leaves)
    for start in range(0, len(clouds), batch_size):
        words, deltas = [], []
        for pts, o in zip(clouds[start:start + batch_size], origins[start:start + batch_size]):
            upd = compute_update(pts, o, m.resolution, max_range, plan=plan)
            k = int(upd.count)
            # sliced on the host: a device slice compiles a program for every length k
            words.append(np.asarray(upd.words)[:k])
            deltas.append(np.where(np.asarray(upd.occupied)[:k], np.float32(p.hit_log_odds),
                                   np.float32(p.miss_log_odds)).astype(np.float32))
        n = sum(len(d) for d in deltas)
        if n == 0:
            continue
        cap = bucket_capacity(n, plan.marked * min(batch_size, len(clouds)))
        w = np.zeros((cap, 2), np.int32)
        w[:, 0] = morton.SENTINEL_HI
        d = np.zeros((cap,), np.float32)
        w[:n] = np.concatenate(words)
        d[:n] = np.concatenate(deltas)
        m = apply_voxel_updates(m, to_device(w), to_device(d), to_device(np.arange(cap) < n), sizes=plan)
    return m.trimmed(capacity) if own_plan else m  # the headroom of the updates removed
