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

1. **Host plan**: bucket the point count (power of two), the DDA step count (the L1 key
   distance of the longest ray, rounded up) and a dense key box enclosing every ray (each axis
   rounded up to a power of two). These static sizes select the compiled function.
2. **Jitted DDA** (``_trace``): all rays step together in a ``fori_loop`` of ``max_steps``
   iterations, exactly mirroring ``computeRayKeys`` (same tie-breaking, same early stop);
   each step marks its voxel in a dense ``int8`` box (1 = free); then the end voxels get 2
   (occupied wins). The dense box dedupes in O(1) per key instead of sorting tens of millions
   of ray keys (the "dense where it pays" of DESIGN.md §2; a scan's rays span a few million
   voxels at most).
3. **Jitted extraction** (``_extract``): the marked cells (count known after step 2) become
   Morton code words, sorted.
4. ``tree.apply_voxel_updates`` adds hit/miss log-odds with per-update clamping, expanding
   pruned leaves locally, and prunes maximally.

Precision: OctoMap does the DDA in ``double`` on ``float`` points; we do it in float32 (we do
not enable x64). Voxel sets agree up to rare DDA ties; ``tests/test_insert.py`` measures the
agreement against pyoctomap's ``insertPointCloud``.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import morton
from .map import OccupancyMap, bucket_capacity
from .tree import apply_voxel_updates

__all__ = ["ScanUpdate", "compute_update", "insert_point_cloud", "MAX_BOX_CELLS"]

_OFFSET = morton.KEY_OFFSET
MAX_BOX_CELLS = 1 << 28  # dense dedupe box limit (int8 cells, 256 MiB)
_BOX_STEP = 32


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


@partial(jax.jit, static_argnames=("resolution", "max_steps", "box"))
def _trace(points, valid, origin, max_range, box_min, *, resolution: float, max_steps: int,
           box: tuple[int, int, int]):
    """DDA of every ray into a dense box of ``box`` cells whose min key is ``box_min``.

    Returns ``(grid (prod(box),) int8 with 0 unknown / 1 free / 2 occupied, num_marked,
    overflow)``; ``overflow`` counts in-box violations and unfinished rays (must be 0).
    """
    points = points.astype(jnp.float32)
    origin = origin.astype(jnp.float32)
    ends, hit = _ends(points, origin, max_range)
    key_o, ok_o = morton.points_to_keys(origin, resolution)
    key_e, ok_e = morton.points_to_keys(ends, resolution)
    key_p, ok_p = morton.points_to_keys(points, resolution)
    dx, dy, dz = box
    n_cells = dx * dy * dz

    def flat(key, mask):
        local = key - box_min
        inside = jnp.all((local >= 0) & (local < jnp.array(box, jnp.int32)), axis=-1)
        idx = (local[..., 0] * dy + local[..., 1]) * dz + local[..., 2]
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

    init = (grid, jnp.broadcast_to(key_o, key_e.shape), t_max, ray_ok, bad0)
    grid, _, _, active, bad = jax.lax.fori_loop(0, max_steps, body, init)
    # Occupied end points (genKey(p) of the uncut point), written last: occupied wins.
    occ = valid & hit & ok_p
    idx_e, bad_e = flat(key_p, occ)
    grid = grid.at[idx_e].set(jnp.int8(2), mode="drop")
    overflow = jnp.sum(active | bad | bad_e, dtype=jnp.int32)
    return grid, jnp.sum(grid > 0, dtype=jnp.int32), overflow


@partial(jax.jit, static_argnames=("capacity", "box"))
def _extract(grid, box_min, *, capacity: int, box: tuple[int, int, int]) -> ScanUpdate:
    """Marked cells of the dense box -> sorted Morton words, occupied flags, count."""
    (idx,) = jnp.nonzero(grid > 0, size=capacity, fill_value=-1)
    ok = idx >= 0
    safe = jnp.maximum(idx, 0)
    dx, dy, dz = box
    keys = jnp.stack([safe // (dy * dz), (safe // dz) % dy, safe % dz], axis=-1) + box_min
    words = morton.keys_to_words(keys)
    hi = jnp.where(ok, words[:, 0], morton.SENTINEL_HI)
    lo = jnp.where(ok, words[:, 1], 0)
    occupied = ok & (grid[safe] == 2)
    hi, lo, occupied = jax.lax.sort((hi, lo, occupied), num_keys=2)
    return ScanUpdate(jnp.stack([hi, lo], axis=-1), occupied, jnp.sum(ok, dtype=jnp.int32))


def _host_plan(points: np.ndarray, origin: np.ndarray, max_range: float, resolution: float):
    """Static sizes (max_steps, box, box_min) for a scan, computed in float64 with margins."""
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
    lo = np.minimum(k_e.min(axis=0), k_o) - 2
    hi = np.maximum(k_e.max(axis=0), k_o) + 2
    lo = np.clip(lo + _OFFSET, 0, 2 * _OFFSET - 1)
    hi = np.clip(hi + _OFFSET, 0, 2 * _OFFSET - 1)
    # each axis rounded up to a multiple of 32 cells: few distinct compiled shapes without
    # the up-to-8x volume of power-of-two boxes
    box = tuple(int(_BOX_STEP * np.ceil((h - l + 1) / _BOX_STEP)) for l, h in zip(lo, hi))
    l1 = np.abs(k_e - k_o).sum(axis=1).max() if len(ends) else 0
    # a DDA visits at most L1 + 1 voxels (+ margin for float ties); multiples of 64 steps
    max_steps = int(64 * np.ceil((l1 + 4) / 64))
    return max_steps, box, lo.astype(np.int32)


def compute_update(points, sensor_origin, resolution: float, max_range: float = -1.0) -> ScanUpdate:
    """OctoMap ``computeUpdate`` for one scan: the voxels to mark free and occupied.

    Args:
      points: ``(n, 3)`` end points [m] in the map frame (rounded to float32 like OctoMap's
        ``point3d``); non-finite points are dropped.
      sensor_origin: ``(3,)`` sensor position [m] in the map frame.
      resolution: voxel edge [m].
      max_range: rays longer than this [m] are cut and their end is not a hit; < 0: no limit.

    Returns:
      ``ScanUpdate`` with code words sorted, capacity a power of two.
    Raises ``ValueError`` for malformed arguments or a ray box beyond ``MAX_BOX_CELLS``
    (pass a ``max_range``).
    """
    pts = np.asarray(points, dtype=np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points: expected shape (n, 3), got {pts.shape}")
    origin = np.asarray(sensor_origin, dtype=np.float32).reshape(-1)
    if origin.shape != (3,) or not np.all(np.isfinite(origin)):
        raise ValueError(f"sensor_origin: expected 3 finite coordinates, got {sensor_origin!r}")
    max_range = float(max_range)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    morton.coords_to_keys(origin, resolution, name="sensor_origin")
    n = pts.shape[0]
    cap = bucket_capacity(n)
    if n == 0:
        words = np.zeros((cap, 2), np.int32)
        words[:, 0] = morton.SENTINEL_HI
        return ScanUpdate(jnp.asarray(words), jnp.zeros((cap,), bool), jnp.asarray(0, jnp.int32))
    max_steps, box, box_min = _host_plan(pts, origin, max_range, resolution)
    cells = int(np.prod(box, dtype=np.int64))
    if cells > MAX_BOX_CELLS:
        raise ValueError(
            f"points: the rays span {box} voxels ({cells} > {MAX_BOX_CELLS}); pass a smaller "
            "max_range or split the scan")
    padded = np.zeros((cap, 3), np.float32)
    padded[:n] = pts
    valid = np.arange(cap) < n
    grid, marked, overflow = _trace(
        jnp.asarray(padded), jnp.asarray(valid), jnp.asarray(origin), jnp.float32(max_range),
        jnp.asarray(box_min), resolution=float(resolution), max_steps=max_steps, box=box)
    if int(overflow):
        raise RuntimeError(f"internal: {int(overflow)} rays left the planned box or step budget")
    return _extract(grid, jnp.asarray(box_min), capacity=bucket_capacity(int(marked)), box=box)


def insert_point_cloud(m: OccupancyMap, points, sensor_origin, max_range: float = -1.0,
                       ) -> OccupancyMap:
    """Insert one scan as OctoMap's ``insertPointCloud(cloud, origin, maxrange)`` does.

    Args:
      m: the map to update (its ``resolution`` and ``params`` are used).
      points: ``(n, 3)`` end points [m] in the map frame.
      sensor_origin: ``(3,)`` sensor position [m] in the map frame.
      max_range: maximum ray length [m]; longer rays are cut and not counted as hits.

    Returns the updated map (pruned maximally; capacity grows to the next bucket if needed).
    Every traversed voxel gets one ``miss_log_odds``, every end voxel one ``hit_log_odds``
    per scan, clamped after each update.
    """
    upd = compute_update(points, sensor_origin, m.resolution, max_range)
    p = m.params
    deltas = jnp.where(upd.occupied, p.hit_log_odds, p.miss_log_odds).astype(jnp.float32)
    valid = jnp.arange(upd.occupied.shape[0]) < upd.count
    return apply_voxel_updates(m, upd.words, deltas, valid)
