"""Point-to-point ICP (thesis §3.3.1, §6.3, Alg. 3), jitted, batched and differentiable.

**Algorithm.** Each iteration matches every valid source point to its nearest target point within
the current correspondence distance ``d`` (a hashed-grid search, ``neighbors.py``: cell = ``d``,
27 cells, ``cell_capacity`` slots; searched in two phases, the 8 nearest cells first, outside
``vmap``) and solves eq. 3.18 in closed form (weighted Kabsch/Umeyama
on the inliers, SVD of the 3x3 cross-covariance, reflection-corrected). The transform is always
re-solved from the *original* source points (``T_k = argmin S(R, t)`` of eq. 3.18), so eq. 3.20's
product of increments is implicit and no drift accumulates in float32.

**Schedule** (thesis §6.3 / Appendix A.1): when the change between consecutive transforms,
``sum |T_k - T_{k-1}|`` over all 16 entries (the thesis's transformation epsilon), falls below
``transformation_epsilon`` (default ``res/60``), the correspondence distance shrinks
(``d <- max(shrink_factor * d, min_correspondence_distance)``, defaults ``10 res -> 2 res``
by halves; the thesis subtracted 0.1 m / 0.001 m steps, which needs hundreds of iterations).
ICP stops when it converges at the floor distance or after ``max_iterations``. The stage
distances are planned on the host (their *number* is static, their values traced), and one grid
per stage is built once per call and shared by all hypotheses of ``icp_multi``.

**Why closed form rather than se(3) Gauss-Newton (jaxopt).** For point-to-point residuals the
Kabsch solution is the exact global minimiser of eq. 3.18 for fixed correspondences, while one
Gauss-Newton step linearises the rotation. Measured (``benchmarks/bench_icp_solver.py``, room
pair, warm jitted float32 solves started at the ICP iterate): Kabsch 0.22-0.30 ms at 12k
source points and 0.44-0.71 ms at 57k (moments as column sums, ``_moments``); Gauss-Newton on
the 6x6 normal equations 2.6-8.4x that per step (0.8-1.8 / 3.2-4.9 ms), jaxopt's ``GaussNewton``
7-12x per step, ``LevenbergMarquardt`` (3 steps) 29-40x. One GN step lands 1e-7 to 2e-5 rad
from the minimiser (Kabsch in float32: 1e-6 to 1e-5). Used as the step of a plain ICP loop
(same host kd-tree matches), one or three GN steps per iteration reach the same fixed point
(within 7e-5 rad / 1.3e-4 m) in as many or more outer iterations (0.1 m: 31-34 either way;
0.05 m: 29 -> 31, 95 -> 105-110; jaxopt's LM 25 and 96), and every outer iteration pays a
full nearest-neighbour query (an ``icp`` iteration at 12k points: 2.1 ms, grid build included).
So the closed form is both the cheaper step and the shorter path. jaxopt is not used here.

**Frame independence.** Both clouds are centred on their own centroids before the search
(the transform is re-expressed between the centred frames and back), so the hashed grids are
anchored to the target, not to the frame's origin: the result does not depend on where the maps
lie in their frame (measured: the test pair moved by 1.5 km lands within 0.001 m of the run at
the origin; anchored at the origin, such a shift changed the coarse stages' cells and ended in
another minimum within a voxel), and float32 keeps ~1e-6 relative precision for maps kilometres
from their origin. The stop rule's ``sum |dT|`` is measured in the centred frames too.

**Coarse stages.** The grids of all but the last stage store, per cell, the centroids of the
occupied half-size sub-cells (a voxel-grid downsample at ``d/2``, like the thesis code's PCL
VoxelGrid at 10 res), at most 8 per cell, so the fixed ``cell_capacity`` never drops data there;
the last stage matches the target points themselves. Matching source points to that smoothed
target (``coarse_matching="centroid"``, default) widens the basin of convergence (a yaw of
0.15 rad plus 0.5 m on the test room is recovered exactly; Open3D from the same start stops at
0.034 rad), at the price of a biased coarse fixed point: started *at* the truth of a partial
overlap it can settle 0.01 rad away, where the last stage's exact energy has a local minimum
(Open3D stays at 0.0003 rad). ``coarse_matching="nearest"`` uses the exact nearest target point
whenever one lies within the floor distance (Open3D's fixed point; its narrower basin).
``coarse_matching="symmetric"`` smooths the source too: coarse stages query the source's
voxel-grid centroids at ``d/2`` (weighted by their point counts in the Kabsch solve and the
energy), as the thesis code downsampled both clouds. Far fewer queries on coarse stages, where
half or more of the iterations are spent (0.05 m room pair: 1.97 -> 1.54 s); on 10 starts of
the benchmark pair at 0.2 / 0.1 m the mean final rotation error falls from 0.016 to 0.0045 rad
(worst 0.068 -> 0.011) and the Table 7.1-style grid is unchanged (9/18 coherent). It is not the
default: the source cells are ``5 res`` wide on the first stage, too coarse for small scenes at
coarse resolutions (the 12 m test room at 0.4 m: 2 m cells, a noisy pair ends 0.076 rad off
where ``"centroid"`` is exact; at 0.2 m 0.026 rad, at 0.1 m exact; these figures are against
coarse stages that queried every source point).

**Coarse queries.** With ``"centroid"`` and ``"nearest"`` the coarse stages query every k-th
source point, ``k = clip(count // 2048, 1, 4)`` (Open3D's ``uniform_down_sample``; at least one
2048-query block is kept, fewer would not save a block), the last stage every point. Unlike
``"symmetric"`` the energy stays a mean over real source points (no smoothing), so the basins
hardly move: ``icp_multi`` from 0.5 and 1.7 rad on the benchmark pair finds the right
candidates at 0.2 and 0.1 m as with every point, 1.3-2.5x faster (12 hypotheses, same
process: 0.2 m 2.84 -> 2.12 s and 4.26 -> 2.45 s, 0.1 m 15.0 -> 8.2 s and 24.7 -> 10.0 s);
single pairs end where they did (0.1 / 0.05 m benchmark pair: same errors to 1e-4).
The coarse stages run in a loop of their own on arrays of ``_coarse_rows(n)`` rows (a quarter
of the source's capacity for clouds above 8192 points), so that the whole iteration (search,
transform, energy, Kabsch sums, state), not only the search, scales with the queries; the last
stage runs in a second loop on the source points. Where the rows would not shrink, one loop
serves all stages (one body to compile). Measured in one process (old / new, alternated):
``icp_multi`` with 36 hypotheses at 0.2 m (12k points) 4.2-6.4 -> 3.2-4.8 s; per iteration at
0.1 m (8 starts) 2.3-2.7 -> 1.9-2.2 ms; the first call compiles both bodies, 1.2-4 s more.

**Stopping.** A stage ends when the change falls below ``epsilon`` or, on coarse stages, when
the truncated energy (mean of ``min(d^2, d_stage^2)``) has not improved by 0.1 % for 3
iterations (centroid matches jitter, so the change may never get below ``epsilon`` there). At
the last stage ICP stops when the change falls below ``final_epsilon`` (default
``transformation_epsilon / 100``), so that it reaches the exact fixed point (noise-free clouds
register to ~1e-6), or when its (exact) energy has not reached a new minimum for 6 iterations:
large clouds in float32 end in a cycle of match sets whose changes stay above
``final_epsilon`` (measured: 134k source points at 0.03 m cycled from iteration ~45 to the
400 tried, within 1e-5 rad of where this rule stops at 50).

**Anderson acceleration** (Walker & Ni 2011; for ICP: Pavlov et al. 2018, Zhang et al. 2021).
Point-to-point ICP converges linearly and slowly along sliding directions (walls, corridors).
Each stage extrapolates the fixed-point map ``T -> Kabsch(matches(T))`` from the last 5
iterates in 6-vector coordinates (rotation vector, translation) about the stage's first
transform, and keeps an accelerated iterate only if it lowers the truncated energy; otherwise
it falls back to the plain step and restarts the history (so the energy decreases as in plain
ICP). The fixed point, and so the result and its derivative, are those of plain ICP; to reach
it takes about half the iterations (178-195 -> 78-111 on the test room at 0.2 m).

**Differentiation: implicit, at the fixed point.** The converged transform ``T*`` satisfies the
optimality condition ``g(T*; source, target[c]) = 0`` of eq. 3.18 with the last correspondences
``c``; the correspondences are piecewise constant in every input, so by the implicit function
theorem ``dT* = -H^{-1} dg`` (a 6x6 Gauss-Newton system about the inlier centroid) and
``dT*/dT_init = 0`` almost everywhere (a nearby start converges to the same fixed point). We
attach exactly this derivative to ``T*`` with one stop-gradient Newton step (value unchanged).
Unrolling the loop instead would need reverse-mode through a data-dependent ``while_loop`` (not
supported), memory linear in the iterations, and SVD derivatives that are NaN for planar or
symmetric inlier sets (repeated singular values); the implicit form has none of these problems,
and is exact rather than an approximation of a truncated loop.

**Model choice.** The thesis uses the larger cloud as the model (target): ``icp`` swaps the
clouds when the source is larger and returns the inverted result (``swap_larger=True``,
host-side only; under ``jit``/``vmap`` tracing nothing is swapped).

Status codes (``IcpResult.status``): 0 converged, 1 max_iterations reached, 2 too few inliers
(fewer than ``min_inliers`` correspondences: the transform is the last valid one).
"""

from __future__ import annotations

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from .. import map as _map
from . import neighbors
from .. import se3

__all__ = [
    "invert_result",
    "pad_points_host",
    "sequential_default",
    "IcpResult",
    "IcpMultiResult",
    "STATUS_CONVERGED",
    "STATUS_MAX_ITERATIONS",
    "STATUS_TOO_FEW_INLIERS",
    "icp",
    "icp_padded",
    "icp_padded_stack",
    "icp_multi",
    "default_hypotheses",
    "stage_distances",
    "pad_points",
]

STATUS_CONVERGED = 0
STATUS_MAX_ITERATIONS = 1
STATUS_TOO_FEW_INLIERS = 2
COARSE_MATCHING = ("centroid", "nearest", "symmetric")
_ANDERSON = 5  # history length of the Anderson acceleration (0: plain ICP)
# coarse stages ("centroid", "nearest") query every k-th source point, k <= _COARSE_EVERY, keeping
# at least one query block (neighbors.QUERY_BLOCK): fewer would not save a block
_COARSE_EVERY, _COARSE_MIN_QUERIES = 4, 2048
_STALL_REL, _STALL_PATIENCE = 1e-3, 3  # a coarse stage ends when its energy stalls
_STALL_REL_FINAL, _STALL_PATIENCE_FINAL = 0.0, 6  # the last stage: no new best at all (a cycle)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class IcpResult:
    """Result of one ICP registration (all fields arrays; batched under ``vmap``).

    - ``T_target_source``: ``(4, 4)`` float32, maps source points into the target frame.
    - ``converged``: ``()`` bool, converged at the floor correspondence distance.
    - ``num_iterations``: ``()`` int32, correspondence searches performed.
    - ``num_inliers``: ``()`` int32, source points with a target point within the floor
      (smallest) correspondence distance under ``T_target_source``.
    - ``rmse``: ``()`` float32 [m], root mean square inlier distance.
    - ``fitness``: ``()`` float32, ``num_inliers / valid source points``.
    - ``num_close``: ``()`` int32, source points within a quarter of the floor distance
      (half a voxel at the defaults): the tight overlap ``icp_multi`` ranks candidates by.
    - ``correspondence_distance``: ``()`` float32 [m], the distance of the last stage reached.
    - ``status``: ``()`` int32, see module docstring.
    - ``grid_overflow``: ``()`` int32, target points dropped by the final-stage grid (0 means
      the nearest-neighbour search was exact).
    - ``swapped``: ``()`` bool, the clouds were swapped (larger one as model) and the result
      inverted.
    """

    T_target_source: jax.Array
    converged: jax.Array
    num_iterations: jax.Array
    num_inliers: jax.Array
    rmse: jax.Array
    fitness: jax.Array
    num_close: jax.Array
    correspondence_distance: jax.Array
    status: jax.Array
    grid_overflow: jax.Array
    swapped: jax.Array


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class IcpMultiResult:
    """``icp_multi`` output: the best candidate, every candidate (leading axis ``k``), the
    index of the best, the scores (``num_close - rmse / d_floor``, higher is better), the
    initial guesses used (``(k, 4, 4)``) and ``basin`` (``(k,)`` int32: the candidate whose
    run each candidate's result is; ``basin[i] == i`` unless candidate ``i`` left a stage
    within ``basin_tolerance`` of an earlier one and was merged into it, see ``icp_multi``).
    Counts and rmse are measured at the returned transforms for every candidate.
    ``num_iterations_run`` (``(k,)`` int32): the iterations each hypothesis's own run took
    before it stopped or merged (``candidates.num_iterations`` of a merged candidate is its
    leader's); their sum is the call's work. ``None`` where the candidates do not come from
    ``icp_multi``.

    Why ``num_close`` (points within ``d_floor / 4``) and not ``num_inliers`` (within
    ``d_floor``): a room turned by pi onto itself fits many points within two voxels, but
    fewer within half a voxel than the right alignment (measured on the test room at 0.5 rad:
    right 7.7-7.9k vs flipped 7.5k close points, while the inlier counts were 10.5-10.7k vs
    10.7k)."""

    best: IcpResult
    candidates: IcpResult
    best_index: jax.Array
    scores: jax.Array
    hypotheses: jax.Array
    basin: jax.Array
    num_iterations_run: jax.Array | None = None


# ----------------------------------------------------------------------------- host helpers


def pad_points(points, capacity: int | None = None, *, name: str = "points"):
    """Host: ``(n, 3)`` points [m] -> ``(padded (C, 3) float32 jax array, count int32)`` with
    ``C = bucket_capacity(n)`` unless given. Raises ``ValueError`` naming ``name`` on a bad
    shape or non-finite coordinates."""
    out, n = pad_points_host(points, capacity, name)
    return jnp.asarray(out), jnp.asarray(n, jnp.int32)


def pad_points_host(points, capacity, name):
    """``pad_points`` on the host: ``(padded (C, 3) float32 NumPy array, n)``."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{name}: expected shape (n, 3), got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{name}: contains non-finite coordinates")
    n = p.shape[0]
    cap = _map.bucket_capacity(n) if capacity is None else int(capacity)
    if cap < n:
        raise ValueError(f"{name}: capacity {cap} < {n} points")
    out = np.zeros((cap, 3), np.float32)
    out[:n] = p
    return out, n


def stage_distances(resolution: float, max_correspondence_distance: float | None = None,
                    min_correspondence_distance: float | None = None,
                    shrink_factor: float = 0.5) -> np.ndarray:
    """Host: the correspondence-distance schedule ``(s,)`` [m]: ``d_max, shrink*d_max, ...``
    clipped at ``d_min`` (defaults ``10 res`` and ``2 res``)."""
    res = float(resolution)
    if not (np.isfinite(res) and res > 0):
        raise ValueError(f"resolution must be a positive number of metres, got {resolution!r}")
    d_max = 10.0 * res if max_correspondence_distance is None else float(max_correspondence_distance)
    d_min = min(2.0 * res, d_max) if min_correspondence_distance is None else float(min_correspondence_distance)
    if not (np.isfinite(d_max) and d_max > 0):
        raise ValueError(f"max_correspondence_distance must be positive, got {max_correspondence_distance!r}")
    if not (np.isfinite(d_min) and 0 < d_min <= d_max):
        raise ValueError(f"min_correspondence_distance must lie in (0, max_correspondence_distance="
                         f"{d_max:g}], got {min_correspondence_distance!r}")
    if not 0.0 < float(shrink_factor) < 1.0:
        raise ValueError(f"shrink_factor must lie in (0, 1), got {shrink_factor!r}")
    out = [d_max]
    while out[-1] > d_min * (1 + 1e-9) and len(out) < 32:
        out.append(max(out[-1] * float(shrink_factor), d_min))
    return np.asarray(out, np.float32)


# ----------------------------------------------------------------------------- kernels


def _moments(src, dst, wf, stride: int = 16):
    """Weighted means ``ms, md (3,)`` and cross-covariance ``H = sum wf (s - ms)(d - md)^T
    (3, 3)`` of ``src, dst (n, 3)`` [m] with weights ``wf (n,)``, in one pass of 16 scalar
    sums over columns: XLA:CPU reduced the ``(n, 3)`` arrays along ``n`` (and ran the 3x3
    ``dot``) 3-4x slower inside the ICP loop (0.1 m pair: ~0.67 -> ~0.15 ms per iteration;
    8 starts at 0.1 / 0.05 m 0.83 -> 0.69 s, 4.81 -> 4.02 s). The sums are taken about the
    weighted mean of every ``stride``-th point, so that the one-pass formula keeps float32
    precision when the inliers lie far from the origin (about the origin, a 2 m patch 100 m
    away came out 5e-4 rad off; about the reference, within 3e-7 of the float64 solution,
    as the two-pass form)."""
    ws = wf[::stride]
    k = jnp.sum(ws)

    def reference(x):  # weighted mean of every stride-th row; the origin when none has weight
        mean = jnp.stack([jnp.sum(x[::stride, i] * ws) for i in range(3)]) / jnp.maximum(k, 1e-30)
        return jnp.where(k > 0, mean, 0.0)

    cs, cd = reference(src), reference(dst)
    s = [src[:, i] - cs[i] for i in range(3)]
    d = [dst[:, i] - cd[i] for i in range(3)]
    a = [s[i] * wf for i in range(3)]
    sums = [jnp.sum(a[i] * d[j]) for i in range(3) for j in range(3)]
    sums += [jnp.sum(a[i]) for i in range(3)] + [jnp.sum(wf * d[j]) for j in range(3)] + [jnp.sum(wf)]
    m = jnp.stack(sums)
    W = jnp.maximum(m[15], 1e-30)
    ms, md = m[9:12] / W, m[12:15] / W
    H = m[:9].reshape(3, 3) - W * jnp.outer(ms, md)
    return ms + cs, md + cd, H


def _kabsch(src, dst, w):
    """Weighted least squares ``argmin_{R,t} sum w |R src + t - dst|^2`` (eq. 3.18), closed form."""
    wf = w.astype(src.dtype)
    ms, md, H = _moments(src, dst, wf)
    U, _, Vt = jnp.linalg.svd(H)
    V = Vt.T
    d = jnp.sign(jnp.linalg.det(V @ U.T))
    d = jnp.where(d == 0, 1.0, d)
    R = V @ jnp.diag(jnp.stack([jnp.ones_like(d), jnp.ones_like(d), d])) @ U.T
    t = md - R @ ms
    return se3.from_rotation_translation(R, t)


def _skew(v):
    z = jnp.zeros_like(v[..., 0])
    return jnp.stack([jnp.stack([z, -v[..., 2], v[..., 1]], -1),
                      jnp.stack([v[..., 2], z, -v[..., 0]], -1),
                      jnp.stack([-v[..., 1], v[..., 0], z], -1)], -2)


def _implicit_step(T_hat, src, tgt_pts, w):
    """``T_hat`` (value) carrying the implicit-function-theorem derivative of the least
    squares fixed point with respect to ``src`` and ``tgt_pts`` (see module docstring)."""
    T_hat = jax.lax.stop_gradient(T_hat)
    w = jax.lax.stop_gradient(w).astype(src.dtype)
    n = jnp.maximum(jnp.sum(w), 1.0)
    p = se3.transform_points(T_hat, src)
    c = jax.lax.stop_gradient(jnp.sum(w[:, None] * p, 0) / n)
    pc = p - c
    r = p - tgt_pts
    # left perturbation about c: x' = x + [omega]x (x - c) + v;  J_i = [I, -[pc_i]x]
    g = jnp.concatenate([jnp.sum(w[:, None] * r, 0), jnp.sum(w[:, None] * jnp.cross(pc, r), 0)])
    spc = jnp.sum(w[:, None] * pc, 0)
    K = _skew(pc)
    Hrr = -jnp.einsum("n,nij,njk->ik", w, K, K)
    Htr = -_skew(spc)
    H = jnp.block([[n * jnp.eye(3, dtype=src.dtype), Htr], [-Htr, Hrr]])
    H = jax.lax.stop_gradient(H)
    lam = 1e-6 * jnp.trace(H) / 6.0 + 1e-12
    delta = -jnp.linalg.solve(H + lam * jnp.eye(6, dtype=src.dtype), g)
    delta = jnp.where(jnp.all(jnp.isfinite(delta)), delta, jnp.zeros_like(delta))
    v, om = delta[:3], delta[3:]
    Om = _skew(om)
    Xi = jnp.zeros((4, 4), src.dtype).at[:3, :3].set(Om).at[:3, 3].set(v - Om @ c)
    return T_hat + (Xi - jax.lax.stop_gradient(Xi)) @ T_hat


def _so3_exp(w):
    """Rotation matrix of the rotation vector ``w (3,)`` [rad] (Rodrigues)."""
    th2 = jnp.sum(w * w)
    small = th2 < 1e-8
    th = jnp.sqrt(jnp.where(small, 1.0, th2))
    a = jnp.where(small, 1.0 - th2 / 6.0, jnp.sin(th) / th)
    b = jnp.where(small, 0.5 - th2 / 24.0, (1.0 - jnp.cos(th)) / jnp.where(small, 1.0, th2))
    K = _skew(w)
    return jnp.eye(3, dtype=w.dtype) + a * K + b * (K @ K)


def _so3_log(R):
    """Rotation vector ``(3,)`` [rad] of ``R (3, 3)`` (angle < pi; accurate for small angles)."""
    v = jnp.stack([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    s2 = jnp.sqrt(jnp.sum(v * v))  # 2 sin(theta)
    th = jnp.arctan2(0.5 * s2, 0.5 * (jnp.trace(R) - 1.0))
    f = jnp.where(s2 < 1e-7, 0.5, th / jnp.where(s2 < 1e-7, 1.0, s2))
    return f * v


def _chart(T, T_ref):
    """6-vector coordinates ``(rotation vector of R R_ref^T, t - t_ref)`` of ``T`` about ``T_ref``."""
    return jnp.concatenate([_so3_log(T[:3, :3] @ T_ref[:3, :3].T), T[:3, 3] - T_ref[:3, 3]])


def _unchart(x, T_ref):
    return se3.from_rotation_translation(_so3_exp(x[:3]) @ T_ref[:3, :3], x[3:] + T_ref[:3, 3])


def _anderson(x_g, f, dF, dG, n_hist):
    """Anderson acceleration (type II, Walker & Ni 2011) of the fixed-point map ``x -> g``:
    ``x_g - dG gamma`` with ``gamma = argmin |f - dF gamma|``; ``dF, dG (m, 6)`` hold the
    last ``n_hist`` differences of residuals ``f = g - x`` and of images ``g`` (older rows
    zero)."""
    m = dF.shape[0]
    used = (jnp.arange(m) < n_hist).astype(f.dtype)
    A = dF * used[:, None]
    M = A @ A.T
    reg = 1e-8 * jnp.max(jnp.diag(M)) + 1e-20
    gamma = jnp.linalg.solve(M + reg * jnp.eye(m, dtype=f.dtype) + jnp.diag(1.0 - used), A @ f)
    x = x_g - (dG * used[:, None]).T @ gamma
    return jnp.where(jnp.all(jnp.isfinite(x)), x, x_g)


def _voxel_downsample(points, valid, cell):
    """Voxel-grid downsample (PCL's VoxelGrid): the centroid of the valid ``points (n, 3)`` in
    each occupied cube of edge ``cell`` [m] (traced). Returns ``(centroids (n, 3), weights (n,)
    float32 point counts, m)``: rows ``< m`` hold the cells (weight >= 1), the rest weight 0.
    Jittable and vmappable (one sort and two segment sums)."""
    n = points.shape[0]
    big = jnp.iinfo(jnp.int32).max
    c = jnp.where(valid[:, None], jnp.floor(points / cell).astype(jnp.int32), big)
    rows = jnp.arange(n, dtype=jnp.int32)
    cx, cy, cz, order = jax.lax.sort((c[:, 0], c[:, 1], c[:, 2], rows), num_keys=3)
    start = jnp.concatenate([jnp.ones((1,), bool),
                             (cx[1:] != cx[:-1]) | (cy[1:] != cy[:-1]) | (cz[1:] != cz[:-1])])
    seg = jnp.cumsum(start.astype(jnp.int32)) - 1
    v = valid[order]
    sums = jax.ops.segment_sum(jnp.where(v[:, None], points[order], 0.0), seg, num_segments=n)
    counts = jax.ops.segment_sum(v.astype(jnp.float32), seg, num_segments=n)
    return sums / jnp.maximum(counts, 1.0)[:, None], counts, jnp.sum(start & v).astype(jnp.int32)


def _coarse_rows(n: int, downsample: bool) -> int:
    """Static rows of the coarse stages' query cloud for a source of capacity ``n``. Every k-th
    point (``_every_kth``, ``m = _COARSE_MIN_QUERIES``) leaves ``count`` rows for ``count <
    2 m`` (k = 1), at most ``1.5 m`` for k = 2 and 3, and ``count / 4 <= n / 4`` for k = 4:
    so ``max(min(n, 2 m), n / 4)`` rows, rounded up to whole query blocks, hold every count
    (``n`` itself for small clouds). The voxel-grid centroids (``downsample``) need ``n``."""
    if downsample:
        return n
    block = neighbors.QUERY_BLOCK  # the search's query block
    rows = max(min(n, 2 * _COARSE_MIN_QUERIES), -(-n // _COARSE_EVERY))
    return min(n, -(-rows // block) * block)


def _every_kth(src, source_count, rows: int):
    """The coarse stages' query cloud without ``downsample``: every k-th source point (Open3D's
    ``uniform_down_sample``), ``k = clip(count // _COARSE_MIN_QUERIES, 1, _COARSE_EVERY)``,
    packed to the front of ``rows`` rows (``_coarse_rows``): ``(points (rows, 3), weights
    (rows,), count)``. Fewer queries where most iterations are spent; the energy stays a mean
    over real source points (no smoothing)."""
    n = src.shape[0]
    count = jnp.asarray(source_count, jnp.int32)
    k = jnp.clip(count // _COARSE_MIN_QUERIES, 1, _COARSE_EVERY)
    at = jnp.arange(rows, dtype=jnp.int32) * k
    keep = at < count
    pts = jnp.where(keep[:, None], src[jnp.minimum(at, n - 1)], 0.0)
    return pts, keep.astype(src.dtype), (count + k - 1) // k


def _coarse_clouds(src, valid, source_count, dists, downsample: bool):
    """The query clouds of the coarse stages (all but the last): ``(points (S, m, 3), weights
    (S, m), counts (S,))`` with ``m = _coarse_rows(n)``: the source's voxel-grid centroids at
    ``d / 2`` weighted by their point counts when ``downsample`` (one entry per coarse stage),
    else every k-th point (``_every_kth``, one entry for all). ``None`` for one stage."""
    num_stages = dists.shape[0]
    if num_stages == 1:
        return None
    if downsample:
        coarse = [_voxel_downsample(src, valid, dists[s] * 0.5) for s in range(num_stages - 1)]
    else:
        coarse = [_every_kth(src, source_count, _coarse_rows(src.shape[0], False))]
    return tuple(jnp.stack([c[i] for c in coarse]) for i in range(3))


def _coarse_cloud(clouds, stage):
    """Coarse stage ``stage``'s ``(points (m, 3), weights (m,), count)`` of ``_coarse_clouds``."""
    i = jnp.minimum(stage, clouds[0].shape[0] - 1)
    return clouds[0][i], clouds[1][i], clouds[2][i]


def _icp_core(source, source_count, target, grids, T_init, dists, epsilon, final_epsilon,
              min_inliers, max_iterations: int, anderson: int | None = None,
              coarse_matching: str = "centroid", two_phase: bool = True, start=None,
              stop_stage: int | None = None, coarse: bool = True, stop_when=None):
    """One registration on padded clouds with pre-built stage grids (vmappable over T_init;
    pass ``two_phase=False`` under ``vmap``, see ``neighbors.nearest_with_points``).

    Two loops of the same iteration: the coarse stages on the coarse query cloud, whose arrays
    have ``_coarse_rows(n)`` rows (a quarter of the source's for large clouds: the per-point
    work of an iteration, not only its search, scales with the queries), then the last stage
    on the source points; one loop for all stages when the coarse cloud is as long as the
    source. The hand-over is a stage change, which restarts the acceleration history and the
    stall count anyway, so the iterates are those of one loop.

    Resumable, for ``icp_multi``'s basin merging: ``stop_stage`` (may be traced) returns the loop
    state ``(T, stage, iteration, done, status)`` as soon as the run leaves that stage (or
    stops); only coarse stages can be stop stages (the last stage's loop is not built then).
    ``start`` resumes from such a state (``T_init`` is then ignored); ``coarse=False`` skips the
    coarse loop (every resumed run is past the coarse stages). A run split at a stage boundary
    takes exactly the steps of the uninterrupted run. ``stop_when(T) -> bool`` (with
    ``stop_stage``) also returns the state before any iteration at whose start it holds."""
    nearest = partial(neighbors.nearest_with_points, two_phase=two_phase)
    src_sg = jax.lax.stop_gradient(source)
    n = source.shape[0]
    valid = jnp.arange(n) < source_count
    src_sg = jnp.where(valid[:, None], src_sg, 0.0)
    num_stages = dists.shape[0]
    T0 = jax.lax.stop_gradient(jnp.asarray(T_init, jnp.float32))
    last_stage = num_stages - 1
    d_floor2 = dists[last_stage] * dists[last_stage]
    anderson = _ANDERSON if anderson is None else int(anderson)
    m_hist = max(anderson, 1)
    # coarse stages query every k-th source point, or with "symmetric" the source's voxel-grid
    # centroids (both clouds smoothed at the stage's scale, as the thesis code's VoxelGrid on
    # both clouds); the last stage every point
    coarse_clouds = _coarse_clouds(src_sg, valid, source_count, dists, coarse_matching == "symmetric")
    full = (src_sg, valid.astype(src_sg.dtype), jnp.asarray(source_count, jnp.int32))

    def correspond(T, stage, queries):
        # coarse stages: the nearest sub-cell centroid of the stage's grid ("centroid",
        # "symmetric"), or the exact nearest target point when one lies within the floor
        # distance and the nearest centroid otherwise ("nearest"); last stage: the exact
        # nearest point. ``queries`` = (points, weights, count), a stage's query cloud.
        pts, wt, cnt = queries
        p = se3.transform_points(T, pts)
        if coarse_matching != "nearest":  # one query; the level is data (no cond: vmap-friendly)
            return _finish_match(*nearest(grids, p, stage, cnt), stage, wt)
        d2, idx, match = nearest(grids, p, last_stage, cnt)
        fine = (idx >= 0) & (d2 <= d_floor2)

        def coarse(_):
            d2c, idxc, matchc = nearest(grids, p, stage, cnt)
            return (jnp.where(fine, d2, d2c), jnp.where(fine, idx, idxc),
                    jnp.where(fine[:, None], match, matchc))

        return _finish_match(*jax.lax.cond(stage == last_stage, lambda _: (d2, idx, match), coarse, None),
                             stage, wt)

    def _finish_match(d2, idx, match, stage, wt):
        dmax = dists[stage]
        w = (wt > 0) & (idx >= 0) & (d2 <= dmax * dmax)
        return d2, jnp.maximum(idx, 0), w, match

    def energy(d2, stage, wt):
        # truncated least squares: weighted mean over the stage's cloud (weights ``wt``) of
        # min(d^2, d_stage^2), comparable between iterates of one stage (the safeguard of the
        # accelerated steps)
        dmax2 = dists[stage] * dists[stage]
        return jnp.sum(wt * jnp.minimum(jnp.where(wt > 0, d2, 0.0), dmax2)) / jnp.maximum(jnp.sum(wt), 1.0)

    zero6 = jnp.zeros((6,), jnp.float32)
    hist0 = jnp.zeros((m_hist, 6), jnp.float32)

    def body(cloud, state):
        (T, stage, it, done, status, idx_k, w_k, match_k, T_plain, accel, E_prev, T_ref, dF, dG, n_hist,
         f_prev, g_prev, E_best, stall) = state
        pts, wt, _ = queries = cloud(stage)
        d2, idx, w, match = correspond(T, stage, queries)
        E = energy(d2, stage, wt)
        # safeguard (Zhang et al. 2021, "Fast and robust ICP"): an accelerated iterate that
        # does not lower the energy is replaced by the plain step it extrapolated from
        reject = accel & ~(E < E_prev)
        n_in = jnp.sum(w)
        enough = n_in >= min_inliers
        G = jnp.where(enough, _kabsch(pts, jnp.where(w[:, None], match, 0.0), jnp.where(w, wt, 0.0)), T)
        change = jnp.sum(jnp.abs(G - T))
        last = stage == last_stage
        # a stage also ends when its energy stalls: no new best by a relative margin for
        # _STALL_PATIENCE iterations (coarse stages jitter between centroid matches and the
        # transform change may never fall below epsilon there); the last stage when no new
        # best at all for _STALL_PATIENCE_FINAL iterations, rejected steps included (a cycle)
        better = E < E_best * (1.0 - jnp.where(last, _STALL_REL_FINAL, _STALL_REL))
        stall = jnp.where(better | (reject & ~last), 0, stall + 1)
        E_best = jnp.minimum(E_best, E)
        stalled = stall >= jnp.where(last, _STALL_PATIENCE_FINAL, _STALL_PATIENCE)
        small = ((change < jnp.where(last, final_epsilon, epsilon)) | stalled) & ~reject
        finish = ((small & last) | ~enough) & ~reject
        advance = small & ~last
        # Anderson step in the chart about T_ref (history restarts on rejection / new stage)
        g = _chart(G, T_ref)
        f = g - _chart(T, T_ref)
        has_prev = n_hist > 0
        dF_new = jnp.where(has_prev, jnp.roll(dF, 1, 0).at[0].set(f - f_prev), dF)
        dG_new = jnp.where(has_prev, jnp.roll(dG, 1, 0).at[0].set(g - g_prev), dG)
        n_used = jnp.minimum(n_hist, m_hist)
        x_acc = _anderson(g, f, dF_new, dG_new, n_used) if anderson > 0 else g
        use_acc = (n_used > 0) & (anderson > 0)
        T_acc = jnp.where(use_acc, _unchart(x_acc, T_ref), G)
        restart = reject | advance
        T_next = jnp.where(reject, T_plain, jnp.where(advance | finish, G, T_acc))
        new_status = jnp.where(~enough, STATUS_TOO_FEW_INLIERS, STATUS_CONVERGED)
        keep = reject  # a rejected iterate's correspondences are not used
        return (T_next,
                jnp.where(advance, stage + 1, stage),
                it + 1,
                finish,
                jnp.where(finish, new_status, status).astype(jnp.int32),
                jnp.where(keep, idx_k, idx), jnp.where(keep, w_k, w), jnp.where(keep, match_k, match),
                jnp.where(keep, T_plain, G),
                use_acc & ~restart & ~finish,
                jnp.where(restart, jnp.inf, E),
                jnp.where(restart, T_next, T_ref),
                jnp.where(restart, hist0, dF_new), jnp.where(restart, hist0, dG_new),
                jnp.where(restart, 0, jnp.minimum(n_hist + 1, m_hist + 1)).astype(jnp.int32),
                jnp.where(restart, zero6, f), jnp.where(restart, zero6, g),
                jnp.where(advance, jnp.inf, E_best), jnp.where(advance, 0, stall).astype(jnp.int32))

    def running(state):
        go = (~state[3]) & (state[2] < max_iterations)
        if stop_stage is not None:
            go = go & (state[1] <= stop_stage)
        return go if stop_when is None else go & ~stop_when(state[0])

    def run_loop(state, cloud, rows: int, in_loop):
        """Iterate while ``in_loop(stage)``; the per-point state (last correspondences) is
        ``rows`` long and starts empty, the rest carries over (a stage change restarts it)."""
        per_point = (jnp.zeros((rows,), jnp.int32), jnp.zeros((rows,), bool),
                     jnp.zeros((rows, 3), jnp.float32))
        state = (*state[:5], *per_point, *state[8:])
        return jax.lax.while_loop(lambda st: running(st) & in_loop(st[1]), partial(body, cloud), state)

    if start is None:
        start = (T0, jnp.int32(0), jnp.int32(0), jnp.bool_(False), jnp.int32(STATUS_MAX_ITERATIONS))
    T0 = jax.lax.stop_gradient(jnp.asarray(start[0], jnp.float32))
    state = (T0, *(jnp.asarray(x) for x in start[1:]), None, None, None,
             T0, jnp.bool_(False), jnp.float32(jnp.inf), T0, hist0, hist0, jnp.int32(0), zero6, zero6,
             jnp.float32(jnp.inf), jnp.int32(0))
    every_stage = lambda stage: True  # noqa: E731
    if coarse_clouds is None:
        loops = [(lambda stage: full, n, every_stage)]
    elif coarse_clouds[0].shape[1] == n:  # nothing to save: one loop (one body to compile)
        clouds = tuple(jnp.concatenate([c, f[None]]) for c, f in zip(coarse_clouds, full))
        num = clouds[0].shape[0]  # the coarse stages' entries, then the source points

        def any_stage(stage):
            i = jnp.where(stage == last_stage, num - 1, jnp.minimum(stage, num - 2))
            return clouds[0][i], clouds[1][i], clouds[2][i]

        loops = [(any_stage, n, every_stage)]
    else:
        loops = [(partial(_coarse_cloud, coarse_clouds), coarse_clouds[0].shape[1],
                  lambda stage: stage < last_stage)] if coarse else []
        if stop_stage is None:
            loops.append((lambda stage: full, n, lambda stage: stage == last_stage))
    for cloud, rows, in_loop in loops:
        state = run_loop(state, cloud, rows, in_loop)
    if stop_stage is not None:
        return state[:5]
    _, stage, it, done, status, idx, w, match, T = state[:9]
    status = jnp.where(done, status, STATUS_MAX_ITERATIONS).astype(jnp.int32)
    if coarse_clouds is not None:
        # stopped on a coarse stage (max_iterations): its correspondences name centroids;
        # the derivative below needs the source points' own, at that stage
        # (a cond: the usual stop, at the last stage, skips this full-cloud query)
        idx, w, match = jax.lax.cond(stage == last_stage, lambda: (idx, w, match),
                                     lambda: correspond(T, stage, full)[1:])

    # final report at the returned transform and the floor distance (a common yardstick, so
    # that icp_multi can rank candidates that stopped at different stages)
    d2, _, w_fin, _ = correspond(T, jnp.int32(last_stage), full)
    n_in = jnp.sum(w_fin).astype(jnp.int32)
    rmse = jnp.sqrt(jnp.sum(jnp.where(w_fin, d2, 0.0)) / jnp.maximum(n_in, 1).astype(jnp.float32))
    n_valid = jnp.maximum(source_count, 1).astype(jnp.float32)

    # y has the value of the matched coordinates (T is exactly their least-squares solution)
    # and the derivative of the matched target points (exact at the finest stage; on a
    # coarse centroid stage, reached only via max_iterations, it is that of one member point)
    y_t = jnp.asarray(target, jnp.float32)[idx]
    y = jax.lax.stop_gradient(match) + (y_t - jax.lax.stop_gradient(y_t))
    T_out = _implicit_step(T, jnp.asarray(source, jnp.float32), y, w)
    return IcpResult(
        T_target_source=T_out,
        converged=status == STATUS_CONVERGED,
        num_iterations=it,
        num_inliers=n_in,
        rmse=rmse,
        fitness=n_in.astype(jnp.float32) / n_valid,
        num_close=jnp.sum(w_fin & (d2 <= d_floor2 / 16.0)).astype(jnp.int32),
        correspondence_distance=dists[stage],
        status=status,
        grid_overflow=grids.overflow[stage],
        swapped=jnp.bool_(False),
    )


def _build(target, target_count, dists, table_sizes, cell_capacity):
    # coarse stages match against the voxel-grid centroids at d/2 (the thesis code's VoxelGrid
    # downsampling); the last stage against the target points themselves
    cl = (True,) * (len(table_sizes) - 1) + (False,)
    return neighbors.build_grids(jax.lax.stop_gradient(jnp.asarray(target, jnp.float32)), target_count,
                                 dists, table_sizes=table_sizes, cell_capacity=cell_capacity,
                                 centroid_levels=cl)


def _centroid(points, count):
    valid = (jnp.arange(points.shape[0]) < count)[:, None]
    return jnp.sum(jnp.where(valid, points, 0.0), 0) / jnp.maximum(count, 1).astype(points.dtype)


def _centered(source, source_count, target, target_count, T):
    """Both clouds about their own centroids and ``T`` re-expressed between the centred
    frames: the hash grids are then anchored to the target, not to the frame's origin, so
    results do not depend on where the maps lie in their frames (translation-equivariant) and
    float32 keeps its precision for maps kilometres from the origin. Returns
    ``(source', target', T', uncentre)`` with ``uncentre(T') = T``."""
    cs = jax.lax.stop_gradient(_centroid(source, source_count))
    ct = jax.lax.stop_gradient(_centroid(target, target_count))
    shift = lambda T, a, b: T.at[..., :3, 3].add(jnp.einsum("...ij,j->...i", T[..., :3, :3], a) - b)  # noqa: E731
    return source - cs, target - ct, shift(T, cs, ct), lambda Tc: shift(Tc, -cs, -ct)


def _uncentre_result(r: IcpResult, uncentre) -> IcpResult:
    return dataclasses.replace(r, T_target_source=uncentre(r.T_target_source))


@partial(jax.jit, static_argnames=("max_iterations", "cell_capacity", "table_sizes", "coarse_matching",
                                   "two_phase"))
def _icp_padded_jit(source, source_count, target, target_count, T_init, dists, epsilon,
                    final_epsilon, min_inliers, *, max_iterations, cell_capacity, table_sizes,
                    coarse_matching, two_phase):
    source, target, T_init, uncentre = _centered(source, source_count, target, target_count, T_init)
    grids = _build(target, target_count, dists, table_sizes, cell_capacity)
    r = _icp_core(source, source_count, target, grids, T_init, dists, epsilon, final_epsilon,
                  min_inliers, max_iterations, coarse_matching=coarse_matching, two_phase=two_phase)
    return _uncentre_result(r, uncentre)


def _table_sizes(capacity, dists, table_sizes):
    if table_sizes is not None:
        return tuple(int(t) for t in table_sizes)
    if _is_traced(dists):
        raise ValueError("table_sizes must be given when the stage distances are traced")
    return neighbors.level_table_sizes(capacity, np.asarray(dists))


def icp_padded(source, source_count, target, target_count, T_target_source_init, dists,
               epsilon, final_epsilon=None, min_inliers=6, *, max_iterations: int = 100,
               cell_capacity: int = 8, table_sizes: tuple[int, ...] | None = None,
               coarse_matching: str = "centroid", two_phase: bool = True) -> IcpResult:
    """ICP on padded clouds, jitted: ``source (Ns, 3)``, ``target (Nt, 3)`` float32 [m] whose
    rows ``>= *_count`` are padding, ``T_target_source_init (4, 4)``, stage distances
    ``dists (s,)`` [m] (``stage_distances``), ``epsilon`` (stage change threshold, sum of
    ``|dT|``), ``final_epsilon`` (threshold at the last stage, default ``epsilon / 100``) and
    ``min_inliers`` are traced; ``max_iterations``, ``cell_capacity`` and ``table_sizes``
    (default ``neighbors.level_table_sizes(Nt, dists)``, needs concrete ``dists``),
    ``coarse_matching`` (see ``icp``) and ``two_phase`` (the nearest-neighbour search,
    ``neighbors.nearest_with_points``) are static. Pure and ``vmap``-able over stacked pairs of
    one bucket (pass ``table_sizes`` then, and ``two_phase=False``: same results, and under
    ``vmap`` the one-phase search is the cheaper)."""
    _check_choice(coarse_matching)
    ts = _table_sizes(target.shape[0], dists, table_sizes)
    epsilon = _arg(epsilon, np.float32)
    final_epsilon = epsilon * np.float32(0.01) if final_epsilon is None else _arg(final_epsilon, np.float32)
    return _icp_padded_jit(source, source_count, target, target_count,
                           _arg(T_target_source_init, np.float32), _arg(dists, np.float32), epsilon,
                           final_epsilon, _arg(min_inliers, np.int32), max_iterations=int(max_iterations),
                           cell_capacity=int(cell_capacity), table_sizes=ts,
                           coarse_matching=coarse_matching, two_phase=bool(two_phase))


@partial(jax.jit, static_argnames=("max_iterations", "cell_capacity", "table_sizes", "coarse_matching",
                                   "sequential"))
def icp_padded_stack(sources, source_counts, targets, target_counts, T_inits, dists, epsilon,
                     final_epsilon, min_inliers, *, max_iterations: int, cell_capacity: int,
                     table_sizes: tuple[int, ...], coarse_matching: str, sequential: bool):
    """``icp_padded`` over stacked pairs of one bucket (leading axis ``p`` on the clouds,
    counts and ``T_inits``; the rest shared), as one ``IcpResult`` with leading axis ``p``:
    pair after pair (``lax.map``, ``sequential=True``: each stops at its own convergence,
    the faster on CPUs) or as one ``vmap`` batch (accelerators)."""
    def one(s, sc, t, tc, T):
        return _icp_padded_jit(s, sc, t, tc, T, dists, epsilon, final_epsilon, min_inliers,
                               max_iterations=max_iterations, cell_capacity=cell_capacity,
                               table_sizes=table_sizes, coarse_matching=coarse_matching,
                               two_phase=sequential)

    xs = (sources, source_counts, targets, target_counts, T_inits)
    if sequential:
        return jax.lax.map(lambda a: one(*a), xs)
    return jax.vmap(one)(*xs)


def _check_choice(coarse_matching):
    if coarse_matching not in COARSE_MATCHING:
        raise ValueError(f"coarse_matching must be one of {COARSE_MATCHING}, got {coarse_matching!r}")


def _is_traced(*xs) -> bool:
    return any(isinstance(x, jax.core.Tracer) for x in xs)


def _arg(x, dtype):
    """An argument for a jitted call: JAX arrays (and tracers) as they are, anything else as a
    NumPy array (host values go to the device with the call, not one eager op each)."""
    return jnp.asarray(x, dtype) if isinstance(x, jax.Array) else np.asarray(x, dtype)


def _prepare(points, count, name):
    """(padded (C,3) float32 array, count, host count or None)."""
    if count is None and not _is_traced(points):
        p, c = pad_points_host(points, None, name)
        return p, np.int32(c), c
    p = jnp.asarray(points, jnp.float32)
    if p.ndim != 2 or p.shape[-1] != 3:
        raise ValueError(f"{name}: expected shape (n, 3), got {p.shape}")
    c = jnp.asarray(p.shape[0] if count is None else count, jnp.int32)
    host = None if _is_traced(c) else int(c)
    return p, c, host


def _options(resolution, max_correspondence_distance, min_correspondence_distance, shrink_factor,
             transformation_epsilon, max_iterations, cell_capacity):
    dists = stage_distances(resolution, max_correspondence_distance, min_correspondence_distance,
                            shrink_factor)
    eps = float(resolution) / 60.0 if transformation_epsilon is None else float(transformation_epsilon)
    if not eps > 0:
        raise ValueError(f"transformation_epsilon must be positive, got {transformation_epsilon!r}")
    if int(max_iterations) < 1:
        raise ValueError(f"max_iterations must be >= 1, got {max_iterations!r}")
    if int(cell_capacity) < 1:
        raise ValueError(f"cell_capacity must be >= 1, got {cell_capacity!r}")
    return dists, np.float32(eps)


def _number(x) -> float:
    """``float(x)``, or NaN for anything that is not a real number (rejected by the caller)."""
    try:
        return float(x)
    except (TypeError, ValueError):
        return float("nan")


def _check_T(T, name):
    if _is_traced(T):
        return jnp.asarray(T, jnp.float32)
    return se3.check_rigid(T, name).astype(np.float32)


def invert_result(r: IcpResult) -> IcpResult:
    """The result of the swapped problem read back: ``T_target_source`` inverted, ``swapped`` set."""
    return dataclasses.replace(r, T_target_source=se3.inverse(r.T_target_source),
                               swapped=jnp.ones_like(r.swapped))


def icp(source, target, T_target_source_init, *, resolution: float,
        max_correspondence_distance: float | None = None,
        min_correspondence_distance: float | None = None, shrink_factor: float = 0.5,
        transformation_epsilon: float | None = None, max_iterations: int = 100,
        cell_capacity: int = 8, min_inliers: int = 6, swap_larger: bool = True,
        coarse_matching: str = "centroid", source_count=None, target_count=None) -> IcpResult:
    """Register ``source`` to ``target`` (Alg. 3): returns ``IcpResult`` whose
    ``T_target_source`` maps source points into the target frame.

    ``source (Ns, 3)``, ``target (Nt, 3)`` [m]: NumPy arrays are validated and padded to
    ``bucket_capacity``; JAX arrays (e.g. inside ``jit``/``grad``/``vmap``) are used as given,
    with optional ``*_count`` valid-row counts. ``T_target_source_init (4, 4)``.
    ``resolution`` [m] sets the defaults: distances ``10 res -> 2 res`` halving, epsilon
    ``res / 60`` (sum of absolute entry changes of T). Differentiable w.r.t. the point
    coordinates (implicit differentiation at the fixed point, see module docstring).

    ``coarse_matching``: ``"centroid"`` (default) matches coarse stages to the target's
    voxel-grid centroids at ``d / 2`` (a smoothed target, like the thesis code's VoxelGrid
    downsampling: a wider basin of convergence); ``"nearest"`` matches the exact nearest target
    point whenever one lies within the floor distance (Open3D's semantics: the same fixed point
    as Open3D near the solution, a narrower basin); ``"symmetric"`` is ``"centroid"`` with the
    source's voxel-grid centroids at ``d / 2`` as the queries (see the module docstring).
    Coarse stages of ``"centroid"`` and ``"nearest"`` query every k-th source point (k <= 4,
    at least 2048 queries kept). The last stage always matches the exact nearest target point
    to every source point.
    """
    dists, eps = _options(resolution, max_correspondence_distance, min_correspondence_distance,
                          shrink_factor, transformation_epsilon, max_iterations, cell_capacity)
    T0 = _check_T(T_target_source_init, "T_target_source_init")
    s, sc, s_host = _prepare(source, source_count, "source")
    t, tc, t_host = _prepare(target, target_count, "target")
    kw = dict(max_iterations=int(max_iterations), cell_capacity=int(cell_capacity),
              coarse_matching=coarse_matching)
    if swap_larger and s_host is not None and t_host is not None and s_host > t_host:
        T0_inv = se3.inverse(T0) if _is_traced(T0) else np.linalg.inv(np.float64(T0)).astype(np.float32)
        r = icp_padded(t, tc, s, sc, T0_inv, dists, eps, min_inliers=min_inliers, **kw)
        return invert_result(r)
    return icp_padded(s, sc, t, tc, T0, dists, eps, min_inliers=min_inliers, **kw)


def default_hypotheses(T_target_source_init, center, yaw_step_rad: float = np.pi / 6,
                       roll_pitch_offset_rad: float = 0.1):
    """Initial guesses ``(k, 4, 4)``: ``T_init`` pre-multiplied by rotations about ``center``
    (a target-frame point [m], e.g. the centroid of the initially transformed source): every
    ``yaw_step_rad`` of yaw about +z (``2 pi / yaw_step`` guesses, the first being ``T_init``
    itself), plus ``+-roll_pitch_offset_rad`` of roll and of pitch at zero yaw (4 more; none if 0).
    """
    k = int(round(2 * np.pi / float(yaw_step_rad)))
    if k < 1:
        raise ValueError(f"yaw_step_rad must lie in (0, 2 pi], got {yaw_step_rad!r}")
    T0 = jnp.asarray(T_target_source_init, jnp.float32)
    c = jnp.asarray(center, jnp.float32)
    yaws = np.arange(k) * (2 * np.pi / k)
    rpy = [(0.0, 0.0, float(y)) for y in yaws]
    a = float(roll_pitch_offset_rad)
    if a != 0.0:
        rpy += [(a, 0.0, 0.0), (-a, 0.0, 0.0), (0.0, a, 0.0), (0.0, -a, 0.0)]
    rpy = np.asarray(rpy, np.float32)
    z = jnp.zeros((rpy.shape[0],), jnp.float32)
    D = se3.from_xyz_rpy(z, z, z, rpy[:, 0], rpy[:, 1], rpy[:, 2])
    C = se3.from_rotation_translation(jnp.eye(3, dtype=jnp.float32), c)
    return C @ D @ se3.inverse(C) @ T0


def sequential_default() -> bool:
    """Host: run hypotheses one after another on CPU backends, batched elsewhere."""
    return jax.default_backend() == "cpu"


@partial(jax.jit, static_argnames=("max_iterations", "cell_capacity", "table_sizes", "coarse_matching",
                                   "sequential"))
def _icp_multi_padded(source, source_count, target, target_count, hypotheses, dists, epsilon,
                      final_epsilon, min_inliers, basin_tolerance, *, max_iterations: int, cell_capacity: int,
                      table_sizes: tuple[int, ...], coarse_matching: str, sequential: bool = False):
    source, target, hyps_c, uncentre = _centered(source, source_count, target, target_count, hypotheses)
    grids = _build(target, target_count, dists, table_sizes, cell_capacity)
    run = partial(_icp_core, source, source_count, target, grids, dists=dists, epsilon=epsilon,
                  final_epsilon=final_epsilon, min_inliers=min_inliers, max_iterations=max_iterations,
                  coarse_matching=coarse_matching, two_phase=sequential)
    # sequential (lax.map): each hypothesis stops at its own convergence and skips work per
    # block; vmap runs every hypothesis until the slowest stops and computes both sides of every
    # data-dependent branch - on a GPU the batch runs in parallel, on a CPU it does not
    def each(f, *xs):
        return jax.lax.map(lambda a: f(*a), xs) if sequential else jax.vmap(f)(*xs)

    k = hyps_c.shape[0]
    # every stage for every hypothesis still running, but after each stage but the last one run
    # per basin: runs that left the stage within the stage's tolerance (``basin_tolerance`` [m]
    # scaled by the stage's correspondence distance over the floor's) of each other (every
    # source point displaced less) go on as one and share its result; one after another, a run
    # also stops as soon as it comes that close to where an earlier run left the stage
    radius = jnp.sqrt(jnp.max(jnp.where(jnp.arange(source.shape[0]) < source_count,
                                        jnp.sum(jax.lax.stop_gradient(source) ** 2, -1), 0.0)))
    owner = jnp.arange(k, dtype=jnp.int32)
    state = (hyps_c, jnp.zeros((k,), jnp.int32), jnp.zeros((k,), jnp.int32), jnp.zeros((k,), bool),
             jnp.full((k,), STATUS_MAX_ITERATIONS, jnp.int32))

    def through_stage(stop, carry):  # one loop for every coarse stage (one copy of the ICP loop to compile)
        state, owner = carry
        tol = basin_tolerance * dists[stop] / dists[-1]
        if sequential:
            def one(ends, x):  # ends: where the earlier runs left the stage, and which go on
                i, st = x[0], x[1:]
                T_ends, goes_on = ends
                near = lambda T: goes_on & (_displacements(T[None], T_ends, radius)[0] < tol)  # noqa: E731
                out = run(st[0], start=st, stop_stage=stop, stop_when=lambda T: jnp.any(near(T)))
                early = ~out[3] & (out[1] == stop) & (out[2] < max_iterations)
                lead = jnp.where(early, jnp.argmax(near(out[0])), i).astype(jnp.int32)
                go_on = ~out[3] & (out[2] < max_iterations) & ~early
                return (T_ends.at[i].set(out[0]), goes_on.at[i].set(go_on)), (out, lead)

            ends0 = (jnp.zeros_like(hyps_c), jnp.zeros((k,), bool))
            _, (state, lead) = jax.lax.scan(one, ends0, (jnp.arange(k, dtype=jnp.int32), *state))
        else:
            state = jax.vmap(lambda *st: run(st[0], start=st, stop_stage=stop))(*state)
            lead = jnp.arange(k, dtype=jnp.int32)
        early = lead != jnp.arange(k)
        basin = _basins(state[0], ~state[3] & (state[2] < max_iterations) & ~early, radius, tol)
        basin = jnp.where(early, basin[lead], basin)
        return (*state[:3], state[3] | (basin != jnp.arange(k)), state[4]), basin[owner]

    state, owner = jax.lax.fori_loop(0, dists.shape[0] - 1, through_stage, (state, owner))
    # a merged candidate takes its leader's result: skip its final report (two full-cloud queries)
    # where branches are real (sequential); under vmap the cond computes both sides anyway
    merged = owner != jnp.arange(k)
    # every run is past the coarse stages: only the last stage's loop is built
    final = partial(run, coarse=False)
    shapes = jax.eval_shape(lambda *st: final(st[0], start=st), *(x[0] for x in state))
    dummy = lambda: jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), shapes)  # noqa: E731
    cands = each(lambda m, *st: jax.lax.cond(m, dummy, lambda: final(st[0], start=st)), merged, *state)
    iterations_run = jnp.where(merged, state[2], cands.num_iterations).astype(jnp.int32)
    cands = jax.tree_util.tree_map(lambda a: a[owner] if a.ndim else a, cands)
    cands = _uncentre_result(cands, uncentre)
    # every field batched along k (a constant field comes out of vmap unbatched)
    cands = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (k,)) if a.ndim == 0 else a, cands)
    scores = cands.num_close.astype(jnp.float32) - cands.rmse / dists[-1]
    best = jnp.argmax(scores).astype(jnp.int32)
    best_res = jax.tree_util.tree_map(lambda a: a[best], cands)
    return IcpMultiResult(best_res, cands, best, scores, hypotheses, owner, iterations_run)


def _displacements(Ta, Tb, radius):
    """``(a, b)`` [m]: a bound on how far transforms ``Ta (a, 4, 4)`` and ``Tb (b, 4, 4)``
    place any point within ``radius`` [m] of the origin apart, ``angle(Ra^T Rb) * radius +
    |ta - tb|`` (no gradient)."""
    Ta, Tb = jax.lax.stop_gradient(Ta), jax.lax.stop_gradient(Tb)
    cos = (jnp.einsum("iab,jab->ij", Ta[:, :3, :3], Tb[:, :3, :3]) - 1.0) * 0.5
    angle = jnp.arccos(jnp.clip(cos, -1.0, 1.0))
    return angle * radius + jnp.linalg.norm(Ta[:, None, :3, 3] - Tb[None, :, :3, 3], axis=-1)


def _basins(T, running, radius, tolerance):
    """``(k,)`` int32: for each of ``k`` transforms ``T (k, 4, 4)`` (centred frames), the first
    running one whose displacement of points within ``radius`` [m] of the origin,
    ``angle(R_i^T R_j) * radius + |t_i - t_j|``, is below ``tolerance`` [m] among the basins'
    leaders (greedy in order, so every leader is a running transform and ``basin[j] == j``);
    itself for a stopped one."""
    close = _displacements(T, T, radius) < tolerance
    k = T.shape[0]

    def step(i, basin):
        lead = (basin == jnp.arange(k)) & running & (jnp.arange(k) < i)
        hit = close[i] & lead
        return basin.at[i].set(jnp.where(running[i] & jnp.any(hit), jnp.argmax(hit), i).astype(jnp.int32))

    return jax.lax.fori_loop(0, k, step, jnp.arange(k, dtype=jnp.int32))


def icp_multi(source, target, T_target_source_init, hypotheses=None, *, resolution: float,
              yaw_step_rad: float = np.pi / 6, roll_pitch_offset_rad: float = 0.1,
              max_correspondence_distance: float | None = None,
              min_correspondence_distance: float | None = None, shrink_factor: float = 0.5,
              transformation_epsilon: float | None = None, max_iterations: int = 100,
              cell_capacity: int = 8, min_inliers: int = 6, swap_larger: bool = True,
              coarse_matching: str = "centroid", source_count=None,
              target_count=None, sequential: bool | None = None,
              basin_tolerance: float | None = None) -> IcpMultiResult:
    """Multi-hypothesis ICP: ``icp`` from many initial guesses sharing one set of target
    grids, in one jitted call (see ``sequential``); returns the best by the number of source
    points within a quarter of the floor distance, ties broken by inlier rmse
    (``score = num_close - rmse / d_floor``), plus every candidate.

    ``hypotheses``: ``(k, 4, 4)`` absolute initial guesses ``T_target_source``; by default
    ``default_hypotheses(T_target_source_init, centroid of T_init * source, yaw_step_rad,
    roll_pitch_offset_rad)`` (12 yaws + 4 roll/pitch offsets = 16). Other arguments as ``icp``.

    ``basin_tolerance`` [m] at the floor distance, scaled with each stage's correspondence
    distance (``None``: a quarter of the floor distance, half a voxel at the defaults, so a
    quarter of every stage's distance; 0 turns merging off): after each stage but the last,
    hypotheses whose transforms displace every source point by less than the stage's
    tolerance from an earlier running hypothesis's (``angle * max source radius + translation
    difference``) are merged into it: only one of them runs on, and each reports that run's
    result (``basin``). Run one after another (``sequential``), a hypothesis also merges as
    soon as it comes that close to where an earlier one left the stage, before it ends the
    stage itself. Many of a yaw grid's hypotheses fall into a few basins on the coarsest stage
    (36 yaws from 1.7 rad at 0.2 m on the benchmark pair: 7 runs after it; merging at the
    stages' ends only left 10, 2.9 s against 2.0 s). The runs that go on take exactly the
    steps of uninterrupted ones.

    ``sequential``: run the hypotheses one after another (``lax.map``) instead of as one
    ``vmap`` batch; default: sequential on CPU backends (3x faster there: 12 hypotheses at
    0.2 m, 10.7 -> 3.5 s, as each stops at its own convergence), batched on accelerators.
    The two agree to float rounding on converged candidates (batched float arithmetic
    differs in the last bits, which can send a non-converging candidate elsewhere).
    """
    _check_choice(coarse_matching)
    dists, eps = _options(resolution, max_correspondence_distance, min_correspondence_distance,
                          shrink_factor, transformation_epsilon, max_iterations, cell_capacity)
    T0 = _check_T(T_target_source_init, "T_target_source_init")
    s, sc, s_host = _prepare(source, source_count, "source")
    t, tc, t_host = _prepare(target, target_count, "target")
    if hypotheses is None:
        valid = (jnp.arange(s.shape[0]) < sc)[:, None]
        centroid = jnp.sum(jnp.where(valid, s, 0.0), 0) / jnp.maximum(sc, 1).astype(jnp.float32)
        center = se3.transform_points(T0, centroid[None])[0]
        hyps = default_hypotheses(T0, center, yaw_step_rad, roll_pitch_offset_rad)
    else:
        hyps = jnp.asarray(hypotheses, jnp.float32)
        if hyps.ndim != 3 or hyps.shape[-2:] != (4, 4):
            raise ValueError(f"hypotheses: expected shape (k, 4, 4), got {hyps.shape}")
        if not _is_traced(hypotheses):
            se3.check_rigid(np.asarray(hypotheses), "hypotheses")
    swap = swap_larger and s_host is not None and t_host is not None and s_host > t_host
    if swap:
        s, sc, t, tc = t, tc, s, sc
        hyps = se3.inverse(hyps)
    tol = float(dists[-1]) / 4.0 if basin_tolerance is None else _number(basin_tolerance)
    if not (np.isfinite(tol) and tol >= 0):
        raise ValueError(f"basin_tolerance must be a finite number >= 0 [m], got {basin_tolerance!r}")
    out = _icp_multi_padded(s, sc, t, tc, hyps, dists, eps, eps * 0.01, jnp.asarray(min_inliers, jnp.int32),
                            jnp.float32(tol),
                            max_iterations=int(max_iterations), cell_capacity=int(cell_capacity),
                            table_sizes=neighbors.level_table_sizes(t.shape[0], np.asarray(dists)),
                            coarse_matching=coarse_matching,
                            sequential=sequential_default() if sequential is None else bool(sequential))
    if swap:
        out = IcpMultiResult(invert_result(out.best), invert_result(out.candidates), out.best_index,
                             out.scores, se3.inverse(out.hypotheses), out.basin, out.num_iterations_run)
    return out
