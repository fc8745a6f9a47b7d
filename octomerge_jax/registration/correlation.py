"""Global pose search by occupancy correlation: a yaw grid x every translation (FFT).

``icp_multi``'s default hypotheses turn the initial guess about the source's centroid; the
translation stays the guess's. When the maps overlap only partly, or the guess's yaw error
is large (the guess rotates map 2 about a point metres from where the error was made), the
right yaw starts metres off and whole-cloud ICP slides it along a corridor or turns it onto
the other map's larger part, and neither a longer ICP nor the dense alignment leaves such a
slide. This is the missing global step: for every
yaw ``theta_j`` of a fine grid (the guess's roll and pitch kept), map 2's cells are
correlated with *signed* grids of map 1 over all translations at once (FFT products per yaw),
and the best-scoring poses become the starts of the local refinement.

**Score** of a pose, over grid cells of edge ``cell`` [m]: ``N(t) / (D(t) + 0.1 W)`` with
``N(t) = sum_x g2(x) s1(x + t)`` and ``D(t) = sum_x w2(x) k1(x + t)``. Map 2's cells (at
``cell / 2``, moved by ``theta_j``) carry weights ``w2`` (its occupied cells 1 in total, its
free cells ``free_weight`` in total; ``W`` = all weight) and ``g2 = +w2`` occupied, ``-w2``
free. ``s1`` is map 1's signed occupancy (+1 occupied, -1 free, 0 unknown) and ``k1`` its
known indicator, both blurred by ``[1/4, 1/2, 1/4]`` per axis (one cell of tolerance for
surfaces voxelised in two frames). So ``N`` counts agreement (surface on surface, free on
free) minus disagreement, and ``D`` the commonly known space: the dense loss's normalisation
(``registration/dense/``), which keeps a slide into more overlap from scoring better by overlap alone;
the ``0.1 W`` keeps a sliver of overlap from scoring as perfect. With points (no map), map 1
has no free space and ``D`` is ``W``: the score is surface overlap. Unlike ICP, no
correspondence distance limits where the optimum can lie: the whole translation range of the
two grids is searched.

**Cost**: per yaw two scatters of map 2's cells and two real FFT pairs of the padded grid
(``S1 + S2 - 1`` cells per axis, rounded up to ``2^a`` or ``3 * 2^a``) and a separable max filter for
the local peaks; the yaws run one after another (``lax.map``) under one ``jit``. ``cell``
defaults to ``max(0.2 m, 2 res)`` rounded to ``res * 2^k`` and grows (x2) until the padded
grid has at most ``max_cells`` cells. The yaw step defaults to ``cell / r`` (one cell of
arc at the source's RMS radius ``r`` [m]), clipped to 1-6 degrees, and the number of yaws
is rounded up to a multiple of 8 (with the grid lengths: few compiled shapes).
"""

from __future__ import annotations

import dataclasses
import math
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from .. import morton
from ..map import OccupancyMap, bucket_capacity
from ..tree import coarsen
from .. import se3

__all__ = ["CorrelationResult", "correlation_search"]


@partial(jax.tree_util.register_dataclass, data_fields=["hypotheses", "scores", "yaws"], meta_fields=["cell"])
@dataclasses.dataclass(frozen=True)
class CorrelationResult:
    """``hypotheses (k, 4, 4)`` float64 ``T_1_2`` (map 2 -> map 1), best first; ``scores (k,)``
    their score ``N / (D + 0.1 W)`` (module docstring; below 1, higher is better);
    ``yaws (k,)`` [rad] the yaw turned onto the guess's rotation; ``cell``
    [m] the grid's cell edge."""

    hypotheses: np.ndarray
    scores: np.ndarray
    yaws: np.ndarray
    cell: float


def _grid_len(n: int) -> int:
    """Padded grid length for ``n`` cells: the next ``2^a`` or ``3 * 2^a`` (fast FFT sizes, and
    few of them, so map pairs of similar extents share one compiled search)."""
    p = 1 << max(int(n - 1).bit_length(), 0)
    return 3 * p // 4 if p >= 4 and 3 * p // 4 >= n else p


def _map_cells(m: OccupancyMap, k: int):
    """Host: every cell of ``m`` coarsened by ``2^k`` (``tree.coarsen``'s max rule) as
    ``(cell indices (n, 3) int64, occupied (n,) bool)``; cell ``i`` spans ``[i, i + 1) * res 2^k``."""
    lv = coarsen(m, k).leaves()
    thr = float(np.asarray(m.params.occupancy_threshold_log_odds))
    cell_codes, leaf = morton.leaf_cell_codes(lv.codes, lv.depths)
    keys = morton.codes_to_keys(cell_codes).astype(np.int64) - morton.KEY_OFFSET
    return keys, lv.log_odds[leaf] >= thr


def _point_cells(points, cell: float):
    """Host: the cells of edge ``cell`` holding ``points``, all occupied."""
    cells = np.unique(np.floor(points / cell).astype(np.int64), axis=0)
    return cells, np.ones(cells.shape[0], bool)


def _blur(g):
    """Separable ``[1/4, 1/2, 1/4]`` blur (one cell of tolerance for surfaces voxelised in two
    frames)."""
    for axis in range(3):
        a = np.moveaxis(g, axis, 0)
        b = 0.5 * a
        b[1:] += 0.25 * a[:-1]
        b[:-1] += 0.25 * a[1:]
        g = np.moveaxis(b, 0, axis)
    return g


def _target_grids(cells, occupied, known: bool):
    """Host: map 1's signed occupancy ``s1`` (+1 occupied, -1 free, 0 unknown) and known
    indicator ``k1`` (None for points: all known) on the cells' box grown by two cells, both
    blurred (``_blur``), and the box's lower cell index."""
    lo = cells.min(0) - 2
    shape = tuple(int(v) for v in cells.max(0) - lo + 3)
    i = cells - lo
    s1 = np.zeros(shape, np.float32)
    s1[i[:, 0], i[:, 1], i[:, 2]] = np.where(occupied, 1.0, -1.0)
    if not known:
        return _blur(s1), None, lo
    k1 = np.zeros(shape, np.float32)
    k1[i[:, 0], i[:, 1], i[:, 2]] = 1.0
    return _blur(s1), _blur(k1), lo


def _max_filter(x, radius: int):
    """Separable max over a ``(2 radius + 1)^3`` window."""
    for axis in range(3):
        win = [1, 1, 1]
        win[axis] = 2 * radius + 1
        x = jax.lax.reduce_window(x, -jnp.inf, jax.lax.max, tuple(win), (1, 1, 1), "SAME")
    return x


@partial(jax.jit, static_argnames=("per_yaw", "radius"))
def _search(s1, k1, points, signed, weights, rotations, cell, pseudo, source_shape, *, per_yaw, radius):
    """Per rotation ``(r, 3, 3)``: ``(scores (per_yaw,), flat shift indices (per_yaw,))`` of the
    highest local maxima over the padded grid (``s1``'s shape) of ``N(t) / (D(t) + pseudo)``,
    ``N`` the correlation of map 2's weighted signed cells (``points (n, 3)`` [m] about their
    centre, rows of weight 0 are padding) with ``s1``, ``D`` of their weights with ``k1``
    (``None``: ``D`` = the total weight). ``source_shape (3,)`` int32: map 2's box in cells."""
    shape = s1.shape
    S1 = jnp.fft.rfftn(s1)
    K1 = None if k1 is None else jnp.fft.rfftn(k1)
    half = jnp.stack([source_shape[0] // 2, source_shape[1] // 2, 0]).astype(jnp.int32)
    live = weights > 0
    zmin = jnp.min(jnp.where(live, points[:, 2], jnp.inf))
    total = jnp.sum(weights)

    def one(R):
        q = points @ R.T
        q = q.at[:, 2].add(-zmin)  # z: the rotations keep it (yaw only); from the lowest point
        i = jnp.floor(q / cell).astype(jnp.int32) + half
        i = jnp.clip(i, 0, source_shape - 1)
        at = (i[:, 0], i[:, 1], i[:, 2])
        corr = lambda g, F: jnp.fft.irfftn(jnp.conj(jnp.fft.rfftn(g)) * F, s=shape)  # noqa: E731
        num = corr(jnp.zeros(shape, jnp.float32).at[at].add(signed * weights), S1)
        den = total if K1 is None else corr(jnp.zeros(shape, jnp.float32).at[at].add(weights), K1)
        score = num / (jnp.maximum(den, 0.0) + pseudo)
        peak = (score >= _max_filter(score, radius)) & (num > 0)
        return jax.lax.top_k(jnp.where(peak, score, -jnp.inf).reshape(-1), per_yaw)

    return jax.lax.map(one, rotations)


def _turn(a):
    """``|a|`` wrapped to [0, pi] [rad]."""
    return abs((a + math.pi) % (2 * math.pi) - math.pi)


def _yaw(a: float) -> np.ndarray:
    R = np.eye(3)
    R[:2, :2] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
    return R


def correlation_search(target, source, T_1_2_init, *, cell: float | None = None,
                       yaw_step_rad: float | None = None, num_hypotheses: int = 12,
                       per_yaw: int = 4, free_weight: float = 1.0, max_cells: int = 1 << 23,
                       max_free_points: int = 200_000, separation: float | None = None,
                       seed: int = 0) -> CorrelationResult:
    """Poses of ``source`` (map 2) in ``target``'s frame (map 1) that best explain map 1's
    occupancy: a yaw grid about +z (turning ``T_1_2_init``'s rotation, so its roll and pitch
    are kept) x every translation by FFT correlation (module docstring).

    ``target``: an ``OccupancyMap`` (its free space takes part) or occupied points
    ``(n1, 3)`` [m]; ``source``: an ``OccupancyMap`` (occupied and free space) or occupied
    points ``(n2, 3)`` [m] in map 2's frame. ``T_1_2_init (4, 4)``: only its rotation is used.
    ``cell`` [m] (default ``max(0.2, 2 res)``, ``res`` from a map, else 0.2 m; with a map
    rounded to ``res * 2^k``), ``yaw_step_rad`` (default: one cell of arc at map 2's RMS
    radius, 1-6 degrees), ``per_yaw`` local maxima kept per yaw, ``free_weight`` map 2's free
    cells' total weight relative to its occupied cells' (>= 0; at most ``max_free_points``
    of them, drawn with ``seed``). Returns the ``num_hypotheses`` best poses, each at least
    ``separation`` [m] (default 4 cells) from the better ones in ``yaw difference x map 2's RMS
    radius + translation difference``.
    """
    T0 = se3.check_rigid(T_1_2_init, "T_1_2_init").astype(np.float64)
    if int(num_hypotheses) < 1 or int(per_yaw) < 1:
        raise ValueError(f"num_hypotheses and per_yaw must be >= 1, got {num_hypotheses!r}, {per_yaw!r}")
    if not (np.isfinite(free_weight) and free_weight >= 0):
        raise ValueError(f"free_weight must be a finite number >= 0, got {free_weight!r}")
    target, source = (m if isinstance(m, OccupancyMap) else _points(m, name)
                      for name, m in (("target", target), ("source", source)))
    maps = [m for m in (target, source) if isinstance(m, OccupancyMap)]
    if len(maps) == 2 and not math.isclose(maps[0].resolution, maps[1].resolution, rel_tol=1e-9):
        raise ValueError(f"resolutions differ: target {maps[0].resolution:g} m, source {maps[1].resolution:g} m")
    res = maps[0].resolution if maps else None
    cell = (max(0.2, 2.0 * res) if res else 0.2) if cell is None else float(cell)
    if not (np.isfinite(cell) and cell > 0):
        raise ValueError(f"cell must be a positive length [m], got {cell!r}")
    rng = np.random.default_rng(seed)
    while True:
        if res is not None:
            k = max(int(round(math.log2(cell / res))), 0)
            cell = res * 2.0 ** k
        if isinstance(target, OccupancyMap):
            cells1, occ1 = _map_cells(target, k)
        else:
            cells1, occ1 = _point_cells(target, cell)
        src, signed, weights = _source_samples(source, cell, float(free_weight), int(max_free_points), rng)
        if not occ1.any() or not (signed > 0).any():
            raise ValueError("correlation_search: " + ("target" if not occ1.any() else "source")
                             + " has no occupied cells")
        centre = src[signed > 0].mean(0)
        q = (src - centre) @ T0[:3, :3].T  # the guess's roll and pitch; yaw turns about +z
        r_xy = float(np.sqrt((q[:, :2] ** 2).sum(1)).max())
        h = int(math.ceil(r_xy / cell)) + 1
        source_shape = (2 * h + 1, 2 * h + 1, int(math.ceil((q[:, 2].max() - q[:, 2].min()) / cell)) + 2)
        s1, k1, lo1 = _target_grids(cells1, occ1, isinstance(target, OccupancyMap))
        shape = tuple(_grid_len(a + b - 1) for a, b in zip(s1.shape, source_shape))
        if math.prod(shape) <= max_cells:
            break
        cell *= 2.0
    occ = signed > 0
    r_rms = float(np.sqrt((q[occ, :2] ** 2).sum(1).mean()))
    step = (min(max(cell / max(r_rms, 1e-9), math.radians(1)), math.radians(6)) if yaw_step_rad is None
            else float(yaw_step_rad))
    if not (np.isfinite(step) and 0 < step <= 2 * math.pi):
        raise ValueError(f"yaw_step_rad must lie in (0, 2 pi], got {yaw_step_rad!r}")
    num_yaws = -(-max(int(round(2 * math.pi / step)), 1) // 8) * 8  # a multiple of 8 (fewer compilations)
    yaws = np.arange(num_yaws) * (2 * math.pi / num_yaws)
    rotations = np.stack([_yaw(a) for a in yaws])  # about +z, applied after the guess's rotation
    cap = bucket_capacity(q.shape[0])
    pad = lambda a: np.concatenate([a, np.zeros((cap - a.shape[0],) + a.shape[1:], a.dtype)])  # noqa: E731
    def grid(g):  # the target grid zero-padded to the search's shape
        out = np.zeros(shape, np.float32)
        out[: g.shape[0], : g.shape[1], : g.shape[2]] = g
        return out

    sc, idx = _search(grid(s1), None if k1 is None else grid(k1), pad(q.astype(np.float32)),
                      pad(signed), pad(weights), rotations.astype(np.float32), np.float32(cell),
                      np.float32(0.1 * weights.sum()), np.asarray(source_shape, np.int32),
                      per_yaw=int(per_yaw), radius=2)
    sc, idx = np.asarray(sc, np.float64), np.asarray(idx, np.int64)
    # shift t (cells, negative ones wrapped to the top) -> map 1 position of source cell 0
    t = np.stack(np.unravel_index(idx, shape), -1)
    t = np.where(t > np.asarray(shape) - np.asarray(source_shape), t - np.asarray(shape), t)
    cand = sorted(((sc[j, p], j, t[j, p]) for j in range(num_yaws) for p in range(sc.shape[1])
                   if np.isfinite(sc[j, p])), key=lambda c: -c[0])
    sep = 4.0 * cell if separation is None else float(separation)
    chosen = _separated(cand, yaws, r_rms, cell, sep, int(num_hypotheses))
    R = np.asarray([rotations[c[1]] @ T0[:3, :3] for c in chosen]).reshape(-1, 3, 3)
    t_cells = np.asarray([np.asarray([h, h, 0], np.float64) + c[2] + lo1 for c in chosen]).reshape(-1, 3)
    Ts = _poses(R, t_cells, centre, cell, float(q[:, 2].min()))
    return CorrelationResult(Ts, np.asarray([c[0] for c in chosen]), yaws[[c[1] for c in chosen]], float(cell))


def _separated(candidates, yaws, r_rms: float, cell: float, separation: float, num: int):
    """Greedy suppression in pose space: the best ``num`` of ``candidates`` ``(score, yaw index
    j, shift t (3,) cells)``, sorted best first, each at least ``separation`` [m] (yaw difference
    x map 2's RMS radius ``r_rms`` + translation difference) from the better ones; a pose
    closer than that to a chosen one adds nothing for ICP."""
    chosen = []
    for score, j, tj in candidates:
        if any(_turn(yaws[j] - yaws[jj]) * r_rms + np.linalg.norm((tj - tt) * cell) < separation
               for _, jj, tt in chosen):
            continue
        chosen.append((score, j, tj))
        if len(chosen) == num:
            break
    return chosen


def _poses(R, t_cells, centre, cell: float, zmin: float) -> np.ndarray:
    """``T_1_2 (k, 4, 4)`` of the chosen poses: rotations ``R (k, 3, 3)`` and, per pose, the
    map-1 cell ``t_cells (k, 3)`` that map 2's source cell 0 lands on. A source point ``p``
    goes to ``q = R (p - centre)``, ``q' = q - (0, 0, zmin)`` in source cell ``floor(q' / cell)``
    plus the offset already folded into ``t_cells``."""
    Ts = np.tile(np.eye(4), (len(R), 1, 1))
    for n in range(len(R)):
        Ts[n, :3, :3] = R[n]
        Ts[n, :3, 3] = -R[n] @ centre + t_cells[n] * cell - np.asarray([0.0, 0.0, zmin])
    return Ts


def _points(p, name):
    a = np.asarray(p, np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] == 0:
        raise ValueError(f"{name}: expected occupied points of shape (n, 3), n > 0, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: points must be finite")
    return a


def _source_samples(source, cell: float, free_weight: float, max_free: int, rng):
    """Map 2's cells of edge ``cell / 2`` as ``(centres (n, 3) [m], signed (n,) +1 occupied /
    -1 free, weights (n,))``: occupied cells weigh 1 in total, free ones ``free_weight``."""
    half = cell / 2
    if isinstance(source, OccupancyMap):
        k = max(int(round(math.log2(half / source.resolution))), 0)
        cells, occ = _map_cells(source, k)
        size = source.resolution * 2.0 ** k
        occ_c, free_c = cells[occ], cells[~occ]
        if free_c.shape[0] > max_free:
            free_c = free_c[rng.choice(free_c.shape[0], max_free, replace=False)]
        if free_weight == 0:
            free_c = free_c[:0]
    else:  # points, validated by the caller
        occ_c = np.unique(np.floor(source / half).astype(np.int64), axis=0)
        free_c = np.zeros((0, 3), np.int64)
        size = half
    n_o, n_f = occ_c.shape[0], free_c.shape[0]
    pts = (np.concatenate([occ_c, free_c]) + 0.5) * size
    signed = np.concatenate([np.ones(n_o, np.float32), -np.ones(n_f, np.float32)])
    weights = np.concatenate([np.full(n_o, 1.0 / max(n_o, 1)), np.full(n_f, free_weight / max(n_f, 1))])
    return pts, signed, weights.astype(np.float32)
