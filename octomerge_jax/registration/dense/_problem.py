"""The dense alignment's problem: host planning of the coarse-to-fine levels
(``prepare_alignment``), the ``AlignProblem`` pytree, per-level views of it, and the pose
parametrisation the solver searches over (``pose_from_increment``)."""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ... import morton, se3
from ..._ops import is_traced, to_device
from ...leaf_index import LeafIndex, index_shift, key_box, leaf_index
from ...map import OccupancyMap, bucket_capacity, leaves_cache
from ...tree import coarsen

__all__ = ["AlignProblem", "Level", "LevelPair", "both_at", "default_levels", "level_at",
           "pose_from_increment", "prepare_alignment", "stack_problems"]

_D = morton.TREE_DEPTH


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class AlignProblem:
    """Host-prepared input of ``solve_alignment`` / ``problem_loss`` (a pytree; stack several
    with ``stack_problems`` to ``vmap`` over pairs). ``L`` levels, coarse to fine, stacked on
    a leading axis so one compiled solver step serves all of them:

    - ``map1``: map 1 coarsened by ``2^k`` per level (``OccupancyMap`` with arrays of leading
      shape ``(L,)`` and one capacity). Coarse cells are stored as depth-16 voxels *of the
      finest resolution* ``res``; sampling at metric points ``y * scale`` reads the coarse map
      as if its resolution were ``res * 2^k`` (exact: centres scale with the key grid), so
      every level shares one static resolution.
    - ``scale``: ``(L,)`` float32, ``2^-k``.
    - ``points2``: ``(L, P, 3)`` float32 [m], sample points of map 2 (coarse-cell centres) in
      map 2's frame; padding rows are zeros.
    - ``signed2``: ``(L, P)`` float32, map 2's signed occupancy ``tanh(l / 2)`` at each point.
    - ``weight2``: ``(L, P)`` float32, non-negative, summing to 1 per level (0 on padding).
    - ``occupied2``: ``(L, P)`` bool, the point is occupied in map 2 (status checks).
    - ``center2``: ``(3,)`` float32 [m], centroid of map 2's finest sample points (frame 2),
      the pivot of the rotation increment; ``radius``: ``()`` float32 [m], their RMS
      distance to it (rotation scale).
    - ``coverage_norm``: ``(L,)`` float32 in [0, 1], how much of the loss denominator is the
      commonly known weight (1: ``sum w C + 0.1 sum w``; 0: ``sum w``, the plain mean).
    - ``levels``: static tuple of the coarsening exponents ``k``.
    - ``reverse``: the finest level's problem with the maps' roles swapped (map 2 sampled at
      map 1's points; one level), or ``None``; with it the finest level's loss is symmetric;
      the coarser levels and the status checks stay map 2 -> 1.
    - ``index1``: ``map1``'s ``leaf_index`` per level (arrays stacked like ``map1``'s), which
      narrows the loss's lookups to a few leaves each (the same leaves), or ``None`` (whole
      binary searches). It describes ``map1``: a problem built with another ``map1`` needs its
      own index or ``None``.
    """

    map1: OccupancyMap
    scale: jax.Array
    points2: jax.Array
    signed2: jax.Array
    weight2: jax.Array
    occupied2: jax.Array
    center2: jax.Array
    radius: jax.Array
    coverage_norm: jax.Array
    levels: tuple = dataclasses.field(metadata=dict(static=True), default=(0,))
    reverse: "AlignProblem | None" = None
    index1: LeafIndex | None = None

    @property
    def num_levels(self) -> int:
        return len(self.levels)


class Level(NamedTuple):
    """One level of an unbatched ``AlignProblem`` (its fields at index ``i``)."""

    map1: OccupancyMap         # map 1 coarsened by 2^k, labelled at the finest resolution
    scale: jax.Array           # () float32, 2^-k
    points2: jax.Array         # (P, 3) float32 [m], map 2's sample points (frame 2)
    signed2: jax.Array         # (P,) float32, map 2's signed occupancy there
    weight2: jax.Array         # (P,) float32, sample weights (sum 1)
    occupied2: jax.Array       # (P,) bool, occupied in map 2
    coverage_norm: jax.Array   # () float32 in [0, 1]
    index: LeafIndex | None = None  # map1's leaf index, or None


class LevelPair(NamedTuple):
    """A level and what its loss needs to be symmetric."""

    forward: Level                  # map 2's points in map 1
    reverse: "Level | None"         # the reverse problem's finest level, or None (one-way)
    finest: "bool | jax.Array"      # the level is the finest (the reverse applies); traced or not


def level_at(problem: AlignProblem, i) -> Level:
    """Level ``i`` (int or traced) of an unbatched problem."""
    take = lambda a: a[i]  # noqa: E731
    index = None if problem.index1 is None else jax.tree_util.tree_map(take, problem.index1)
    return Level(jax.tree_util.tree_map(take, problem.map1), problem.scale[i], problem.points2[i],
                 problem.signed2[i], problem.weight2[i], problem.occupied2[i], problem.coverage_norm[i], index)


def both_at(problem: AlignProblem, i) -> LevelPair:
    """Level ``i`` (an int, negative counts from the end, or traced) with the reverse
    problem's finest level when the problem is symmetric."""
    if problem.reverse is None:
        return LevelPair(level_at(problem, i), None, False)
    last = problem.num_levels - 1
    finest = i % problem.num_levels == last if isinstance(i, (int, np.integer)) else jnp.asarray(i) == last
    return LevelPair(level_at(problem, i), level_at(problem.reverse, 0), finest)


def pose_from_increment(T_start, z, center, radius):
    """``T_start (4, 4) @ C exp([z[:3], z[3:] / radius]) C^-1`` with ``C = [I | center]``.

    ``z (6,)``: translation [m] and rotation scaled to arc length at ``radius`` [m] (so both
    halves are in metres), applied in the frame of ``T_start``'s source about ``center (3,)``.
    """
    xi = jnp.concatenate([z[:3], z[3:] / radius])
    E = se3.se3_exp(xi)
    R, t = E[:3, :3], E[:3, 3]
    t = t + center - R @ center
    return T_start @ se3.from_rotation_translation(R, t)


def default_levels(resolution: float, coarsest: float = 0.8) -> tuple[int, ...]:
    """Coarse-to-fine exponents ``(K, ..., 1, 0)`` whose coarsest cell ``res * 2^K`` is at most
    ``coarsest`` metres."""
    K = int(np.floor(np.log2(max(coarsest / float(resolution), 1.0)) + 1e-9))
    return tuple(range(K, -1, -1))


# ----------------------------------------------------------------------------- host planning


class _LevelSamples(NamedTuple):
    """Host arrays of one level before padding (``n`` sample points of map 2)."""

    map1: OccupancyMap     # map 1 coarsened by 2^k, labelled at the finest resolution
    box1: tuple            # (first, last) (3,) int64: the keys map1's leaves cover (leaf_index.key_box)
    points: np.ndarray     # (n, 3) float64 [m], frame 2
    signed: np.ndarray     # (n,) float64, tanh(l / 2)
    weight: np.ndarray     # (n,) float64, sum 1
    occupied: np.ndarray   # (n,) bool


def _cell_samples(m: OccupancyMap, mask: np.ndarray, budget: int, rng,
                  jitter: bool) -> tuple[np.ndarray, np.ndarray]:
    """Points ``(n, 3)`` [m] and log-odds of the depth-16 cells of the leaves selected by
    ``mask``: all of them if they fit in ``budget``, else ``budget`` cells drawn uniformly
    (by volume) without replacement. With ``jitter`` each point is drawn uniformly inside its
    cell instead of at the centre."""
    lv = m.leaves()
    codes, depths, lo = lv.codes[mask], lv.depths[mask], lv.log_odds[mask]
    if codes.size == 0 or budget <= 0:
        return np.zeros((0, 3)), np.zeros(0, np.float32)
    total = int(morton.leaf_cell_counts(depths).sum())
    idx = None if total <= budget else np.sort(rng.choice(total, size=budget, replace=False))
    cell_codes, leaf = morton.leaf_cell_codes(codes, depths, idx)
    keys = morton.codes_to_keys(cell_codes)
    centres = morton.keys_to_coords(keys, m.resolution)
    if jitter:
        centres = centres + rng.uniform(-0.5, 0.5, centres.shape) * m.resolution
    return centres, lo[leaf]


def _level_samples(m1: OccupancyMap, m2: OccupancyMap, box1, k: int, max_points: int, free_weight: float,
                   rng, jitter: bool) -> _LevelSamples:
    """Host: level ``k``'s coarse map 1 (``box1``: the keys ``m1``'s leaves cover) and map 2's
    weighted sample points (occupied first)."""
    c1 = coarsen(m1, k, resolution=m1.resolution)
    c2 = coarsen(m2, k)
    lv2 = c2.leaves()
    thr = float(np.asarray(m2.params.occupancy_threshold_log_odds))
    occ = lv2.log_odds >= thr
    p_occ, l_occ = _cell_samples(c2, occ, max_points // 2, rng, jitter)
    p_free, l_free = _cell_samples(c2, ~occ, max_points - p_occ.shape[0], rng, jitter)
    n_occ, n_free = p_occ.shape[0], p_free.shape[0]
    pts = np.concatenate([p_occ, p_free])
    lo = np.concatenate([l_occ, l_free]).astype(np.float64)
    w = np.concatenate([np.full(n_occ, 1.0 / max(n_occ, 1)),
                        np.full(n_free, float(free_weight) / max(n_free, 1))])
    w = w / max(w.sum(), 1e-30)
    return _LevelSamples(c1, _coarsened_box(box1, k), pts, np.tanh(lo / 2.0), w, np.arange(pts.shape[0]) < n_occ)


def _coarsened_box(box, k: int) -> tuple:
    """The key box ``(first, last)`` of a map's leaves after ``coarsen(., k)`` (each key
    ``K`` relabelled ``KEY_OFFSET + (K - KEY_OFFSET) >> k``: monotone per axis)."""
    return tuple(((np.asarray(b, np.int64) - morton.KEY_OFFSET) >> k) + morton.KEY_OFFSET for b in box)


def _checked_levels(m1: OccupancyMap, m2: OccupancyMap, levels, max_points, free_weight) -> tuple:
    """Validate ``prepare_alignment``'s maps and options; the levels as a tuple of ints."""
    if m1.resolution != m2.resolution:
        raise ValueError(f"m1 and m2 must share a resolution, got {m1.resolution} and {m2.resolution}")
    if m1.num_leaves == 0 or m2.num_leaves == 0:
        raise ValueError("m1 and m2 must both hold leaves")
    levels = default_levels(m1.resolution) if levels is None else tuple(int(k) for k in levels)
    if not levels or any(not 0 <= k < _D for k in levels):
        raise ValueError(f"levels must be a non-empty sequence of ints in 0..15, got {levels}")
    if int(max_points) < 8:
        raise ValueError(f"max_points must be at least 8, got {max_points}")
    if not (np.isfinite(free_weight) and free_weight >= 0):
        raise ValueError(f"free_weight must be a non-negative number, got {free_weight!r}")
    return levels


def _capacities(built, map_capacity, point_capacity) -> tuple[int, int]:
    """Static capacities ``(map, points)`` shared by all levels (default: bucket of the largest)."""
    n_map = max(b.map1.num_leaves for b in built)
    n_pts = max(b.points.shape[0] for b in built)
    mcap = bucket_capacity(n_map) if map_capacity is None else int(map_capacity)
    pcap = bucket_capacity(n_pts) if point_capacity is None else int(point_capacity)
    if mcap < n_map:
        raise ValueError(f"map_capacity {mcap} is smaller than the {n_map} leaves of a level")
    if pcap < n_pts:
        raise ValueError(f"point_capacity {pcap} is smaller than the {n_pts} points of a level")
    return mcap, pcap


def _pivot(points: np.ndarray, resolution: float) -> tuple[np.ndarray, float]:
    """Centroid ``(3,)`` [m] of the finest sample points and their RMS radius [m] about it
    (at least ten voxels)."""
    center = points.mean(axis=0) if points.size else np.zeros(3)
    radius = np.sqrt(np.mean(np.sum((points - center) ** 2, axis=1))) if points.size else 1.0
    return center, max(float(radius), 10.0 * resolution)


def _assemble(built, levels: tuple, mcap: int, pcap: int, center, radius: float, cn,
              reverse) -> AlignProblem:
    """The ``AlignProblem`` of the levels ``built``: arrays padded to ``pcap`` points, map 1's
    copies to ``mcap`` leaves, stacked on a leading axis."""

    def pad(a, fill=0.0, dtype=np.float32):
        out = np.full((pcap,) + a.shape[1:], fill, dtype)
        out[:a.shape[0]] = a
        return out

    maps = [b.map1.with_capacity(mcap) for b in built]
    indexes = None if is_traced(*jax.tree_util.tree_leaves(maps)) else _level_indexes(maps, [b.box1 for b in built])
    return AlignProblem(
        # stacked on the host unless traced: a device stack compiles a program per leaf shape
        map1=jax.tree_util.tree_map(lambda *a: jnp.stack(a) if is_traced(*a) else to_device(
            np.stack([np.asarray(x) for x in a])), *maps),
        scale=to_device([2.0 ** -k for k in levels], np.float32),
        points2=to_device(np.stack([pad(b.points) for b in built])),
        signed2=to_device(np.stack([pad(b.signed) for b in built])),
        weight2=to_device(np.stack([pad(b.weight) for b in built])),
        occupied2=to_device(np.stack([pad(b.occupied, False, bool) for b in built])),
        center2=to_device(center, np.float32),
        radius=to_device(radius, np.float32),
        coverage_norm=to_device(cn, np.float32),
        levels=levels,
        reverse=reverse,
        index1=indexes,
    )


def _level_indexes(maps, boxes) -> LeafIndex | None:
    """The levels' ``leaf_index`` stacked (one cell size and capacity for all), or ``None``
    when a level's box does not fit ``MAX_INDEX_CELLS`` at any cell size."""
    shifts = [index_shift(b) for b in boxes]
    if any(s is None for s in shifts):
        return None
    s = max(shifts)
    cells = max(int(np.prod((last >> s) - (first >> s) + 1)) for first, last in boxes)
    indexes = [leaf_index(m, bucket_capacity(cells), s, box) for m, box in zip(maps, boxes)]
    if any(i is None for i in indexes):
        return None
    return jax.tree_util.tree_map(lambda *a: to_device(np.stack([np.asarray(x) for x in a])), *indexes)


def prepare_alignment(m1: OccupancyMap, m2: OccupancyMap, *, levels=None,
                      max_points: int = 8192, free_weight: float = 0.5, seed: int = 0,
                      jitter: bool = True, map_capacity: int | None = None,
                      point_capacity: int | None = None,
                      coverage_norm=1.0, symmetric: bool = True) -> AlignProblem:
    """Host planning for ``solve_alignment`` / ``problem_loss``.

    Args:
      m1, m2: the maps (same resolution); map 1 is sampled, map 2 provides the points.
      levels: coarsening exponents, coarse to fine (``k`` -> cells of ``res * 2^k``; each
        coarse cell takes the maximum log-odds of its known children, ``tree.coarsen``);
        default ``default_levels(res)`` (coarsest cell <= 0.8 m); ``(0,)`` for the finest
        level only.
      max_points: sample points of map 2 per level (up to half occupied cells, the rest free
        cells drawn by volume with ``seed``); all known cells when they fit. The finest
        level's optimum is then a Monte-Carlo estimate.
      free_weight: total weight of the free points relative to the occupied ones.
      jitter: draw each point uniformly inside its cell (seeded) rather than at the centre, so
        the kinks of trilinear interpolation (on the planes of voxel centres) do not line up
        at the optimum; the loss becomes a Monte-Carlo estimate of the voxel-volume overlap
        integral, which is C1 in the pose.
      coverage_norm: per level (or one number for all) in [0, 1]: 1 divides the agreement
        by the commonly known weight, 0 by the total sample weight (the plain mean; unknown
        space counts as neutral); in between, a blend.
      map_capacity, point_capacity: static capacities of the coarsened map 1 and of the points
        (default ``bucket_capacity`` of the largest level): fix them to share one compilation
        across pairs, or to stack problems (the reverse problem of a symmetric one gets them too).
      symmetric: also prepare the finest level's reverse problem (map 2 sampled at map 1's
        points under ``T_1_2^-1``) and average the two losses there (``AlignProblem.reverse``),
        at twice the finest level's work.

    Returns:
      ``AlignProblem``.

    Raises:
      ValueError: naming the argument, on mismatched resolutions, empty maps or bad options.
    """
    levels = _checked_levels(m1, m2, levels, max_points, free_weight)
    rng = np.random.default_rng(seed)
    with leaves_cache():  # each map's host leaves decoded once: its key box, every level's coarsening
        box1 = key_box(m1)
        built = [_level_samples(m1, m2, box1, k, int(max_points), float(free_weight), rng, bool(jitter))
                 for k in levels]
        mcap, pcap = _capacities(built, map_capacity, point_capacity)
        center, radius = _pivot(built[-1].points, m2.resolution)
        cn = np.broadcast_to(np.asarray(coverage_norm, np.float64), (len(levels),))
        if not np.all((cn >= 0) & (cn <= 1)):
            raise ValueError(f"coverage_norm must lie in [0, 1], got {coverage_norm!r}")
        reverse = None
        if symmetric:
            try:
                reverse = prepare_alignment(m2, m1, levels=levels[-1:], max_points=max_points,
                                            free_weight=free_weight, seed=seed, jitter=jitter,
                                            map_capacity=map_capacity, point_capacity=point_capacity,
                                            coverage_norm=cn[-1:], symmetric=False)
            except ValueError as err:
                raise ValueError(f"{err} (in the reverse problem: map 2 at the finest level, sampled at map 1's "
                                 "points; symmetric=False skips it)") from None
        return _assemble(built, levels, mcap, pcap, center, radius, cn, reverse)


def stack_problems(problems) -> AlignProblem:
    """Stack problems of several pairs (same ``levels``, resolution and capacities: pass
    ``map_capacity`` / ``point_capacity`` to ``prepare_alignment``) along a new leading axis,
    for ``solve_alignment_batch``.

    Raises:
      ValueError: ``problems`` is empty or its members differ in levels, resolution or capacities.
    """
    problems = list(problems)
    if not problems:
        raise ValueError("problems must not be empty")
    p0 = problems[0]
    for i, p in enumerate(problems):
        r, r0 = p.reverse, p0.reverse
        if (p.levels != p0.levels or p.map1.resolution != p0.map1.resolution
                or p.map1.code.shape != p0.map1.code.shape or p.points2.shape != p0.points2.shape
                or (r is None) != (r0 is None)
                or (r is not None and (r.map1.code.shape != r0.map1.code.shape
                                       or r.points2.shape != r0.points2.shape))):
            raise ValueError(f"problems[{i}] differs from problems[0] in levels, resolution or "
                             "capacities; prepare them with equal map_capacity and point_capacity")
    # the pairs' leaf indexes differ in size: the stacked problem searches whole leaf arrays
    bare = [dataclasses.replace(p, index1=None, reverse=None if p.reverse is None else
                                dataclasses.replace(p.reverse, index1=None)) for p in problems]
    return jax.tree_util.tree_map(lambda *a: jnp.stack(a), *bare)
