"""Hashed-grid nearest neighbours against brute force; overflow is reported, never silent."""

import jax
import numpy as np
import pytest

from octomerge_jax.registration import neighbors as nb


def _brute(P, Q, chunk=512):
    """Exact nearest neighbours (float64 squared distances, first index on ties), in query
    chunks (one (q, n, 3) array would be gigabytes)."""
    P, Q = P.astype(np.float64), Q.astype(np.float64)
    d, i = [], []
    for s in range(0, len(Q), chunk):
        q = Q[s:s + chunk]
        D = (q[:, :1] - P[:, 0]) ** 2 + (q[:, 1:2] - P[:, 1]) ** 2 + (q[:, 2:] - P[:, 2]) ** 2
        d.append(D.min(1))
        i.append(D.argmin(1))
    return np.concatenate(d), np.concatenate(i)


@pytest.mark.parametrize("extent,table", [(4.0, 4096), (400.0, 256)])  # dense box / hashed
def test_nearest_is_exact_within_the_cell_size(extent, table):
    rng = np.random.default_rng(0)
    P = rng.uniform(-extent, extent, (3000, 3)).astype(np.float32)
    if extent > 10:  # clustered, so that cells stay below capacity
        P = (rng.integers(-4, 4, (3000, 1)) * 50 + rng.uniform(-2, 2, (3000, 3))).astype(np.float32)
    Q = (P[rng.integers(0, 2900, 1000)] + rng.normal(0, 0.3, (1000, 3))).astype(np.float32)
    h = 0.6
    g = nb.build_grid(P, 2900, h, table_size=table, cell_capacity=32)
    assert int(g.overflow[0]) == 0
    assert bool(g.dense[0]) == (extent < 10)
    d2, idx = nb.nearest(g, Q)
    bd, bi = _brute(P[:2900], Q)
    m = bd <= h * h
    assert m.mean() > 0.5
    np.testing.assert_array_equal(np.asarray(idx)[m], bi[m])
    np.testing.assert_allclose(np.asarray(d2)[m], bd[m], rtol=1e-5, atol=1e-9)
    assert np.all(np.asarray(idx) < 2900)  # padding rows are never returned
    within = np.asarray(nb.any_within(g, Q, 0.4))
    np.testing.assert_array_equal(within, bd <= 0.16)


def test_overflow_is_counted_and_empty_grid_finds_nothing():
    P = np.zeros((100, 3), np.float32) + 0.5  # one cell, 100 points
    g = nb.build_grid(P, 100, 1.0, table_size=256, cell_capacity=8)
    assert int(g.overflow[0]) == 92
    d2, idx = nb.nearest(g, np.array([[0.4, 0.5, 0.5]], np.float32))
    assert int(idx[0]) >= 0 and float(d2[0]) == pytest.approx(0.01, rel=1e-4)
    g0 = nb.build_grid(P, 0, 1.0, table_size=256, cell_capacity=8)
    d2, idx = nb.nearest(g0, np.array([[0.4, 0.5, 0.5], [np.nan, 0, 0]], np.float32))
    assert np.all(np.asarray(idx) == -1) and np.all(np.isinf(np.asarray(d2)))


def test_levels_and_chunked_queries():
    rng = np.random.default_rng(2)
    P = rng.uniform(0, 20, (5000, 3)).astype(np.float32)
    sizes = np.array([4.0, 1.0], np.float32)
    g = nb.build_grids(P, 5000, sizes, table_sizes=nb.level_table_sizes(5000, sizes), cell_capacity=64)
    Q = rng.uniform(0, 20, (4096, 3)).astype(np.float32)  # two 2048-query blocks
    bd, bi = _brute(P, Q)
    f = jax.jit(nb.nearest)
    for level, h in enumerate(sizes):
        assert int(g.overflow[level]) == 0
        d2, idx = f(g, Q, level)
        m = bd <= h * h
        np.testing.assert_array_equal(np.asarray(idx)[m], bi[m])
    with pytest.raises(ValueError, match="powers of two"):
        nb.build_grid(P, 10, 1.0, table_size=300)


def test_centroid_level_matches_voxel_grid_centroids():
    rng = np.random.default_rng(3)
    P = rng.uniform(0, 4, (2000, 3)).astype(np.float32)
    g = nb.build_grids(P, 2000, np.array([1.0], np.float32), table_sizes=(4096,), cell_capacity=8,
                       centroid_levels=(True,))
    assert int(g.overflow[0]) == 0
    sub = np.floor(P / 0.5).astype(np.int64)
    _, inv = np.unique(sub, axis=0, return_inverse=True)
    inv = inv.ravel()
    C = np.zeros((inv.max() + 1, 3))
    np.add.at(C, inv, P)
    C /= np.bincount(inv)[:, None]
    Q = rng.uniform(0, 4, (500, 3)).astype(np.float32)
    d2, idx, match = nb.nearest_with_points(g, Q)
    D = ((Q[:, None].astype(np.float64) - C[None]) ** 2).sum(-1)
    np.testing.assert_allclose(np.asarray(d2), D.min(1), rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(np.asarray(match), C[D.argmin(1)], atol=1e-5)


@pytest.mark.parametrize("dense", [True, False])
def test_two_phase_search_equals_the_27_cell_search(dense):
    """The 8-cell first phase + 27-cell re-search of the unsettled queries returns exactly what
    one 27-cell phase returns (same slot, distance and point, ties included) on a voxel lattice
    (surfaces: many equidistant candidates), with queries near it, far from it, on cell faces,
    non-finite, and padding rows past ``count``."""
    res = 0.05
    rng = np.random.default_rng(7)
    ij = rng.integers(0, 120, (6000, 2))
    wall = np.c_[ij[:, 0], np.zeros(6000, int) + 3, ij[:, 1] // 2]
    floor_ = np.c_[ij[:, 0], ij[:, 1], np.zeros(6000, int)]
    P = ((np.unique(np.r_[wall, floor_], axis=0) + 0.5) * res).astype(np.float32)
    if not dense:
        P = P + np.float32(300.0) * (rng.integers(0, 2, (len(P), 1)) - 0.5).astype(np.float32)
    n = len(P)
    h = np.float32(2 * res)
    g = nb.build_grids(P, n, np.array([h], np.float32), table_sizes=(1 << 17,) if dense else (1 << 15,),
                       cell_capacity=8)
    assert bool(g.dense[0]) == dense and int(g.overflow[0]) == 0
    q = 6 * 2048
    Q = P[rng.integers(0, n, q)] + rng.normal(0, 0.6 * res, (q, 3)).astype(np.float32)  # near
    Q[:2048] += rng.uniform(-1.0, 1.0, (2048, 3)).astype(np.float32)  # far from most points
    Q[2048:2560] = np.round(Q[2048:2560] / h) * h  # on cell faces / corners
    Q[2560:2600] = P[rng.integers(0, n, 40)]  # exactly on lattice points
    Q[2600, 1] = np.nan
    count = q - 3000  # the last block is padding, the one before partly
    one = jax.jit(lambda Q, c: nb.nearest_with_points(g, Q, 0, c, two_phase=False))(Q, count)
    two = jax.jit(lambda Q, c: nb.nearest_with_points(g, Q, 0, c, two_phase=True))(Q, count)
    for a, b in zip(one, two):
        np.testing.assert_array_equal(np.asarray(a)[:count], np.asarray(b)[:count])
    d2, idx = np.asarray(two[0])[:count], np.asarray(two[1])[:count]
    assert 0.2 < np.mean(d2 > h * h) < 0.6  # both phases were exercised
    bd, bi = _brute(P, Q[:count])
    m = bd <= h * h
    np.testing.assert_allclose(d2[m], bd[m], rtol=1e-5, atol=1e-9)
    assert idx[2600] == -1
