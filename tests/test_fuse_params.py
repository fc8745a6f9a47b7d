"""``om.fuse`` with non-default occupancy parameters (the first map's are kept and clamp the
result) and with leaves coarser than depth 12 (depth 8-11 free leaves around fine occupied
ones), against a brute-force NumPy fusion of the maps expanded to a common grid depth."""

from __future__ import annotations

import functools

import numpy as np
import pytest

import octomerge_jax as om

RES = 0.1
CAP = 4096  # input capacity: one bucket for every map here
OUT_CAP = 16384
P1 = om.OccupancyParams.from_probabilities(prob_hit=0.8, prob_miss=0.3, clamp_min=0.2, clamp_max=0.9,
                                           occupancy_threshold=0.6)
P0 = om.OccupancyParams()


def span(depth, grid=16):
    """Cells of depth ``grid`` in a node of ``depth`` (as a code step when ``grid`` = 16)."""
    return np.uint64(1) << np.uint64(3 * (grid - int(depth)))


@functools.lru_cache(maxsize=1)
def base_code():
    """Morton code of the voxel with keys (32768, 32768, 32768) (at the origin's positive
    corner): aligned at every depth >= 1."""
    m = om.update_points(om.empty(RES), np.array([0.05, 0.05, 0.05]), True)
    return np.uint64(m.leaves().codes[0])


def cells(m, grid):
    """The map's leaves as cells of depth ``grid``: (codes (n,) uint64 sorted, log-odds (n,))."""
    L = m.leaves()
    assert np.all(L.depths <= grid)
    n = np.left_shift(1, 3 * (grid - L.depths.astype(np.int64)))
    first = np.repeat(np.cumsum(n) - n, n)
    step = span(grid)
    c = np.repeat(L.codes.astype(np.uint64), n) + (np.arange(int(n.sum())) - first).astype(np.uint64) * step
    v = np.repeat(L.log_odds.astype(np.float32), n)
    order = np.argsort(c, kind="stable")
    return c[order], v[order]


def ref_fuse_sum(m1, m2, grid, params):
    """Per cell: the sum where both maps know it (float32), the one value where one does;
    then clamped to ``params``'s bounds."""
    c1, v1 = cells(m1, grid)
    c2, v2 = cells(m2, grid)
    c = np.union1d(c1, c2)
    k1, k2 = np.isin(c, c1), np.isin(c, c2)
    a = np.zeros(c.size, np.float32)
    b = np.zeros(c.size, np.float32)
    a[k1] = v1
    b[k2] = v2
    v = np.where(k1 & k2, a + b, np.where(k1, a, b)).astype(np.float32)
    lo, hi = np.float32(params.clamp_min_log_odds), np.float32(params.clamp_max_log_odds)
    return c, np.clip(v, lo, hi).astype(np.float32)


def assert_fused_as_reference(out, ref, grid):
    c, v = cells(out, grid)
    np.testing.assert_array_equal(c, ref[0])
    np.testing.assert_array_equal(v, ref[1])
    # maximally pruned: no 8 siblings of one value at one depth (never into depth 0)
    L = out.leaves()
    groups = {}
    for code, d, val in zip(L.codes, L.depths, L.log_odds):
        if d >= 2:
            groups.setdefault((int(code) >> (3 * (17 - int(d))), int(d)), []).append(float(val))
    assert not any(len(g) == 8 and len(set(g)) == 1 for g in groups.values())


def random_subtree(rng, code, depth, max_depth, values, p_leaf=0.4, p_unknown=0.2):
    """Leaves under node (code, depth) split at random down to ``max_depth``."""
    codes, depths, vals = [], [], []

    def rec(c, d):
        r = rng.random()
        if d == max_depth or (d > depth and r < p_leaf):
            codes.append(c)
            depths.append(d)
            vals.append(values[rng.integers(len(values))])
            return
        if d > depth and r < p_leaf + p_unknown:
            return
        for k in range(8):
            rec(c + k * int(span(d + 1)), d + 1)

    rec(int(code), depth)
    return codes, depths, vals


def make_map(parts, params=None):
    codes, depths, vals = (sum((list(p[i]) for p in parts), []) for i in range(3))
    return om.from_leaves(np.array(codes, np.uint64), np.array(depths, np.int32),
                          np.array(vals, np.float32), RES, params=params, capacity=CAP)


@pytest.mark.parametrize("seed", [0, 1])
def test_first_maps_params_are_kept_and_clamp(seed):
    rng = np.random.default_rng(seed)
    base = int(base_code())
    values = np.float32([-1.9, -1.0, -0.4, 0.3, 0.85, 1.7, 2.5, 3.4])  # sums pass P1's clamps
    roots = [base + k * int(span(13)) for k in rng.choice(8, 3, replace=False)]
    m1 = make_map([random_subtree(rng, r, 13, 16, values) for r in roots[:2]], params=P1)
    m2 = make_map([random_subtree(rng, r, 13, 16, values) for r in roots[1:]])
    out = om.fuse(m1, m2, capacity=OUT_CAP)
    for f in ("hit_log_odds", "miss_log_odds", "clamp_min_log_odds", "clamp_max_log_odds",
              "occupancy_threshold_log_odds"):
        assert np.float32(getattr(out.params, f)) == np.float32(getattr(P1, f)), f
    ref = ref_fuse_sum(m1, m2, 16, P1)
    assert_fused_as_reference(out, ref, 16)
    # the bounds bite: some cells sit at each of P1's clamps, where P0 would not have clamped
    assert np.any(ref[1] == np.float32(P1.clamp_max_log_odds))
    assert np.any(ref[1] == np.float32(P1.clamp_min_log_odds))
    # the other order keeps m2's (default) parameters and clamps with them
    back = om.fuse(m2, m1, capacity=OUT_CAP)
    assert np.float32(back.params.clamp_max_log_odds) == np.float32(P0.clamp_max_log_odds)
    ref_back = ref_fuse_sum(m2, m1, 16, P0)
    assert_fused_as_reference(back, ref_back, 16)
    assert not np.array_equal(ref[1], ref_back[1])
    # maximum likelihood uses the kept threshold (0.6): 0.3 is free under P1, occupied under P0
    ml = om.to_max_likelihood(out)
    Lo, Lm = out.leaves(), ml.leaves()
    np.testing.assert_array_equal(Lo.codes, Lm.codes)
    thr = np.float32(P1.occupancy_threshold_log_odds)
    occupied = Lm.log_odds == np.float32(P1.clamp_max_log_odds)
    np.testing.assert_array_equal(occupied, Lo.log_odds > thr)


FREE = np.float32([-2.0, -1.2, -0.4])
OCCUPIED = np.float32([0.85, 1.7, 3.5])


def coarse_pair(rng, coarse_depths, fine_depth, grid):
    """m_coarse: free leaves at ``coarse_depths`` tiling the children of a node one level
    above them (one child left unknown, some leaves missing); m_fine: occupied subtrees from
    ``fine_depth`` down to ``grid`` inside some coarse leaves, inside the unknown child and
    outside that node."""
    top = min(coarse_depths) - 1
    base = int(base_code())
    coarse = []
    for k in range(8):
        node = base + k * int(span(top + 1))
        d = coarse_depths[k % len(coarse_depths)]
        if k == 5:  # unknown in the coarse map
            continue
        for j in range(8 ** (d - top - 1)):
            if rng.random() < 0.8:
                coarse.append(([node + j * int(span(d))], [d], [FREE[rng.integers(3)]]))
    fine = []
    for k in [0, 1, 5] + [k for k in range(2, 8) if rng.random() < 0.4]:
        node = base + k * int(span(top + 1))
        j = int(rng.integers(8 ** (fine_depth - top - 1)))
        fine.append(random_subtree(rng, node + j * int(span(fine_depth)), fine_depth, grid, OCCUPIED))
    fine.append(random_subtree(rng, base + int(span(top)), fine_depth, grid, OCCUPIED))  # the next node
    return make_map(coarse), make_map(fine)


@pytest.mark.parametrize("coarse_depths, fine_depth, grid",
                         [((8, 9), 12, 14), ((10, 11), 13, 16)], ids=["depth8-9", "depth10-11"])
def test_coarse_free_leaves_against_fine_occupied(coarse_depths, fine_depth, grid):
    rng = np.random.default_rng(7 + grid)
    m_coarse, m_fine = coarse_pair(rng, coarse_depths, fine_depth, grid)
    depths = m_coarse.leaves().depths
    assert set(np.unique(depths).tolist()) == set(coarse_depths)
    for a, b in ((m_coarse, m_fine), (m_fine, m_coarse)):
        out = om.fuse(a, b, capacity=OUT_CAP)
        assert_fused_as_reference(out, ref_fuse_sum(a, b, grid, P0), grid)
        # the coarse leaves split locally: no output leaf is coarser than its input's
        assert out.leaves().depths.min() == min(coarse_depths)
    # and the max rule over the same split
    out = om.fuse(m_coarse, m_fine, "max", capacity=OUT_CAP)
    c1, v1 = cells(m_coarse, grid)
    c2, v2 = cells(m_fine, grid)
    c = np.union1d(c1, c2)
    a = np.full(c.size, -np.inf, np.float32)
    b = np.full(c.size, -np.inf, np.float32)
    a[np.isin(c, c1)] = v1
    b[np.isin(c, c2)] = v2
    assert_fused_as_reference(out, (c, np.maximum(a, b)), grid)
