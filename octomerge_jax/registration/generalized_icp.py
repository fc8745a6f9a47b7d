"""Generalized ICP on occupied voxel centres: the sub-voxel polish of the default refinement.

GICP (Segal, Haehnel and Thrun, "Generalized-ICP", RSS 2009) minimises, over ``T_1_2 = (R, t)``,

    E(T) = sum_j e_j^T (C1_n(j) + R C2_j R^T)^-1 e_j,    e_j = p1_n(j) - (R x_j + t),

over sample points ``x_j`` of map 2 matched to their nearest occupied voxel centre ``p1_n(j)``
of map 1 within ``max_correspondence_distance``: a plane-to-plane distance. Each covariance is
that of the occupied voxel centres within ``radius_voxels`` voxels of the point, looked up in
its own map (the 81 lattice offsets of a 2.5-voxel ball; a pruned occupied leaf counts as all
its voxels), with its eigenvalues replaced by ``(1e-3, 1, 1)``: a disc along the local surface,
the plane regularisation of fast_gicp / small_gicp. The lookups read a dense grid of occupied
flags over the box of the points (``VoxelGrid``, one gather each), or, for a box over
``MAX_GRID_VOXELS``, the map's leaves by Morton key (a binary search each). Each covariance is
computed once: the samples' before the iterations, a target's when a sample first matches it.
Gauss-Newton steps update ``T`` on the left (``exp(xi) T``) until the step falls below
``STEP_ROTATION_RAD`` and ``STEP_TRANSLATION_VOXELS``, or the energy has not reached a new low
for ``STALL_PATIENCE`` steps (then the lowest-energy iterate is returned).

Voxel centres quantise a surface to the lattice; a plane fitted to a surface's voxels
averages the quantisation out, which point-to-point ICP and the dense loss cannot
(``docs/design.md``, "GICP polishes the default refinement").
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import morton, se3, tree
from .._ops import bucket_capacity, count_true, nonzero_rows, to_device
from ..kernel_store import stored_jit
from ..budget import current_budget
from ..map import OccupancyMap
from . import neighbors
from ._icp import pad_points_host

__all__ = ["GICP_MIN_POINTS", "MAX_GRID_VOXELS", "GicpResult", "VoxelGrid", "gicp", "lattice_covariances",
           "ball_offsets", "precompile_gicp", "smallest_eigenvector", "voxel_grid"]

PLANE_EPSILON = 1e-3  # the regularised covariances' normal eigenvalue (in-plane ones are 1)
# a step below both ends the iteration (docs/design.md, "GICP polishes the default refinement")
STEP_ROTATION_RAD, STEP_TRANSLATION_VOXELS = 1e-4, 1e-2
STALL_PATIENCE = 3  # steps without a new lowest energy end a cycle of correspondence sets
GICP_MIN_POINTS = 6  # fewer points in either cloud is an error (a rigid pose needs 3; 6 for some redundancy)
#: a covariance box of more voxels than this is looked up in the map's leaves instead of a dense grid (32 MiB of flags)
MAX_GRID_VOXELS = 1 << 25


class GicpResult(NamedTuple):
    """``gicp``'s outcome (host values)."""

    T_1_2: np.ndarray  # (4, 4) float64, the result (map 2's frame into map 1's)
    num_iterations: int  # Gauss-Newton steps taken
    converged: bool  # within max_iterations the step fell below the thresholds or the energy stopped falling
    num_inliers: int  # samples matched within max_correspondence_distance at the result
    num_samples: int  # map 2's sample points
    rmse: float  # [m] root mean square point distance of the inliers at the result
    shift: float  # [m] mean displacement of the samples between the start and the result


def ball_offsets(radius_voxels: float) -> np.ndarray:
    """``(k, 3)`` int32 lattice offsets within ``radius_voxels`` of the origin (81 for 2.5)."""
    r = int(np.floor(radius_voxels))
    g = np.arange(-r, r + 1)
    o = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    return o[np.sum(o * o, axis=1) <= radius_voxels ** 2 + 1e-9].astype(np.int32)


class VoxelGrid(NamedTuple):
    """Occupied flags of a box of one map's finest voxels (``voxel_grid``; a pytree)."""

    flags: jax.Array  # (G,) uint8, 1 where the voxel is occupied; x fastest, then y, then z; padded with 0
    lo: jax.Array  # (3,) int32, the box's first voxel key (OctoMap key, KEY_OFFSET at the origin)
    dims: jax.Array  # (3,) int32, the box's voxels per axis


def _grid_box(points, resolution: float, reach_voxels: int) -> tuple[np.ndarray, np.ndarray]:
    """``(lo (3,), dims (3,))`` int64: the voxel keys of ``points (P, 3)`` [m] grown by
    ``reach_voxels`` per side, within the key range."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    if pts.shape[0] == 0:
        return np.zeros(3, np.int64), np.ones(3, np.int64)
    top = 2 * morton.KEY_OFFSET - 1
    base = np.floor(pts / float(resolution)).astype(np.int64) + morton.KEY_OFFSET
    lo = np.clip(base.min(axis=0) - int(reach_voxels), 0, top)
    hi = np.clip(base.max(axis=0) + int(reach_voxels), 0, top)
    return lo, hi - lo + 1


def voxel_grid(m: OccupancyMap, points, reach_voxels: int, capacity: int | None = None) -> VoxelGrid | None:
    """Host: ``m``'s occupied voxels (``log_odds >= `` its occupancy threshold; a pruned leaf
    counts as all its voxels) as flags over the box of the voxels of ``points (P, 3)`` [m]
    grown by ``reach_voxels`` per side. ``capacity``: the flags' length (at least the box's
    voxels; default ``bucket_capacity`` of them). ``None`` when the box holds more than
    ``MAX_GRID_VOXELS`` voxels (then look the map up by key)."""
    lo, dims = _grid_box(points, m.resolution, reach_voxels)
    cells = int(np.prod(dims))
    if cells > MAX_GRID_VOXELS:
        return None
    capacity = bucket_capacity(cells) if capacity is None else int(capacity)
    if capacity < cells:
        raise ValueError(f"voxel_grid: capacity {capacity} is smaller than the box's {cells} voxels")
    return _filled_grid(m, lo, dims, capacity)


def _filled_grid(m: OccupancyMap, lo, dims, capacity: int) -> VoxelGrid:
    """``voxel_grid`` of the box of ``dims (3,)`` voxels from key ``lo (3,)``."""
    hi = lo + dims - 1
    lv = m.leaves()
    occupied = lv.log_odds >= m.params.occupancy_threshold_host
    first = lv.keys[occupied].astype(np.int64)
    side = np.left_shift(np.int64(1), morton.TREE_DEPTH - lv.depths[occupied].astype(np.int64))
    a, b = np.maximum(first, lo), np.minimum(first + side[:, None], hi + 1)  # each leaf's part of the box
    inside = np.all(a < b, axis=1)
    a, extent = a[inside] - lo, (b - a)[inside]
    n = np.prod(extent, axis=1)  # voxels per leaf part; the leaves are disjoint, so at most ``cells`` in all
    i = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)  # voxel within its leaf part
    ex, ey = np.repeat(extent[:, 0], n), np.repeat(extent[:, 1], n)
    v = np.repeat(a, n, axis=0) + np.stack([i % ex, (i // ex) % ey, i // (ex * ey)], axis=1)
    flags = np.zeros(capacity, np.uint8)
    flags[v[:, 0] + dims[0] * (v[:, 1] + dims[1] * v[:, 2])] = 1
    return VoxelGrid(to_device(flags), to_device(lo, np.int32), to_device(dims, np.int32))


def _occupied_at(m: OccupancyMap, grid: VoxelGrid | None, keys, occupied_log_odds):
    """``keys (..., 3)`` int32 voxel keys are occupied voxels of ``m``: read in ``grid`` (keys
    outside its box are not), else looked up in ``m``'s leaves."""
    if grid is not None:
        rel = keys - grid.lo
        inside = jnp.all((rel >= 0) & (rel < grid.dims), axis=-1)
        flat = rel[..., 0] + grid.dims[0] * (rel[..., 1] + grid.dims[1] * rel[..., 2])
        return inside & (grid.flags[jnp.where(inside, flat, 0)] > 0)
    row, known = tree.lookup_keys(m, keys)
    return known & (m.log_odds[row] >= occupied_log_odds)


def lattice_covariances(m: OccupancyMap, points, occupied_log_odds, offsets, grid: VoxelGrid | None = None):
    """Plane-regularised covariances ``(P, 3, 3)`` float32 [unitless] of voxel centres ``points
    (P, 3)`` [m] of ``m``'s frame: the covariance of the occupied voxel centres of ``m`` at the
    lattice ``offsets (k, 3)`` around each point (``log_odds >= occupied_log_odds``), its
    eigenvalues set to ``(PLANE_EPSILON, 1, 1)``. A point with fewer than 3 occupied neighbours
    gets the identity. ``grid``: ``m``'s ``voxel_grid`` around the points, read instead of the
    leaves (the same flags where the box reaches ``max |offsets|`` voxels past every point)."""
    res = jnp.float32(m.resolution)
    base = jnp.round(points / res - 0.5).astype(jnp.int32)  # voxel index of each centre
    keys = base[:, None, :] + morton.KEY_OFFSET + jnp.asarray(offsets)[None]  # (P, k, 3)
    w = _occupied_at(m, grid, keys, occupied_log_odds).astype(jnp.float32)  # (P, k)
    o = jnp.asarray(offsets, jnp.float32)
    n = jnp.sum(w, axis=1)
    mean = (w @ o) / jnp.maximum(n, 1.0)[:, None]
    d = o[None] - mean[:, None, :]
    cov = jnp.einsum("pk,pki,pkj->pij", w, d, d) / jnp.maximum(n, 1.0)[:, None, None]
    normal = smallest_eigenvector(cov)
    C = jnp.eye(3, dtype=jnp.float32) - (1.0 - PLANE_EPSILON) * normal[:, :, None] * normal[:, None, :]
    return jnp.where((n >= 3)[:, None, None], C, jnp.eye(3, dtype=jnp.float32))


def _covariances_of_rows(m: OccupancyMap, grid, points, count, occupied_log_odds, offsets, block: int = 4096):
    """``lattice_covariances`` of the first ``count`` (traced) rows of ``points (P, 3)``, in blocks
    of ``block`` rows; blocks past ``count`` are skipped (identity)."""
    P = points.shape[0]
    if P <= block or P % block:
        return lattice_covariances(m, points, occupied_log_odds, offsets, grid)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=jnp.float32), (block, 3, 3))

    def one(args):
        i, rows = args
        return jax.lax.cond(i * block < count, lambda: lattice_covariances(m, rows, occupied_log_odds, offsets, grid),
                            lambda: eye)

    return jax.lax.map(one, (jnp.arange(P // block), points.reshape(-1, block, 3))).reshape(P, 3, 3)


def smallest_eigenvector(A):
    """Unit eigenvector ``(P, 3)`` of the smallest eigenvalue of symmetric ``A (P, 3, 3)``, in
    closed form (Smith 1961's eigenvalue, then the largest cross product of two rows of
    ``A - lambda I``): a batched ``eigh`` on XLA:CPU costs as much as the whole GICP step. Where
    that eigenvalue is repeated (a line, an isotropic blob) any unit vector orthogonal to the
    dominant row is returned."""
    q = jnp.trace(A, axis1=1, axis2=2) / 3.0
    off = A[:, 0, 1] ** 2 + A[:, 0, 2] ** 2 + A[:, 1, 2] ** 2
    diag = jnp.diagonal(A, axis1=1, axis2=2) - q[:, None]
    p = jnp.sqrt((jnp.sum(diag ** 2, axis=1) + 2.0 * off) / 6.0)
    eye = jnp.eye(3, dtype=A.dtype)
    B = (A - q[:, None, None] * eye) / jnp.maximum(p, 1e-12)[:, None, None]
    phi = jnp.arccos(jnp.clip(jnp.linalg.det(B) / 2.0, -1.0, 1.0)) / 3.0
    lam = q + 2.0 * p * jnp.cos(phi + 2.0 * jnp.pi / 3.0)  # the smallest eigenvalue
    M = A - lam[:, None, None] * eye
    c = jnp.stack([jnp.cross(M[:, 0], M[:, 1]), jnp.cross(M[:, 0], M[:, 2]), jnp.cross(M[:, 1], M[:, 2])], 1)
    norms = jnp.linalg.norm(c, axis=-1)  # (P, 3)
    best = jnp.take_along_axis(c, jnp.argmax(norms, axis=1)[:, None, None], axis=1)[:, 0]
    best_norm = jnp.max(norms, axis=1)
    # repeated smallest eigenvalue: a vector orthogonal to the dominant row of M
    row = jnp.take_along_axis(M, jnp.argmax(jnp.linalg.norm(M, axis=-1), axis=1)[:, None, None], axis=1)[:, 0]
    axis = jnp.where((jnp.abs(row[:, 0]) < 0.9 * jnp.linalg.norm(row, axis=-1))[:, None], eye[0], eye[1])
    ortho = jnp.cross(row, axis)
    ortho = jnp.where((jnp.linalg.norm(ortho, axis=-1) > 1e-12)[:, None], ortho, eye[2])
    scale = jnp.max(jnp.abs(M), axis=(1, 2))
    v = jnp.where((best_norm > 1e-6 * jnp.maximum(scale, 1e-12) ** 2)[:, None], best, ortho)
    return v / jnp.linalg.norm(v, axis=-1, keepdims=True)


def _settled(step, res):
    """The last step ``(rotation [rad], translation [m])`` is below both thresholds."""
    return (step[0] < STEP_ROTATION_RAD) & (step[1] < STEP_TRANSLATION_VOXELS * res)


class _State(NamedTuple):
    T: jax.Array  # (4, 4) float32, map 2's frame into map 1's centred frame
    k: jax.Array  # () int32 steps taken
    step: jax.Array  # (2,) float32 last step: rotation [rad], translation [m]
    best_T: jax.Array  # (4, 4) float32, the iterate of the lowest energy so far
    best_energy: jax.Array  # () float32, its mean GICP energy over the inliers
    stall: jax.Array  # () int32, steps since the energy last reached a new low
    C1: jax.Array  # (n_targets, 3, 3) float32, map 1's covariances of the targets matched so far
    have: jax.Array  # (n_targets,) bool, the targets whose covariance ``C1`` holds
    inliers: jax.Array  # () int32, at the returned transform (set by the last pass)
    rmse: jax.Array  # () float32 [m], at the returned transform (set by the last pass)
    done: jax.Array  # () bool, the last pass ran: ``T`` is the result


@stored_jit(static_argnames=("offsets", "max_iterations"))
def _solve(m1, m2, voxels, grid, targets, samples, count, T0, centre, thresholds, mcd, *, offsets, max_iterations):
    """Gauss-Newton on the GICP energy in map 1's frame centred at ``centre``: ``(T (4, 4)
    float32, steps, settled, inliers, rmse [m])``. ``targets``: the points ``grid`` holds
    (centred); a target's covariance is computed the first time a sample matches it and kept,
    the samples' once before the loop, both from ``voxels`` (the maps' ``VoxelGrid`` or ``None``
    each). Correspondence sets can cycle; then the iterate of the lowest energy is returned once
    it has not been beaten for ``STALL_PATIENCE`` steps."""
    off = np.asarray(offsets, np.int32)
    S, n_targets = samples.shape[0], targets.shape[0]
    valid = jnp.arange(S) < count
    C2 = _covariances_of_rows(m2, voxels[1], samples, count, thresholds[1], off)
    mcd2 = mcd * mcd
    res = jnp.float32(m1.resolution)

    def matches(T):
        y = samples @ T[:3, :3].T + T[:3, 3]
        d2, idx, p = neighbors.nearest_with_points(grid, y, count=count)
        inlier = valid & (idx >= 0) & (d2 <= mcd2)
        return y, d2, p, inlier, idx

    def target_covariances(s: _State, inlier, idx):
        """``s.C1, s.have`` with the covariances of the matched targets not computed yet."""
        need = inlier & ~s.have[jnp.maximum(idx, 0)]
        rows = nonzero_rows(need, S, S)
        new = idx.at[rows].get(mode="fill", fill_value=n_targets)  # n_targets: padding, dropped
        C = _covariances_of_rows(m1, voxels[0], targets.at[new].get(mode="fill", fill_value=0.0) + centre,
                                 count_true(need), thresholds[0], off)
        return s.C1.at[new].set(C, mode="drop"), s.have.at[new].set(True, mode="drop")

    def running(s: _State):
        return ((s.k < max_iterations) & ~_settled(s.step, res) & jnp.all(jnp.isfinite(s.step))
                & (s.stall < STALL_PATIENCE))

    def body(s: _State) -> _State:
        # one search per pass: a step from ``s.T`` while running, else the figures at the result (the
        # last iterate when it settled, else the one of the lowest energy) and the end; a second
        # search after the loop would compile the nearest-neighbour search twice
        go = running(s)
        T_at = jnp.where(go, s.T, jnp.where(_settled(s.step, res), s.T, s.best_T))
        y, d2, p, inlier, idx = matches(T_at)

        def step() -> _State:
            C1_all, have = target_covariances(s, inlier, idx)
            C1 = C1_all[jnp.maximum(idx, 0)]
            R = s.T[:3, :3]
            W = jnp.linalg.inv(C1 + jnp.einsum("ij,pjk,lk->pil", R, C2, R))
            W = jnp.where(inlier[:, None, None], W, 0.0)
            e = jnp.where(inlier[:, None], p - y, 0.0)
            J = jnp.concatenate([se3.skew(y), -jnp.broadcast_to(jnp.eye(3, dtype=jnp.float32), y.shape + (3,))],
                                -1)
            energy = jnp.einsum("pa,pab,pb->", e, W, e) / jnp.maximum(count_true(inlier), 1).astype(jnp.float32)
            better = energy < s.best_energy * (1.0 - 1e-4)
            H = jnp.einsum("pai,pab,pbj->ij", J, W, J)
            g = jnp.einsum("pai,pab,pb->i", J, W, e)
            dx = -jnp.linalg.solve(H + 1e-6 * jnp.trace(H) * jnp.eye(6, dtype=jnp.float32), g)
            dT = se3.from_rotation_translation(se3.so3_exp(dx[:3]), dx[3:])
            step = jnp.stack([jnp.linalg.norm(dx[:3]), jnp.linalg.norm(dx[3:])])
            return s._replace(T=dT @ s.T, k=s.k + 1, step=jnp.where(jnp.all(jnp.isfinite(dx)), step, jnp.inf),
                              best_T=jnp.where(better, s.T, s.best_T),
                              best_energy=jnp.where(better, energy, s.best_energy),
                              stall=jnp.where(better, 0, s.stall + 1), C1=C1_all, have=have)

        def finish() -> _State:
            n = count_true(inlier)
            rmse = jnp.sqrt(jnp.sum(jnp.where(inlier, d2, 0.0)) / jnp.maximum(n, 1).astype(jnp.float32))
            return s._replace(T=T_at, inliers=n, rmse=rmse, done=jnp.bool_(True))

        return jax.lax.cond(go, step, finish)

    start = _State(T0, jnp.int32(0), jnp.full((2,), 1e30, jnp.float32), T0, jnp.float32(jnp.inf), jnp.int32(0),
                   jnp.zeros((n_targets, 3, 3), jnp.float32), jnp.zeros((n_targets,), bool), jnp.int32(0),
                   jnp.float32(0.0), jnp.bool_(False))
    s = jax.lax.while_loop(lambda s: ~s.done, body, start)
    return s.T, s.k, _settled(s.step, res) | (s.stall >= STALL_PATIENCE), s.inliers, s.rmse


def _near_box(points, other, T_1_2, pad: float, inverse: bool) -> np.ndarray:
    """The rows of ``points`` inside the bounding box of ``other`` (``inverse``: ``points`` of map
    2 against map 1's ``other``; else ``points`` of map 1 against map 2's) under ``T_1_2``, grown
    by ``pad`` [m]; all of ``points`` when fewer than ``GICP_MIN_POINTS`` are inside."""
    R, t = T_1_2[:3, :3], T_1_2[:3, 3]
    q = points @ R.T + t if inverse else points
    o = other if inverse else other @ R.T + t
    inside = np.all((q >= o.min(axis=0) - pad) & (q <= o.max(axis=0) + pad), axis=1)
    return points[inside] if inside.sum() >= GICP_MIN_POINTS else points


class _Prepared(NamedTuple):
    """``gicp``'s host preparation (``_prepare``)."""

    T_init: np.ndarray  # (4, 4) float64 start
    centre: np.ndarray  # (3,) float64, map 1's frame origin of the solve
    sources: np.ndarray  # (s, 3) float64, map 2's samples
    targets: jax.Array  # (C1, 3) float32 map 1's points near the samples, centred, padded
    n_targets: jax.Array  # () int32 valid rows of ``targets``
    mcd: float  # [m] correspondence distance
    table_size: int  # the target grid's hash table size
    voxels: tuple  # (VoxelGrid, VoxelGrid) of map 1 and map 2 around their points (or their shapes), or (None, None)
    arguments: tuple  # ``_solve``'s dynamic arguments after ``grid`` and ``targets``
    offsets: tuple  # ``_solve``'s static lattice offsets


def _prepare(m1, m2, points_1, points_2, T_1_2_init, max_correspondence_distance, num_samples, radius_voxels,
             seed, shapes_only: bool = False) -> _Prepared:
    """Validate ``gicp``'s inputs and cut, sample, centre and pad the clouds (``gicp``'s Args);
    ``shapes_only``: the voxel grids as shapes (``_voxel_grids``)."""
    if abs(m1.resolution - m2.resolution) > 1e-9 * m1.resolution:
        raise ValueError(f"gicp: resolutions differ ({m1.resolution} vs {m2.resolution})")
    p1 = np.asarray(points_1, np.float64).reshape(-1, 3)
    p2 = np.asarray(points_2, np.float64).reshape(-1, 3)
    for name, p in (("points_1", p1), ("points_2", p2)):
        if p.shape[0] < GICP_MIN_POINTS:
            raise ValueError(f"gicp: {name} has {p.shape[0]} points, fewer than {GICP_MIN_POINTS}")
    T_init = np.asarray(T_1_2_init, np.float64)
    voxels = _voxel_grids(m1, m2, p1, p2, radius_voxels, shapes_only)
    # only points that can find a partner (the pose moves little): each cloud cut to the other's
    # bounding box under the start, grown by twice the correspondence distance
    pad = 2.0 * float(max_correspondence_distance) + 2.0 * m1.resolution
    p2 = _near_box(p2, p1, T_init, pad, inverse=True)
    if p2.shape[0] > num_samples:
        p2 = p2[np.sort(np.random.default_rng(seed).choice(p2.shape[0], num_samples, replace=False))]
    p1 = _near_box(p1, p2, T_init, pad, inverse=False)
    centre = p1.mean(axis=0)
    target, n1 = pad_points_host(p1 - centre, None, "points_1")
    samples, n2 = pad_points_host(p2, bucket_capacity(min(num_samples, p2.shape[0])), "points_2")
    T0 = T_init.copy()
    T0[:3, 3] -= centre
    thresholds = to_device([m.params.occupancy_threshold_host for m in (m1, m2)], np.float32)
    targets = to_device(target)
    arguments = (to_device(samples), to_device(n2, np.int32), to_device(T0, np.float32),
                 to_device(centre, np.float32), thresholds, to_device(max_correspondence_distance, np.float32))
    return _Prepared(T_init, centre, p2, targets, to_device(n1, np.int32), float(max_correspondence_distance),
                     neighbors.grid_table_size(target.shape[0], 4.0), voxels,
                     arguments, tuple(map(tuple, ball_offsets(radius_voxels).tolist())))


def _voxel_grids(m1, m2, p1, p2, radius_voxels, shapes_only: bool = False) -> tuple:
    """Both maps' ``voxel_grid`` around all of their points ``p1``, ``p2`` (the targets and samples
    whose covariances ``_solve`` computes are among them; a box that does not depend on the pose
    keeps one program per pair), of one capacity (one program for both), reaching a voxel past
    the lattice ball (float32 rounding of the points on the device); ``(None, None)`` when either
    box is over ``MAX_GRID_VOXELS`` or the grids would take over a quarter of the memory budget
    (``budget.current_budget``): they only save time. ``shapes_only``: their shapes and dtypes
    (``jax.ShapeDtypeStruct``), without reading the maps' leaves (``precompile_gicp``)."""
    reach = int(np.floor(radius_voxels)) + 1
    boxes = [_grid_box(p, m1.resolution, reach) for p in (p1, p2)]
    cells = max(int(np.prod(dims)) for _, dims in boxes)
    if cells > MAX_GRID_VOXELS or 2 * bucket_capacity(cells) > current_budget() // 4:
        return None, None
    if shapes_only:
        box = jax.ShapeDtypeStruct((3,), np.int32)
        return (VoxelGrid(jax.ShapeDtypeStruct((bucket_capacity(cells),), np.uint8), box, box),) * 2
    return tuple(_filled_grid(m, lo, dims, bucket_capacity(cells)) for m, (lo, dims) in zip((m1, m2), boxes))


def precompile_gicp(m1: OccupancyMap, m2: OccupancyMap, points_1, points_2, T_1_2_init, *,
                    max_correspondence_distance: float, num_samples: int = 16384, radius_voxels: float = 2.5,
                    max_iterations: int = 30, seed: int = 0) -> bool:
    """Make ready (``kernel_store.StoredJit.precompile``) the program ``gicp`` with these
    arguments runs, without running it; ``False`` when no kernel store is open. Raises as
    ``gicp``."""
    prep = _prepare(m1, m2, points_1, points_2, T_1_2_init, max_correspondence_distance, num_samples, radius_voxels,
                    seed, shapes_only=True)
    grid = jax.eval_shape(lambda t, n: neighbors.build_grid(t, n, prep.mcd, table_size=prep.table_size),
                          prep.targets, prep.n_targets)
    return _solve.precompile(m1, m2, prep.voxels, grid, prep.targets, *prep.arguments, offsets=prep.offsets,
                             max_iterations=int(max_iterations))


def gicp(m1: OccupancyMap, m2: OccupancyMap, points_1, points_2, T_1_2_init, *, max_correspondence_distance: float,
         num_samples: int = 16384, radius_voxels: float = 2.5, max_iterations: int = 30, seed: int = 0) -> GicpResult:
    """GICP of map 2 onto map 1 from ``T_1_2_init`` ``(4, 4)``.

    Args:
      m1, m2: the maps (``m1.resolution == m2.resolution``); their covariances are looked up in them.
      points_1: ``(n1, 3)`` [m] occupied voxel centres of map 1 (the targets: all of them; those
        beyond the samples' bounding box under the start, by twice the correspondence
        distance, are left out).
      points_2: ``(n2, 3)`` [m] occupied voxel centres of map 2 (all of them); an even random
        subset of at most ``num_samples`` (``seed``) of those inside map 1's grown bounding box
        under the start are the sources.
      max_correspondence_distance: [m] matches farther than this are left out (e.g. 2 voxels).
      radius_voxels: the lattice neighbourhood of the covariances [voxels].
    Returns a ``GicpResult``; ``converged`` is False when the steps neither settled nor cycled
    within ``max_iterations``, or went non-finite (then ``T_1_2`` is the start).
    Raises ``ValueError`` for a resolution mismatch or a cloud of fewer than ``GICP_MIN_POINTS``.
    """
    prep = _prepare(m1, m2, points_1, points_2, T_1_2_init, max_correspondence_distance, num_samples, radius_voxels,
                    seed)
    grid = neighbors.build_grid(prep.targets, prep.n_targets, prep.mcd, table_size=prep.table_size)
    T, k, settled, n_in, rmse = _solve(m1, m2, prep.voxels, grid, prep.targets, *prep.arguments,
                                       offsets=prep.offsets, max_iterations=int(max_iterations))
    T_init, centre, p2 = prep.T_init, prep.centre, prep.sources
    T = np.asarray(T, np.float64)
    finite = bool(np.all(np.isfinite(T)))
    if finite:
        T[:3, 3] += centre
        T = se3.project_to_rigid(T)
    else:
        T = T_init
    k = int(k)
    converged = finite and bool(settled)
    shift = float(np.mean(np.linalg.norm(p2 @ (T[:3, :3] - T_init[:3, :3]).T + (T[:3, 3] - T_init[:3, 3]), axis=1)))
    return GicpResult(T, k, bool(converged), int(n_in), int(p2.shape[0]), float(rmse), shift)
