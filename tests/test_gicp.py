"""``registration.gicp`` (module ``registration.generalized_icp``): the closed-form normals, the lattice
covariances and the solver against a brute-force NumPy GICP on the small room pair."""

from __future__ import annotations

import math

import numpy as np
import pytest

from octomerge_jax import kernel_store, morton, se3
from octomerge_jax import registration as reg
from octomerge_jax.map import from_leaves
from octomerge_jax import tree
from octomerge_jax.registration import generalized_icp
from octomerge_jax.registration.generalized_icp import (PLANE_EPSILON, ball_offsets, lattice_covariances,
                                                       smallest_eigenvector, voxel_grid)
from octomerge_jax.registration.generalized_icp import _solve as gicp_solve
from octomerge_jax.pipeline import transform_from_xyz_rpy
from octomerge_jax.sim import small_room_map, small_room_voxels

from helpers import own_kernel_store

RES = 0.1
T_TRUE = transform_from_xyz_rpy(0.35, -0.25, 0.0, 0.0, 0.0, math.pi / 4)


def test_smallest_eigenvector_matches_eigh():
    rng = np.random.default_rng(0)
    X = rng.normal(size=(500, 3, 3))
    A = X @ X.transpose(0, 2, 1)
    A[:3] = np.diag([1.0, 1.0, 0.0])  # a plane: a single smallest eigenvalue
    A[3:6] = np.diag([0.0, 2.0, 0.0])  # a line: the smallest one repeated
    A[6] = np.eye(3)
    A[7] = 0.0
    v = np.asarray(smallest_eigenvector(np.asarray(A, np.float32)), np.float64)
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0, atol=1e-5)
    w, U = np.linalg.eigh(A)
    residual = np.linalg.norm(np.einsum("pij,pj->pi", A, v) - w[:, :1] * v, axis=1)
    assert residual.max() < 1e-3 * max(1.0, np.abs(A).max()), residual.max()
    assert np.all(np.abs(np.sum(v[8:] * U[8:, :, 0], axis=1)) > 1 - 1e-4)  # the same direction
    np.testing.assert_allclose(np.abs(v[:3]), [[0, 0, 1]] * 3, atol=1e-6)
    assert np.all(np.abs(v[3:6, 1]) < 1e-6)  # orthogonal to the line's axis


def test_lattice_covariances_of_a_floor_are_discs():
    """A 9 x 9 floor of occupied voxels: interior voxels get a disc with its normal along z; an
    isolated voxel (fewer than 3 neighbours) gets the identity."""
    i = np.arange(9)
    floor = np.stack(np.meshgrid(i, i, [0], indexing="ij"), -1).reshape(-1, 3)
    keys = np.concatenate([floor, [[30, 30, 30]]]) + 32768
    m = from_leaves(morton.keys_to_codes(keys), np.full(len(keys), 16), np.full(len(keys), 2.0, np.float32), RES)
    centres = (np.array([[4, 4, 0], [30, 30, 30]]) + 0.5) * RES
    C = np.asarray(lattice_covariances(m, np.asarray(centres, np.float32), np.float32(0.0), ball_offsets(2.5)))
    np.testing.assert_allclose(C[0], np.diag([1.0, 1.0, PLANE_EPSILON]), atol=1e-5)
    np.testing.assert_allclose(C[1], np.eye(3), atol=0)
    assert len(ball_offsets(2.5)) == 81



def test_voxel_grid_flags_are_the_maps_occupied_voxels():
    """Finest leaves on both sides of the origin, a pruned occupied leaf of 4^3 voxels that the
    box cuts, a free one and one below the threshold: every voxel of the box is flagged exactly
    when the map's leaves say it is occupied, and the covariances read from the grid are the
    leaves'."""
    rng = np.random.default_rng(3)
    fine = np.unique(rng.integers(-6, 6, (400, 3)), axis=0)
    fine = fine[~np.all((fine >= 4) & (fine < 8), axis=1) & ~np.all(fine < -4, axis=1)]  # room for the pruned leaves
    keys = np.concatenate([fine, [[4, 4, 4], [-8, -8, -8], [8, -12, 0]]]) + 32768
    depths = np.concatenate([np.full(len(fine), 16), [14, 14, 14]])
    values = np.concatenate([rng.choice([-1.0, 0.1, 2.0], len(fine)), [2.0, -2.0, 1.5]]).astype(np.float32)
    m = from_leaves(morton.keys_to_codes(keys), depths, values, RES)
    points = (np.array([[0, 0, 0], [4, 4, 4], [-3, -3, -3]]) + 0.5) * RES  # the box: -5..6 per axis
    grid = voxel_grid(m, points, 2)
    lo, dims = np.asarray(grid.lo), np.asarray(grid.dims)
    np.testing.assert_array_equal(lo, [32768 - 5] * 3)
    np.testing.assert_array_equal(dims, [12, 12, 12])
    g = np.stack(np.meshgrid(*[np.arange(int(n)) for n in dims], indexing="ij"), -1).reshape(-1, 3) + lo
    log_odds, known = tree.lookup(m, (g - 32768 + 0.5) * RES)
    expected = np.asarray(known) & (np.asarray(log_odds) >= m.params.occupancy_threshold_host)
    flat = (g - lo) @ np.array([1, dims[0], dims[0] * dims[1]])
    flags = np.asarray(grid.flags)
    np.testing.assert_array_equal(flags[flat] > 0, expected)
    assert 100 < expected.sum() < expected.size and expected[np.all(g - 32768 == 6, axis=1)].all()  # the cut leaf
    assert flags.sum() == expected.sum()  # nothing flagged outside the box's rows
    offsets = ball_offsets(2.5)
    centres = np.asarray((fine[:40] + 0.5) * RES, np.float32)
    threshold = m.params.occupancy_threshold_host
    from_grid = lattice_covariances(m, centres, threshold, offsets, voxel_grid(m, centres, 3))
    by_key = lattice_covariances(m, centres, threshold, offsets)
    np.testing.assert_array_equal(np.asarray(from_grid), np.asarray(by_key))
    with pytest.raises(ValueError, match="capacity 8 is smaller"):
        voxel_grid(m, points, 2, capacity=8)


def test_gicp_reads_the_grid_as_the_leaves(room_pair, monkeypatch):
    """``gicp`` with its covariances read from the dense grids ends where it ends looking them up
    in the maps' leaves (a box over ``MAX_GRID_VOXELS``), to the bit."""
    m1, m2, p1, p2 = room_pair
    start = transform_from_xyz_rpy(0.04, -0.05, 0.0, 0.0, 0.0, 0.03) @ T_TRUE
    a = reg.gicp(m1, m2, p1, p2, start, max_correspondence_distance=2 * RES)
    from octomerge_jax import budget

    assert generalized_icp._prepare(m1, m2, p1, p2, start, 2 * RES, 16384, 2.5, 0).voxels[0] is not None
    with budget.memory_budget("256K"):  # grids over a quarter of the budget: the leaves instead
        assert generalized_icp._prepare(m1, m2, p1, p2, start, 2 * RES, 16384, 2.5, 0).voxels == (None, None)
    monkeypatch.setattr(generalized_icp, "MAX_GRID_VOXELS", 0)
    assert generalized_icp._prepare(m1, m2, p1, p2, start, 2 * RES, 16384, 2.5, 0).voxels == (None, None)
    b = reg.gicp(m1, m2, p1, p2, start, max_correspondence_distance=2 * RES)
    np.testing.assert_array_equal(a.T_1_2, b.T_1_2)
    assert (a.num_iterations, a.num_inliers, a.rmse) == (b.num_iterations, b.num_inliers, b.rmse)


def _numpy_gicp(m1, m2, p1, p2, T, mcd, iterations=40):
    """Brute-force GICP: covariances from the occupied voxel centres within 2.5 voxels (exact
    distances, float64), all-pairs nearest neighbours, Gauss-Newton on the left."""
    def covs(points, cloud):
        d2 = np.sum((points[:, None] - cloud[None]) ** 2, axis=-1)
        out = []
        for row in d2:
            nb = cloud[row <= (2.5 * RES) ** 2 + 1e-9]
            c = np.cov(nb.T, bias=True)
            _, U = np.linalg.eigh(c)
            out.append(U @ np.diag([PLANE_EPSILON, 1.0, 1.0]) @ U.T)
        return np.array(out)

    C1, C2 = covs(p1, p1), covs(p2, p2)
    for _ in range(iterations):
        R, t = T[:3, :3], T[:3, 3]
        y = p2 @ R.T + t
        d2 = np.sum((y[:, None] - p1[None]) ** 2, axis=-1)
        j = np.argmin(d2, axis=1)
        ok = d2[np.arange(len(y)), j] <= mcd ** 2
        y, e = y[ok], p1[j[ok]] - y[ok]
        W = np.linalg.inv(C1[j[ok]] + np.einsum("ij,njk,lk->nil", R, C2[ok], R))
        J = np.concatenate([se3.skew(y, xp=np), -np.broadcast_to(np.eye(3), y.shape + (3,))], -1)
        H = np.einsum("nai,nab,nbj->ij", J, W, J)
        g = np.einsum("nai,nab,nb->i", J, W, e)
        dx = -np.linalg.solve(H, g)
        dT = np.eye(4)
        dT[:3, :3] = se3.so3_exp(dx[:3], xp=np)
        dT[:3, 3] = dx[3:]
        T = dT @ T
        if np.linalg.norm(dx[:3]) < 1e-7 and np.linalg.norm(dx[3:]) < 1e-7:
            break
    return T


@pytest.fixture(scope="module")
def room_pair():
    voxels = small_room_voxels(RES)
    m1 = small_room_map((-1.0, 3.0), RES, None, voxels=voxels)
    m2 = small_room_map((0.8, 9.0), RES, T_TRUE, voxels=voxels)
    return m1, m2, reg.occupied_points(m1), reg.occupied_points(m2)


def test_gicp_matches_a_brute_force_reference(room_pair):
    """From a start 0.05 rad / 0.1 m off (0.074 m on average), ``gicp`` (all samples) ends where the float64
    brute-force GICP ends, and within a quarter voxel of the truth."""
    m1, m2, p1, p2 = room_pair
    start = transform_from_xyz_rpy(0.06, -0.08, 0.0, 0.0, 0.0, 0.05) @ T_TRUE
    r = reg.gicp(m1, m2, p1, p2, start, max_correspondence_distance=2 * RES, num_samples=1 << 16)
    assert r.converged and r.num_inliers > 1000
    ref = _numpy_gicp(m1, m2, p1, p2, start, 2 * RES)
    def dist(A, B):  # mean displacement of map 2's occupied voxels [m]
        return float(np.mean(np.linalg.norm(p2 @ (A[:3, :3] - B[:3, :3]).T + (A[:3, 3] - B[:3, 3]), axis=1)))

    assert dist(r.T_1_2, ref) < 0.05 * RES, dist(r.T_1_2, ref)
    assert dist(r.T_1_2, T_TRUE) < RES / 4 and dist(start, T_TRUE) > RES / 2
    assert 0.5 < r.shift / dist(r.T_1_2, start) < 1.5  # the samples' mean shift: the overlap's part of map 2


def test_gicp_input_errors(room_pair):
    m1, m2, p1, p2 = room_pair
    with pytest.raises(ValueError, match="points_2 has 3 points"):
        reg.gicp(m1, m2, p1, p2[:3], T_TRUE, max_correspondence_distance=0.2)
    coarse = small_room_map((-1.0, 3.0), 0.2)
    with pytest.raises(ValueError, match="resolutions differ"):
        reg.gicp(coarse, m2, p1, p2, T_TRUE, max_correspondence_distance=0.2)


def test_precompile_readies_the_program_gicp_runs(room_pair, tmp_path):
    """``precompile_gicp`` (the command line's work ahead) compiles the very program ``gicp`` then runs:
    the call compiles nothing more."""
    m1, m2, p1, p2 = room_pair
    start = transform_from_xyz_rpy(0.02, -0.03, 0.0, 0.0, 0.0, 0.01) @ T_TRUE
    heard = []
    with own_kernel_store(tmp_path / "kernels", [gicp_solve]), kernel_store.compile_listener(heard.append):
        assert reg.precompile_gicp(m1, m2, p1, p2, start, max_correspondence_distance=2 * RES, max_iterations=17)
        assert heard == ["octomerge_jax.registration.generalized_icp._solve"]
        r = reg.gicp(m1, m2, p1, p2, start, max_correspondence_distance=2 * RES, max_iterations=17)
    assert len(heard) == 1 and r.converged
