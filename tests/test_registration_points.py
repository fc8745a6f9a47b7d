"""occupied_points (Alg. 1) against pyoctomap's leaf iterator and a brute-force expansion."""

import numpy as np
import pytest

from octomerge_jax import map as omap
from octomerge_jax import morton
from octomerge_jax.registration import occupied_points


def _brute(keys, depths, log_odds, res, thr):
    out = []
    for k, d, l in zip(keys.astype(np.int64), depths, log_odds):
        if l < thr:
            continue
        side = 1 << (16 - d)
        for dz in range(side):
            for dy in range(side):
                for dx in range(side):
                    out.append((k + [dx, dy, dz] - 32768 + 0.5) * res)
    return np.asarray(out).reshape(-1, 3)


def _random_map(rng, res=0.1):
    # leaves at depths 13..16 inside disjoint depth-13 blocks
    blocks = rng.choice(64, size=12, replace=False)
    codes, depths = [], []
    for b in blocks:
        base = np.uint64(b) << np.uint64(9)  # depth-13 node = 8^3 finest codes
        d = int(rng.integers(13, 17))
        step = np.uint64(1) << np.uint64(3 * (16 - d))
        n = 1 << (3 * (d - 13))
        for i in rng.choice(n, size=min(n, 3), replace=False):
            codes.append(base + np.uint64(i) * step)
            depths.append(d)
    codes = np.asarray(codes, np.uint64) + morton.keys_to_codes(np.array([32760, 32760, 32760], np.uint16))
    log_odds = rng.normal(size=len(codes)).astype(np.float32)
    return omap.from_leaves(codes, depths, log_odds, res)


@pytest.mark.parametrize("seed", range(3))
def test_coarse_leaves_expand_to_their_finest_voxels(seed):
    rng = np.random.default_rng(seed)
    m = _random_map(rng)
    lv = m.leaves()
    got = occupied_points(m)
    want = _brute(lv.keys, lv.depths, lv.log_odds, m.resolution, 0.0)
    assert got.shape == want.shape and got.dtype == np.float64
    key = lambda a: np.lexsort(np.round(a * 1000).T)
    np.testing.assert_allclose(got[key(got)], want[key(want)], atol=1e-9)
    # threshold and cap
    hi = occupied_points(m, min_log_odds=0.5)
    assert len(hi) == len(_brute(lv.keys, lv.depths, lv.log_odds, m.resolution, 0.5))
    one = occupied_points(m, max_points_per_leaf=1)
    occ = lv.log_odds >= 0
    np.testing.assert_allclose(np.sort(one, axis=0), np.sort(lv.centers[occ], axis=0), atol=1e-9)
    eight = occupied_points(m, max_points_per_leaf=10)
    assert len(eight) == int(np.sum(np.where(lv.depths[occ] < 16, 8, 1)))


def test_matches_pyoctomap_leaf_centres():
    pyoctomap = pytest.importorskip("pyoctomap")
    res = 0.1
    rng = np.random.default_rng(3)
    pts = rng.uniform(-1, 1, (300, 3))
    tree = pyoctomap.OcTree(res)
    for p in pts:
        tree.updateNode(p, True)
    cells = []
    for it in tree.begin_leafs():
        node = tree.search(it.getCoordinate())
        if node.getLogOdds() >= 0:
            cells.append(np.asarray(it.getCoordinate(), np.float64))
    want = np.asarray(cells)
    keys = morton.coords_to_keys(pts, res)
    codes = np.unique(morton.keys_to_codes(keys))
    m = omap.from_leaves(codes, np.full(len(codes), 16), np.full(len(codes), 0.85, np.float32), res)
    got = occupied_points(m)
    key = lambda a: np.lexsort(np.round(a / res * 2).T)
    np.testing.assert_allclose(got[key(got)], want[key(want)], atol=1e-6)


def test_empty_and_limit():
    assert occupied_points(omap.empty(0.1)).shape == (0, 3)
    root = omap.from_leaves(np.zeros(1, np.uint64), [0], [2.0], 0.1)
    with pytest.raises(ValueError, match="max_points_per_leaf"):
        occupied_points(root)
    assert occupied_points(root, max_points_per_leaf=64).shape == (64, 3)
    with pytest.raises(ValueError, match=">= 1"):
        occupied_points(root, max_points_per_leaf=0)
