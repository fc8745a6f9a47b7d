"""Dense (map-to-map) alignment and gradient-based transform tuning.

ICP (Alg. 3) aligns the *occupied* voxel centres of two maps. Here the whole map takes part:
map 1 is read by trilinear ``sample`` (eqs. 3.6-3.13) at the known voxel centres of map 2 moved
by ``T_1_2``, and the agreement of the two occupancies is a differentiable function of the six
pose parameters, so the transform can be refined by a quasi-Newton solver or tuned by gradient
through any downstream loss.

**Score.** Each map holds a *signed occupancy* ``s = 2 p - 1 = tanh(l / 2)`` in known voxels
(+1 occupied, -1 free) and ``0`` in unknown space. ``s_1`` is interpolated at ``y_j = T_1_2 x_j``
over the 8 voxel centres around ``y_j`` with unknown neighbours counted as ``0`` -- i.e.
``s_1(y) = 2 A(y) - C(y)`` with ``A = sample(m1, y, method="thesis")`` (unknown neighbours weigh
as p = 0) and ``C`` the same sample of the all-occupied copy of map 1 (the known coverage of
the 8 weights; ``_signed_field`` computes both from one leaf lookup per corner). Unlike the
renormalised ``"trilinear"`` mode, whose set of known neighbours jumps, this field is continuous everywhere and piecewise smooth, so gradients are well
behaved; unknown space in either map is neutral. The loss is a mean agreement over the
commonly known space::

    L(T_1_2) = - sum_j w_j s_2(x_j) s_1(y_j) / D,    D = sum_j w_j C(y_j) + 0.1 sum_j w_j

over sample points ``x_j`` of map 2 (its known voxels, or a seeded subset, each drawn uniformly
inside its voxel so that the kinks of trilinear interpolation do not line up), with the
occupied and free classes weighted to ``1 : free_weight`` in total (free space outnumbers
surfaces by an order of magnitude). Agreement (occupied on occupied, free on free) lowers it;
an occupied voxel moved into the other map's free space raises it. Dividing by the common
coverage matters: normalised by ``sum w`` alone, the loss rewards *more overlap* and slides
map 2 along corridors and walls into map 1's known space (we measured 3.5 m drifts on the
test room); the pseudo-weight ``0.1`` keeps a sliver of overlap from scoring as perfect.
``coverage_norm = a`` (per level, default 1) blends in the plain mean,
``D = a (sum w C + 0.1 sum w) + (1 - a) sum w``: the ratio also rewards moving *disagreeing*
voxels (the staircase of a surface voxelised in another frame) into unknown space, the plain
mean rewards overlap. On our test room (4096 points) a plain-mean finest level ended 0.12 m
from the truth at 0.2 m resolution (ratio 0.15) but 0.43 m at 0.4 m (ratio 0.16), so the
default stays the ratio on every level.

**Symmetric.** Unknown space counts 0 and free space -1, so the field of a surface seen from
one side (free in front, unknown behind: every floor and wall of a robot's map) is one-sided,
and moving map 2's copy of it towards map 1's unknown side lowers the one-way loss. The bias
is a fraction of a voxel and does not cancel where surfaces are seen from one side only
(floors): the example room aligned with itself drifts 0.27 voxel down; the simulated lab /
office (0.05 m, ``.bt``) solved from the truth ended 0.020 / 0.033 m low and 0.006 / 0.008 rad
off, and ranked a pose one voxel off above the truth. ``prepare_alignment(symmetric=True)``
(the default) also samples map 2 at map 1's points under ``T_1_2^-1`` at the finest level
(``AlignProblem.reverse``) and averages the two losses there, whose biases are opposite: lab /
office from the truth within 0.009 m and 0.005 rad, the example room exactly at the truth. The
coarser levels, which only bring the pose into the finest level's basin, stay one-way: symmetric
at every level, the 0.285 rad row of the 0.2 m grid (``bench_dense.py``) ended in a wrong
minimum (17 of 18 rows right, 18 with the finest level only). The status checks stay one-way
(map 2 in map 1).

**Coarse to fine.** Trilinear interpolation only "sees" one voxel around each point, so the
basin of the finest level is about one voxel. ``prepare_alignment`` therefore builds, for each
level ``k`` of ``levels`` (default: coarsest cell <= 0.8 m, e.g. ``(3, 2, 1, 0)`` at 0.1 m), copies of both maps coarsened by ``2^k``
(each coarse cell takes the maximum log-odds of its known children, OctoMap's inner-node rule)
and *relabelled as depth-16 maps of resolution* ``res * 2^k``, so ``sample`` interpolates at
the coarse scale; ``align_dense`` solves from coarse to fine. A coarse level's minimum is biased
by up to a cell (each map is coarsened on its own grid, and max-coarsening thickens surfaces),
so from a start already in the finest basin the coarse levels can carry the pose out of it:
on a simulated 100 x 60 m campus (lidar, 0.2 m, 1.1M leaves each) they moved ICP's result
(0.09 m off) 0.53 m away into a finest-level minimum with a *higher* loss than the start's.
A last guard step therefore compares the finest loss at the end of the path with the start's
and, if the end is worse, solves the finest level again from the start (``AlignResult.restarted``;
campus: loss -0.166 -> -0.276). Starts known to lie within a cell of the answer should also
skip the coarser levels (``start_level``): the path can end lower than the start and still in
a wrong minimum (the simulated lab at 0.1 m from ICP's result: 0.33 m / 0.07 rad off, loss
-0.124 against -0.141 at the truth; from the level of ICP's last correspondence distance, 0.2
m, 0.023 m off).

**Solver.** The unknown is a 6-vector ``z`` = a right increment on se(3) about the centroid
``c`` of map 2's sample points, ``T(z) = T_start C exp([z_t, z_r / rho]) C^-1`` with
``C = [I | c]`` and ``rho`` the RMS radius of the points, so translation (m) and rotation
(rad x rho, the arc length in m) are commensurate. ``z`` is minimised with L-BFGS
(``_solver.minimize``: one ``while_loop`` that evaluates the loss and its gradient once per
step, so they are compiled once) per level, the levels in one ``lax.scan`` over stacked,
equally shaped level data, all under ``jit``; ``vmap`` runs many initial guesses (or many
stacked problems) at once. A level stops on a small gradient, on ``patience`` steps shorter
than ``xtol`` (scaled to the level's cell) or when no step along the gradient lowers the loss
(a minimum at a kink of the piecewise-trilinear loss).

**Status** (``AlignResult.status``): 0 converged; 1 the finest level hit ``maxiter``; 2 poor
agreement -- fewer than ``min_agreement`` of map 2's occupied sample points that land in
map 1's known space land on map 1's surfaces, i.e. next to an occupied voxel (one of the 8
they interpolate from; a wrong local minimum, e.g. from a hopeless start); 3 too little
overlap (fewer than ``min_overlap`` of map 2's occupied points land in map 1's known space);
4 non-finite loss. Only status 0 sets ``converged``.
The checks need free-space evidence: they refute a wrong pose by map 2's surfaces landing in
map 1's *free* space. On the ray-cast-like test room of ``tests/test_dense.py`` (free interior)
36 starts up to 0.8 rad / 1.4 m off gave no wrong "converged" (22 wrong minima, agreement
0.66-0.84; the 14 right ones 0.998); on a surfaces-only map (the pipeline tests' room,
interior unknown but for a thin free slab) a 0.6 rad start converged to a 2 m slide along
the room with agreement 0.991 (loss -0.378 vs -0.402 at the truth), which
no status can tell from the truth without a wider search (``best_result`` over a stack of
guesses).

**Tuning API.** ``transformed_occupancy`` is ``transform_map``'s per-voxel value (eq. 5.13)
with a traced transform (``transform_map`` plans its output on the host, so it cannot be
traced in ``T``); ``fused_log_odds`` is the fusion rule of Alg. 8 evaluated at points; both
are differentiable w.r.t. the transform, as is ``problem_loss``. Gradients through ``icp`` come
from the implicit derivative of its fixed point (``icp.py``).

The se(3) exponential used here (``_se3_exp``) is private to this module: ``se3.py`` has no
Lie-algebra helpers.
"""

from __future__ import annotations

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from .. import morton, tree
from ..map import OccupancyMap, bucket_capacity, from_leaves
from ..resample import check_rigid_transform, sample
from . import _solver
from .. import se3

__all__ = [
    "STATUS_CONVERGED",
    "STATUS_MAX_ITERATIONS",
    "STATUS_POOR_AGREEMENT",
    "STATUS_LOW_OVERLAP",
    "STATUS_NOT_FINITE",
    "AlignProblem",
    "AlignResult",
    "coarsen",
    "default_levels",
    "prepare_alignment",
    "stack_problems",
    "problem_loss",
    "alignment_loss",
    "solve_alignment",
    "solve_alignment_batch",
    "align_dense",
    "best_result",
    "transformed_occupancy",
    "fused_log_odds",
    "pose_from_increment",
]

STATUS_CONVERGED = 0
STATUS_MAX_ITERATIONS = 1
STATUS_POOR_AGREEMENT = 2
STATUS_LOW_OVERLAP = 3
STATUS_NOT_FINITE = 4

_D = morton.TREE_DEPTH
_OVERLAP_PRIOR = 0.1  # pseudo-weight added to the commonly known weight (loss denominator)


# ----------------------------------------------------------------------------- se(3)


def _skew(w):
    z = jnp.zeros_like(w[..., 0])
    return jnp.stack([jnp.stack([z, -w[..., 2], w[..., 1]], -1),
                      jnp.stack([w[..., 2], z, -w[..., 0]], -1),
                      jnp.stack([-w[..., 1], w[..., 0], z], -1)], -2)


def _se3_exp(xi):
    """se(3) exponential: ``xi (..., 6)`` = (v [m], omega [rad]) -> ``T (..., 4, 4)``.

    Taylor series below ``theta = 0.1`` rad (exact to float32 there and NaN-free gradients at
    zero), closed form (Rodrigues) above.
    """
    v, w = xi[..., :3], xi[..., 3:]
    t2 = jnp.sum(w * w, axis=-1)
    small = t2 < 1e-2
    t2s = jnp.where(small, jnp.ones_like(t2), t2)
    t = jnp.sqrt(t2s)
    a = jnp.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, jnp.sin(t) / t)
    b = jnp.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, (1.0 - jnp.cos(t)) / t2s)
    c = jnp.where(small, 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0, (t - jnp.sin(t)) / (t2s * t))
    K = _skew(w)
    K2 = K @ K
    eye = jnp.eye(3, dtype=xi.dtype)
    R = eye + a[..., None, None] * K + b[..., None, None] * K2
    V = eye + b[..., None, None] * K + c[..., None, None] * K2
    return se3.from_rotation_translation(R, (V @ v[..., None])[..., 0])


def pose_from_increment(T_start, z, center, radius):
    """``T_start (4, 4) @ C exp([z[:3], z[3:] / radius]) C^-1`` with ``C = [I | center]``.

    ``z (6,)``: translation [m] and rotation scaled to arc length at ``radius`` [m] (so both
    halves are in metres), applied in the frame of ``T_start``'s source about ``center (3,)``.
    """
    xi = jnp.concatenate([z[:3], z[3:] / radius])
    E = _se3_exp(xi)
    R, t = E[:3, :3], E[:3, 3]
    t = t + center - R @ center
    return T_start @ se3.from_rotation_translation(R, t)


# ----------------------------------------------------------------------------- pytrees


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
      commonly known weight (1: ``sum w C + 0.1 sum w``; 0: ``sum w``, the plain mean). See
      ``prepare_alignment``.
    - ``levels``: static tuple of the coarsening exponents ``k``.
    - ``reverse``: the finest level's problem with the maps' roles swapped (map 2 sampled at
      map 1's points; one level), or ``None``; with it the finest level's loss is symmetric
      (module docstring: one direction alone is biased towards unknown space); the coarser
      levels and the status checks stay map 2 -> 1.
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

    @property
    def num_levels(self) -> int:
        return len(self.levels)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class AlignResult:
    """Result of ``align_dense`` / ``solve_alignment`` (arrays; batched under ``vmap``).

    - ``T_1_2``: ``(4, 4)`` float32, maps points of map 2's frame into map 1's.
    - ``loss``: ``()`` float32, ``problem_loss`` at the finest level (in [-1, 1], lower is better).
    - ``loss_history``: ``(L, maxiter + 1)`` float32, the loss per level (coarse to fine) at
      the start and after every iteration; NaN after a level stopped.
    - ``iterations``: ``(L,)`` int32 solver iterations per level; ``num_iterations`` ``()`` total.
    - ``overlap``: ``()`` float32, share of map 2's occupied sample weight landing in map 1's
      known space (finest level).
    - ``agreement``: ``()`` float32, of that, the share landing next to map 1's occupied space
      (one of the 8 voxels the point interpolates from is occupied).
    - ``grad_norm``: ``()`` float32, gradient norm at the end of the finest level.
    - ``status``: ``()`` int32 (module docstring); ``converged``: ``()`` bool, ``status == 0``.
    - ``restarted``: ``()`` bool, the coarse-to-fine path ended with a higher finest-level loss
      than the initial guess had, so the finest level was solved again from the guess (its
      ``loss_history`` / ``iterations`` row is that solve's; ``num_iterations`` counts both).
    """

    T_1_2: jax.Array
    loss: jax.Array
    loss_history: jax.Array
    iterations: jax.Array
    num_iterations: jax.Array
    overlap: jax.Array
    agreement: jax.Array
    grad_norm: jax.Array
    status: jax.Array
    converged: jax.Array
    restarted: jax.Array


# ----------------------------------------------------------------------------- host planning


def coarsen(m: OccupancyMap, k: int, capacity: int | None = None, *,
            resolution: float | None = None) -> OccupancyMap:
    """Map ``m`` coarsened by ``2^k`` per axis and relabelled as a map of resolution
    ``res * 2^k``: a leaf finer than ``2^k`` voxels goes to the coarse cell containing it
    (cells take the maximum log-odds of their known children, OctoMap's inner-node rule); a
    coarser leaf keeps its extent (depth ``d -> d + k``). Centres keep their metric positions
    (cell ``i`` of the coarse map covers exactly ``2^k`` voxels ``i * 2^k ...``). With
    ``resolution`` given, the result is labelled with it instead (``AlignProblem`` stores
    every level at the finest resolution and scales the sample points). Host function.
    """
    k = int(k)
    if not 0 <= k < _D:
        raise ValueError(f"k (coarsening level) must lie in 0..15, got {k}")
    if k == 0:
        return m if capacity is None else m.with_capacity(capacity)
    lv = m.leaves()
    if lv.depths.size and lv.depths.min() < 1:
        raise ValueError("coarsen: a depth-0 (root) leaf cannot be relabelled; expand it first")
    keys = lv.keys.astype(np.int64) - morton.KEY_OFFSET
    new_keys = (keys >> k) + morton.KEY_OFFSET  # floor division: exact for coarse leaves
    new_depth = np.minimum(lv.depths + k, _D)
    codes = morton.keys_to_codes(new_keys.astype(np.uint64))
    span = np.uint64(1) << (np.uint64(3) * (_D - new_depth).astype(np.uint64))
    codes = codes & ~(span - np.uint64(1))
    order = np.lexsort((new_depth, codes))
    codes, new_depth, lo = codes[order], new_depth[order], lv.log_odds[order]
    first = np.ones(codes.shape, bool)
    first[1:] = codes[1:] != codes[:-1]
    seg = np.cumsum(first) - 1
    n = int(first.sum())
    val = np.full(n, -np.inf, np.float32)
    np.maximum.at(val, seg, lo)
    res = m.resolution * 2.0 ** k if resolution is None else resolution
    return from_leaves(codes[first], new_depth[first], val, res, m.params, capacity=capacity)


def _cell_samples(m: OccupancyMap, mask: np.ndarray, budget: int, rng,
                  jitter: bool) -> tuple[np.ndarray, np.ndarray]:
    """Points ``(n, 3)`` [m] and log-odds of the depth-16 cells of the leaves selected by
    ``mask``: all of them if they fit in ``budget``, else ``budget`` cells drawn uniformly
    (by volume) without replacement. With ``jitter`` each point is drawn uniformly inside its
    cell instead of at the centre (see ``prepare_alignment``)."""
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


def _level(m1: OccupancyMap, m2: OccupancyMap, k: int, max_points: int, free_weight: float, rng,
           jitter: bool):
    """Host: (coarse map 1 labelled at the finest resolution, points, signed, weights, occupied)."""
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
    return c1, pts, np.tanh(lo / 2.0), w, np.arange(pts.shape[0]) < n_occ


def default_levels(resolution: float, coarsest: float = 0.8) -> tuple[int, ...]:
    """Coarse-to-fine exponents ``(K, ..., 1, 0)`` whose coarsest cell ``res * 2^K`` is at most
    ``coarsest`` metres (0.8 m: coarser cells let a room flip onto its own walls)."""
    K = int(np.floor(np.log2(max(coarsest / float(resolution), 1.0)) + 1e-9))
    return tuple(range(K, -1, -1))


def prepare_alignment(m1: OccupancyMap, m2: OccupancyMap, *, levels=None,
                      max_points: int = 8192, free_weight: float = 0.5, seed: int = 0,
                      jitter: bool = True, map_capacity: int | None = None,
                      point_capacity: int | None = None,
                      coverage_norm=1.0, symmetric: bool = True) -> AlignProblem:
    """Host planning for ``solve_alignment`` / ``problem_loss``.

    Args:
      m1, m2: the maps (same resolution); map 1 is sampled, map 2 provides the points.
      levels: coarsening exponents, coarse to fine (``k`` -> cells of ``res * 2^k``); default
        ``default_levels(res)`` (coarsest cell <= 0.8 m); ``(0,)`` for the finest level only.
      max_points: sample points of map 2 per level (up to half occupied cells, the rest free
        cells drawn by volume with ``seed``); all known cells when they fit. The finest
        level's optimum is a Monte-Carlo estimate: on our 0.2 m test room (16k cells in map 2)
        4096 points put it 0.10-0.16 m from the truth depending on the seed, 8192 0.11 m.
      free_weight: total weight of the free points relative to the occupied ones.
      jitter: draw each point uniformly inside its cell (seeded) rather than at the centre.
        Trilinear interpolation has kinks on the planes of voxel centres; centres of two maps
        that share an axis (e.g. both z-up) all sit on those planes at once, so the loss would
        have a V-shaped kink exactly at the optimum and its gradient would not be a descent
        direction. Jittered points spread the kinks: the loss becomes a Monte-Carlo estimate of
        the voxel-volume overlap integral, which is C1 in the pose.
      coverage_norm: per level (or one number for all) in [0, 1]: 1 divides the agreement
        by the commonly known weight (without it the loss rewards overlap and slides map 2
        along walls into map 1's known space), 0 by the total sample weight (the plain mean;
        unknown space counts as neutral). See the module docstring for measurements.
      map_capacity, point_capacity: static capacities of the coarsened map 1 and of the points
        (default ``bucket_capacity`` of the largest level): fix them to share one compilation
        across pairs, or to stack problems (the reverse problem of a symmetric one gets them too).
      symmetric: also prepare the finest level's reverse problem (map 2 sampled at map 1's
        points under ``T_1_2^-1``) and average the two losses there (``AlignProblem.reverse``;
        module docstring): no bias towards unknown space, twice the finest level's work.

    Raises ``ValueError`` (naming the argument) on mismatched resolutions, empty maps or bad
    options.
    """
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
    rng = np.random.default_rng(seed)
    built = [_level(m1, m2, k, int(max_points), float(free_weight), rng, bool(jitter))
             for k in levels]
    n_map = max(b[0].num_leaves for b in built)
    n_pts = max(b[1].shape[0] for b in built)
    mcap = bucket_capacity(n_map) if map_capacity is None else int(map_capacity)
    pcap = bucket_capacity(n_pts) if point_capacity is None else int(point_capacity)
    if mcap < n_map:
        raise ValueError(f"map_capacity {mcap} is smaller than the {n_map} leaves of a level")
    if pcap < n_pts:
        raise ValueError(f"point_capacity {pcap} is smaller than the {n_pts} points of a level")

    def pad(a, fill=0.0, dtype=np.float32):
        out = np.full((pcap,) + a.shape[1:], fill, dtype)
        out[:a.shape[0]] = a
        return out

    maps = [b[0].with_capacity(mcap) for b in built]
    map1 = jax.tree_util.tree_map(lambda *a: jnp.stack([jnp.asarray(x) for x in a]), *maps)
    fine_pts = built[-1][1]
    center = fine_pts.mean(axis=0) if fine_pts.size else np.zeros(3)
    radius = np.sqrt(np.mean(np.sum((fine_pts - center) ** 2, axis=1))) if fine_pts.size else 1.0
    radius = max(float(radius), 10.0 * m2.resolution)
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
    return AlignProblem(
        map1=map1,
        scale=jnp.asarray([2.0 ** -k for k in levels], jnp.float32),
        points2=jnp.asarray(np.stack([pad(b[1]) for b in built])),
        signed2=jnp.asarray(np.stack([pad(b[2]) for b in built])),
        weight2=jnp.asarray(np.stack([pad(b[3]) for b in built])),
        occupied2=jnp.asarray(np.stack([pad(b[4], False, bool) for b in built])),
        center2=jnp.asarray(center, jnp.float32),
        radius=jnp.asarray(radius, jnp.float32),
        coverage_norm=jnp.asarray(cn, jnp.float32),
        levels=levels,
        reverse=reverse,
    )


def stack_problems(problems) -> AlignProblem:
    """Stack problems of several pairs (same ``levels``, resolution and capacities: pass
    ``map_capacity`` / ``point_capacity`` to ``prepare_alignment``) along a new leading axis,
    for ``jax.vmap`` of ``solve_alignment``'s core (``solve_alignment_batch``)."""
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
    return jax.tree_util.tree_map(lambda *a: jnp.stack(a), *problems)


# ----------------------------------------------------------------------------- loss


_CORNERS = np.array([[c & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], np.int32)


def _corners(m1: OccupancyMap, y):
    """The 8 voxel centres around points ``y (P, 3)`` [m] of map 1's frame: ``(trilinear
    weights (P, 8), known (P, 8) bool, log-odds (P, 8))``. The gradient flows through the
    weights (the lookups are piecewise constant)."""
    u = y / jnp.float32(m1.resolution) - jnp.float32(0.5)  # centres at integer u
    finite = jnp.all(jnp.isfinite(u), axis=-1)
    base = jax.lax.stop_gradient(jnp.floor(jnp.where(finite[:, None], u, 0.0)))
    f = jnp.where(finite[:, None], u - base, 0.0)
    base = jnp.clip(base, -morton.KEY_OFFSET - 2, morton.KEY_OFFSET + 1).astype(jnp.int32)
    keys = base[:, None, :] + morton.KEY_OFFSET + jnp.asarray(_CORNERS)  # (P, 8, 3)
    in_range = jnp.all((keys >= 0) & (keys < 2 * morton.KEY_OFFSET), axis=-1)
    words = morton.keys_to_words(jnp.clip(keys, 0, 2 * morton.KEY_OFFSET - 1))
    row, known = tree.lookup_words(m1, words)
    known = known & in_range & finite[:, None]
    c = jnp.asarray(_CORNERS, jnp.float32)  # (8, 3)
    w = jnp.prod(jnp.where(c == 1, f[:, None, :], 1.0 - f[:, None, :]), axis=-1)  # (P, 8)
    return w, known, m1.log_odds[row]


def _signed_field(corners):
    """``(s_1 (P,), coverage (P,))`` from ``_corners(m1, y)`` at points ``y`` (module
    docstring): ``s_1 = sum_c w_c k_c tanh(l_c / 2)`` and ``coverage = sum_c w_c k_c`` over the
    8 voxel centres ``c`` around each point, with trilinear weights ``w_c`` and ``k_c`` = the
    centre is known. The same values as ``2 sample(.., "thesis") - coverage`` but with one
    leaf lookup per corner and no mode switch (cheaper to compile and to run)."""
    w, known, lo = corners
    s = jnp.where(known, jnp.tanh(0.5 * lo), 0.0)
    return jnp.sum(w * s, axis=-1), jnp.sum(w * known.astype(w.dtype), axis=-1)


def _at(problem: AlignProblem, i):
    """Level ``i`` (int or traced) of an unbatched problem: (map1, scale, points, signed, w, occ,
    coverage_norm)."""
    take = lambda a: a[i]  # noqa: E731
    return (jax.tree_util.tree_map(take, problem.map1), problem.scale[i], problem.points2[i],
            problem.signed2[i], problem.weight2[i], problem.occupied2[i], problem.coverage_norm[i])


def _level_terms(lv, T_1_2):
    """``(loss, coverage (P,), _corners(...))`` of a level under ``T_1_2``."""
    map1, scale, pts, signed, w = lv[:5]
    y = se3.transform_points(jnp.asarray(T_1_2, jnp.float32), pts)
    corners = _corners(map1, y * scale)
    s1, cov = _signed_field(corners)
    a = lv[6]
    den = a * (jnp.sum(w * cov) + _OVERLAP_PRIOR * jnp.sum(w)) + (1.0 - a) * jnp.sum(w)
    loss = -jnp.sum(w * signed * s1) / den
    return loss, cov, corners


def _both_at(problem: AlignProblem, i):
    """``(_at(problem, i), the reverse's finest level or None, level i is the finest)``; ``i``
    an int (negative counts from the end) or traced."""
    if problem.reverse is None:
        return _at(problem, i), None, False
    last = problem.num_levels - 1
    finest = i % problem.num_levels == last if isinstance(i, (int, np.integer)) else jnp.asarray(i) == last
    return _at(problem, i), _at(problem.reverse, 0), finest


def _reverse_loss(rev, T_1_2):
    """The reverse direction's loss (map 2 sampled at map 1's points) under ``T_1_2``."""
    return _level_terms(rev, se3.inverse(jnp.asarray(T_1_2, jnp.float32)))[0]


def _symmetrised(loss, rev, finest, T_1_2):
    """The map 2 -> 1 ``loss`` of a level, averaged with the reverse direction's at the finest
    level of a symmetric problem (``_both_at``'s ``rev`` / ``finest``; a ``cond`` when traced)."""
    if rev is None:
        return loss
    both = lambda: 0.5 * (loss + _reverse_loss(rev, T_1_2))  # noqa: E731
    if isinstance(finest, (bool, np.bool_)):
        return both() if finest else loss
    return jax.lax.cond(finest, both, lambda: loss)


def _loss(levels, T_1_2):
    """The loss of ``_both_at``'s triple (``_symmetrised``)."""
    fwd, rev, finest = levels
    return _symmetrised(_level_terms(fwd, T_1_2)[0], rev, finest, T_1_2)


def problem_loss(problem: AlignProblem, T_1_2, level: int = -1):
    """The alignment loss (module docstring) of a prepared problem at ``level`` (index into
    ``problem.levels``, default the finest) under ``T_1_2 (4, 4)``: a float32 scalar in
    [-1, 1]. Pure, jittable, differentiable w.r.t. ``T_1_2`` (and map 2's signed values)."""
    return _loss(_both_at(problem, level), T_1_2)


def alignment_loss(m1: OccupancyMap, m2: OccupancyMap, T_1_2, *, level: int = 0,
                   max_points: int = 8192, free_weight: float = 0.5, seed: int = 0,
                   jitter: bool = True, coverage_norm: float = 1.0, symmetric: bool = True):
    """Differentiable score of how well map 2 agrees with map 1 under ``T_1_2`` (lower is better).

    ``-sum_j w_j s_2(x_j) s_1(T_1_2 x_j)`` over known voxel centres ``x_j`` of map 2 (a seeded
    subset of at most ``max_points``), with ``s = tanh(l / 2)`` the signed occupancy (unknown
    = 0) and ``s_1`` trilinear in map 1, normalised by the commonly known weight (module
    docstring); with ``symmetric`` (default) averaged with the same score of map 1's points in
    map 2 under ``T_1_2^-1``; ``level = k`` compares copies coarsened by ``2^k``.
    ``T_1_2 (4, 4)`` [m] may be traced (``jax.grad`` w.r.t. it works); the maps must be
    concrete (planning runs on the host). For repeated calls prepare once with
    ``prepare_alignment`` and use ``problem_loss``.
    """
    problem = prepare_alignment(m1, m2, levels=(level,), max_points=max_points,
                                free_weight=free_weight, seed=seed, jitter=jitter,
                                coverage_norm=coverage_norm, symmetric=symmetric)
    return problem_loss(problem, T_1_2)


# ----------------------------------------------------------------------------- solve


def _objective(z, levels, T_start, center, radius):
    return _loss(levels, pose_from_increment(T_start, z, center, radius))


def _fine_scores(problem: AlignProblem, T_1_2):
    """``(loss, overlap, agreement)`` at the finest level under ``T_1_2 (4, 4)`` (``AlignResult``
    fields of the same names)."""
    fine, rev, finest = _both_at(problem, problem.num_levels - 1)
    loss, cov, (_, known, lo) = _level_terms(fine, T_1_2)
    loss = _symmetrised(loss, rev, finest, T_1_2)
    w_occ = jnp.where(fine[5], fine[4], 0.0)
    overlap = jnp.sum(w_occ * cov) / jnp.maximum(jnp.sum(w_occ), 1e-30)
    # on map 1's surfaces: one of the 8 voxels the point interpolates from is occupied
    near = jnp.any(known & (lo >= fine[0].params.occupancy_threshold_log_odds), axis=-1)
    agree = jnp.sum(w_occ * cov * near.astype(jnp.float32)) / jnp.maximum(jnp.sum(w_occ * cov), 1e-30)
    return loss, overlap, agree


@jax.jit
def _scores_jit(problem, T_1_2s):
    return jax.vmap(lambda T: _fine_scores(problem, T))(T_1_2s)


@partial(jax.jit, static_argnames="level")
def level_losses(problem: AlignProblem, T_1_2s, level: int = -1):
    """``problem_loss`` at ``level`` (index into ``problem.levels``) for each of ``T_1_2s (k,
    4, 4)``: ``(k,)`` float32, lower is better. A coarse level scores poses a cell or so from
    a minimum close to it (``correlation_search``'s poses are re-ranked this way)."""
    return jax.vmap(lambda T: problem_loss(problem, T, level))(jnp.asarray(T_1_2s, jnp.float32))


def score_alignment(problem: AlignProblem, T_1_2s):
    """Score candidate transforms ``T_1_2s (k, 4, 4)`` (e.g. ``icp_multi``'s candidates) by the
    finest-level alignment loss, without solving: ``(loss, overlap, agreement)``, each ``(k,)``
    float32 (``AlignResult`` fields of the same names; lower loss is better, non-finite
    transforms score ``+inf``). Unlike point inlier counts, the loss sees free space: a
    candidate that puts map 2's surfaces into map 1's free space (e.g. a room turned by 180
    degrees, whose walls still match) scores worse than the truth."""
    T = jnp.asarray(T_1_2s, jnp.float32)
    if T.ndim != 3 or T.shape[-2:] != (4, 4):
        raise ValueError(f"T_1_2s: expected shape (k, 4, 4), got {T.shape}")
    finite = jnp.all(jnp.isfinite(T), axis=(1, 2))
    loss, overlap, agree = _scores_jit(problem, jnp.where(finite[:, None, None], T, jnp.eye(4)))
    return jnp.where(finite, loss, jnp.inf), overlap, agree


def _solve(problem: AlignProblem, T_init, tol, xtol, max_step, min_overlap, min_agreement,
           start_level, maxiter: int):
    """Coarse-to-fine L-BFGS (one compiled level step, scanned over the levels; the levels
    before ``start_level`` pass the pose through), then the guard step (``restarted``)."""

    def solve_level(T, i, active=True):
        # an inactive solve (tol = inf) stops at its first evaluation, also as one member of a
        # vmap batch (a batched ``cond`` would run both branches for every member)
        lvs = _both_at(problem, i)
        cell = problem.map1.resolution / problem.scale[i]  # this level's cell size [m]
        res = _solver.minimize(_objective, jnp.zeros(6, jnp.float32), lvs, T, problem.center2,
                               problem.radius, maxiter=maxiter, tol=jnp.where(active, tol, jnp.inf),
                               xtol=xtol / problem.scale[i], init_step=0.5 * cell)
        # trust region: a level may move the pose by at most max_step (norm of z, metres)
        n = jnp.linalg.norm(res.x)
        z = res.x * jnp.minimum(1.0, max_step / jnp.maximum(n, 1e-12))
        T_new = pose_from_increment(T, z, problem.center2, problem.radius)
        return T_new, (res.history, res.num_iterations, res.converged & (n <= max_step), res.grad_norm)

    def skip_level(T, i):
        nan = jnp.full((maxiter + 1,), jnp.nan, jnp.float32)
        return T, (nan, jnp.int32(0), jnp.bool_(True), jnp.float32(jnp.nan))

    T0 = jnp.asarray(T_init, jnp.float32)
    last = problem.num_levels - 1
    start_loss = _fine_scores(problem, T0)[0]

    def level_step(T, i):
        # steps 0..last: the levels from start_level on; one more step, the guard: the coarse
        # levels' minima are biased (module docstring), and from a start already in the finest
        # basin they can carry the pose out of it, so a path that ends with a higher finest loss
        # than the start's is dropped and the finest level solved again from the start
        guard = i > last
        restart = jax.lax.cond(guard, lambda: (start_level < last) & jnp.isfinite(start_loss)
                               & ~(_fine_scores(problem, T)[0] <= start_loss), lambda: jnp.bool_(False))
        T_out, aux = jax.lax.cond(i < start_level, skip_level, partial(solve_level, active=~guard | restart),
                                  jnp.where(restart, T0, T), jnp.minimum(i, last))
        return jnp.where(guard & ~restart, T, T_out), (*aux, restart)

    T, (hist, iters, conv, gnorm, restarts) = jax.lax.scan(level_step, T0, jnp.arange(last + 2))
    restart = restarts[-1]
    # the level rows; a restart's solve replaces the finest level's
    pick = lambda a: jnp.where(restart, a[-1], a[last])  # noqa: E731
    num_iterations = jnp.sum(iters)
    hist, iters = hist[:-1].at[last].set(pick(hist)), iters[:-1].at[last].set(pick(iters))
    conv, gnorm = conv[:-1].at[last].set(pick(conv)), gnorm[:-1].at[last].set(pick(gnorm))
    loss, overlap, agree = _fine_scores(problem, T)
    finite = jnp.isfinite(loss) & jnp.all(jnp.isfinite(T))
    status = jnp.where(~finite, STATUS_NOT_FINITE,
             jnp.where(overlap < min_overlap, STATUS_LOW_OVERLAP,
             jnp.where(agree < min_agreement, STATUS_POOR_AGREEMENT,
             jnp.where(~conv[-1], STATUS_MAX_ITERATIONS, STATUS_CONVERGED)))).astype(jnp.int32)
    return AlignResult(T_1_2=T, loss=loss, loss_history=hist, iterations=iters,
                       num_iterations=num_iterations, overlap=overlap, agreement=agree,
                       grad_norm=gnorm[-1], status=status, converged=status == STATUS_CONVERGED,
                       restarted=restart)


@partial(jax.jit, static_argnames=("maxiter",))
def _solve_jit(problem, T_init, tol, xtol, max_step, min_overlap, min_agreement, start_level, *, maxiter):
    return _solve(problem, T_init, tol, xtol, max_step, min_overlap, min_agreement, start_level, maxiter)


@partial(jax.jit, static_argnames=("maxiter",))
def _solve_many_jit(problem, T_inits, tol, xtol, max_step, min_overlap, min_agreement, start_level, *,
                    maxiter):
    return jax.vmap(lambda T: _solve(problem, T, tol, xtol, max_step, min_overlap, min_agreement,
                                     start_level, maxiter))(T_inits)


@partial(jax.jit, static_argnames=("maxiter",))
def _solve_pairs_jit(problems, T_inits, tol, xtol, max_step, min_overlap, min_agreement, start_level, *,
                     maxiter):
    return jax.vmap(lambda p, T: _solve(p, T, tol, xtol, max_step, min_overlap, min_agreement,
                                        start_level, maxiter))(problems, T_inits)


def _options(problem, maxiter, tol, xtol, max_step, min_overlap, min_agreement, start_level):
    if int(maxiter) < 1:
        raise ValueError(f"maxiter must be >= 1, got {maxiter}")
    if isinstance(start_level, bool) or not isinstance(start_level, (int, np.integer)) or not (
            0 <= start_level < problem.num_levels):
        raise ValueError(f"start_level must be an int in 0..{problem.num_levels - 1} (an index into the "
                         f"problem's levels {problem.levels}), got {start_level!r}")
    for name, v in dict(tol=tol, max_step=max_step, min_overlap=min_overlap,
                        min_agreement=min_agreement).items():
        if not (np.isfinite(v) and v >= 0):
            raise ValueError(f"{name} must be a non-negative number, got {v!r}")
    xtol = problem.map1.resolution / 100.0 if xtol is None else float(xtol)
    return (jnp.float32(tol), jnp.float32(xtol), jnp.float32(max_step), jnp.float32(min_overlap),
            jnp.float32(min_agreement), jnp.int32(start_level))


def solve_alignment(problem: AlignProblem, T_1_2_init, *, maxiter: int = 30, tol: float = 1e-4,
                    xtol: float | None = None, max_step: float = 3.0,
                    min_overlap: float = 0.15, min_agreement: float = 0.85,
                    start_level: int = 0) -> AlignResult:
    """Jitted coarse-to-fine L-BFGS on a prepared problem from ``T_1_2_init`` ``(4, 4)`` or
    ``(k, 4, 4)`` (then ``vmap``-ed over the ``k`` guesses; every result field gains a leading
    ``k``). ``maxiter`` (per level) is static; ``tol`` (gradient norm of the loss w.r.t. the
    increment, 1/m), ``xtol`` (step length in m at the finest level, default ``res / 100``,
    scaled by ``2^k`` at coarse levels), ``max_step`` (trust region: the norm of one level's
    increment ``z``, metres; a level that wants more is cut back and not counted as
    converged), ``min_overlap`` and ``min_agreement`` (status thresholds, module docstring)
    and ``start_level`` are traced, so changing them does not recompile.
    ``start_level`` (index into ``problem.levels``, default 0): solve from this level on, the
    coarser ones skipped (their ``iterations`` 0, history NaN). For starts already inside a
    finer level's basin: a coarse level's minimum is biased (the maps coarsened by max) and
    flat along some directions, and the solver can wander along it out of the finer basin
    (simulated lab at 0.05 m, a start 0.16 m / 0.002 rad off: 0.59 m off with levels from
    0.8 m, 0.028 m from 0.4 m; ``correlation_search``'s poses are within about a cell). ``min_agreement`` (default 0.85) is a
    heuristic like any fitness threshold: on poses solved from 16 starts (up to 3 rad, 1 m
    off) on the test rooms and on simulated robot maps (lab / office at 0.1 and 0.05 m, loaded
    from .bt files) right poses scored 0.93-1.00 and wrong ones 0.45-0.94, the highest being
    slides along a corridor and the office turned by pi, which no agreement can refute; on
    sparse maps (a 32 x 24 depth camera, few scans) poses solved from the truth scored 0.89.
    (The earlier test, the interpolated occupancy itself above 1/2 at the point, scored right
    poses 0.62-0.97 and reported the truth on those maps at 0.05 m as a failure: a surface one
    voxel thick, sampled in another frame, interpolates to free at many of its points.)
    ``min_overlap`` (default 0.15): a hopeless start can end on a sliver of overlap that
    agrees perfectly (measured: 5-10 % of map 2's surfaces in map 1's known space, agreement
    0.96-0.995, vs 39-41 % for the true pose on our test room); below 15 % the result is
    reported as status 3, not trusted."""
    args = _options(problem, maxiter, tol, xtol, max_step, min_overlap, min_agreement, start_level)
    if isinstance(T_1_2_init, jax.core.Tracer):
        return _solve_jit(problem, T_1_2_init, *args, maxiter=int(maxiter))
    T0 = np.asarray(T_1_2_init, np.float64)
    if T0.ndim == 3:
        for i, T in enumerate(T0):
            check_rigid_transform(T, f"T_1_2_init[{i}]")
        return _solve_many_jit(problem, jnp.asarray(T0, jnp.float32), *args, maxiter=int(maxiter))
    T0 = check_rigid_transform(T0, "T_1_2_init")
    return _solve_jit(problem, jnp.asarray(T0, jnp.float32), *args, maxiter=int(maxiter))


def solve_alignment_batch(problems: AlignProblem, T_1_2_inits, *, maxiter: int = 30,
                          tol: float = 1e-4, xtol: float | None = None, max_step: float = 3.0,
                          min_overlap: float = 0.15, min_agreement: float = 0.85,
                          start_level: int = 0) -> AlignResult:
    """``solve_alignment`` ``vmap``-ed over stacked pairs (``stack_problems``) with one
    initial guess each, ``T_1_2_inits (n, 4, 4)``."""
    args = _options(problems, maxiter, tol, xtol, max_step, min_overlap, min_agreement, start_level)
    T0 = np.asarray(T_1_2_inits, np.float64)
    if T0.ndim != 3 or T0.shape[0] != problems.radius.shape[0]:
        raise ValueError(f"T_1_2_inits: expected shape ({problems.radius.shape[0]}, 4, 4), got {T0.shape}")
    for i, T in enumerate(T0):
        check_rigid_transform(T, f"T_1_2_inits[{i}]")
    return _solve_pairs_jit(problems, jnp.asarray(T0, jnp.float32), *args, maxiter=int(maxiter))


def align_dense(m1: OccupancyMap, m2: OccupancyMap, T_1_2_init, *, levels=None,
                max_points: int = 8192, free_weight: float = 0.5, seed: int = 0,
                maxiter: int = 30, tol: float = 1e-4, xtol: float | None = None,
                max_step: float = 3.0, min_overlap: float = 0.15,
                min_agreement: float = 0.85, start_level: int = 0) -> AlignResult:
    """Refine ``T_1_2`` (maps points of map 2's frame into map 1's) by dense map-to-map
    alignment: ``prepare_alignment`` (host) then ``solve_alignment`` (jitted). See the module
    docstring for the loss, the solver and the status codes; ``T_1_2_init`` may be ``(4, 4)``
    or a ``(k, 4, 4)`` stack of initial guesses (solved in one ``vmap``; pick one with
    ``best_result``). Translations in metres. ``start_level`` (index into ``levels``) skips the
    coarser levels, for guesses already within that level's cell of the answer (e.g. an ICP
    result: ``merge(refine="icp+dense")`` starts at the level of ICP's last correspondence
    distance)."""
    problem = prepare_alignment(m1, m2, levels=levels, max_points=max_points,
                                free_weight=free_weight, seed=seed)
    return solve_alignment(problem, T_1_2_init, maxiter=maxiter, tol=tol, xtol=xtol,
                           max_step=max_step, min_overlap=min_overlap,
                           min_agreement=min_agreement, start_level=start_level)


def best_result(results: AlignResult) -> AlignResult:
    """From a batched ``AlignResult`` (leading ``k``), the one with the lowest final loss,
    preferring candidates whose status is converged or max-iterations over failures."""
    ok = (results.status == STATUS_CONVERGED) | (results.status == STATUS_MAX_ITERATIONS)
    key = jnp.where(ok, results.loss, results.loss + 10.0)
    key = jnp.where(jnp.isfinite(key), key, jnp.inf)
    i = jnp.argmin(key)
    return jax.tree_util.tree_map(lambda a: a[i], results)


# ----------------------------------------------------------------------------- tuning API


def transformed_occupancy(m_src: OccupancyMap, T_dst_src, points_dst, *,
                          method: str = "trilinear", space: str = "probability"):
    """``transform_map``'s value at destination points, with a traceable transform.

    For ``points_dst (..., 3)`` [m] in frame ``dst``, samples ``m_src`` at
    ``T_dst_src^-1 points_dst`` (eq. 5.13) with ``sample``: returns ``(value (...,), known
    (...,))`` as ``sample`` does. Differentiable w.r.t. ``T_dst_src (4, 4)`` and the points
    (``"trilinear"`` / ``"thesis"``), so a downstream loss on a transformed map's occupancy
    can be descended in the transform (``transform_map`` itself plans on the host).
    """
    T_src_dst = se3.inverse(jnp.asarray(T_dst_src, jnp.float32))
    p = se3.transform_points(T_src_dst, jnp.asarray(points_dst, jnp.float32).reshape(-1, 3))
    v, k = sample(m_src, p, method=method, space=space)
    shape = jnp.shape(points_dst)[:-1]
    return v.reshape(shape), k.reshape(shape)


def fused_log_odds(m1: OccupancyMap, m2: OccupancyMap, T_1_2, points_1):
    """Alg. 8's fusion rule at points ``points_1 (..., 3)`` [m] of frame 1: the sum of map 1's
    log-odds and map 2's (moved by ``T_1_2``, trilinear in log-odds) where both know the point,
    the one known value where only one does, clamped to map 1's bounds; ``(log_odds (...,),
    known (...,))``. Differentiable w.r.t. ``T_1_2`` -- e.g. to tune a map pose or a sensor
    extrinsic so the merged occupancy agrees with a reference map."""
    l1, k1 = sample(m1, points_1, space="log_odds")
    l2, k2 = transformed_occupancy(m2, T_1_2, points_1, space="log_odds")
    lo = jnp.where(k1, l1, 0.0) + jnp.where(k2, l2, 0.0)
    lo = jnp.clip(lo, m1.params.clamp_min_log_odds, m1.params.clamp_max_log_odds)
    return lo, k1 | k2
