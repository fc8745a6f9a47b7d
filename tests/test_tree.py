import numpy as np
import pyoctomap
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import octomerge_jax as om
from octomerge_jax import morton, tree
from octomerge_jax.map import leaves_cache

RES = 0.1


def random_leaves(seed: int, n_cells: int = 12, values=(-2.0, -0.4, 0.85, 3.5)):
    """Random disjoint leaves at depths 12..16 under ``n_cells`` depth-12 cells near the origin;
    values come from a small set so that equal siblings (prunable groups) occur."""
    rng = np.random.default_rng(seed)
    cells = rng.choice(64, size=n_cells, replace=False)
    base = morton.keys_to_codes(np.array([[32768, 32768, 32768]], np.uint16))[0]
    codes, depths, lo = [], [], []

    def split(code, depth):
        if depth == 16 or rng.random() < 0.35:
            if rng.random() < 0.9:  # leave some holes (unknown space)
                codes.append(code)
                depths.append(depth)
                lo.append(rng.choice(values))
            return
        for c in range(8):
            split(code | (np.uint64(c) << np.uint64(3 * (16 - depth - 1))), depth + 1)

    for cell in cells:
        split(base + (np.uint64(cell) << np.uint64(12)), 12)
    return np.array(codes, np.uint64), np.array(depths), np.array(lo, np.float32)


def expanded_dict(m):
    """Brute-force reference: {finest code: log-odds} of every voxel the map knows."""
    L = m.leaves()
    out = {}
    for c, d in zip(L.codes, L.depths):
        span = 1 << (3 * (16 - int(d)))
        for k in range(span):
            out[int(c) + k] = None
    for c, d, v in zip(L.codes, L.depths, L.log_odds):
        for k in range(1 << (3 * (16 - int(d)))):
            out[int(c) + k] = float(v)
    return out


def assert_maximally_pruned(m):
    L = m.leaves()
    groups = {}
    for c, d, v in zip(L.codes, L.depths, L.log_odds):
        if d >= 2:
            groups.setdefault((int(c) >> (3 * (17 - int(d))), int(d)), []).append(float(v))
    for vals in groups.values():
        assert not (len(vals) == 8 and len(set(vals)) == 1)


def octomap_from_updates(points, occupied):
    ot = pyoctomap.OcTree(RES)
    for p, o in zip(points, occupied):
        ot.updateNode(p.astype(float), bool(o))
    return ot


def assert_same_as_octomap(m, ot):
    L = m.leaves()
    assert m.num_leaves == ot.getNumLeafNodes()
    assert tree.num_nodes(m) == ot.size()
    theirs = {}
    for it in ot.begin_leafs():
        theirs[tuple(np.round(np.asarray(it.getCoordinate(), np.float64), 5))] = it.getDepth()
    for c, d, v in zip(L.centers, L.depths, L.log_odds):
        key = tuple(np.round(c.astype(np.float32).astype(np.float64), 5))
        assert theirs.get(key) == d
        node = ot.search(c)
        assert node is not None and np.float32(node.getLogOdds()) == v


def test_update_points_matches_octomap_update_node_sequence():
    rng = np.random.default_rng(1)
    block = (np.stack(np.meshgrid(*[np.arange(4)] * 3, indexing="ij"), -1).reshape(-1, 3) + 0.5) * RES
    pts = np.concatenate([rng.uniform(-0.6, 0.6, (400, 3)), block, block, block + 1.0, block - 1.0])
    occ = rng.random(len(pts)) < 0.6
    occ[400:] = True
    occ[-64:] = False  # a free block prunes to a depth-14 leaf
    m = tree.update_points(om.empty(RES), pts, occ)
    ot = octomap_from_updates(pts, occ)
    assert_same_as_octomap(m, ot)
    # then update voxels inside pruned leaves (local expansion) and past the clamps
    more = np.concatenate([block[:5] + 1.0, block[:3] - 1.0, np.repeat(pts[:3], 8, axis=0)])
    more_occ = np.array([False] * 5 + [True] * 3 + [True] * 24)
    m2 = tree.update_points(m, more, more_occ)
    for p, o in zip(more, more_occ):
        ot.updateNode(p.astype(float), bool(o))
    assert_same_as_octomap(m2, ot)
    assert_maximally_pruned(m2)


def test_update_inside_a_coarse_leaf_expands_locally():
    code = morton.keys_to_codes(np.array([[32768, 32768, 32768]], np.uint16))
    m = om.from_leaves(code, [12], [-1.0], RES)
    voxel = morton.keys_to_coords(np.array([32770, 32769, 32771]), RES)
    out = tree.update_points(m, voxel, True)
    L = out.leaves()
    # one voxel at depth 16 and its 7 siblings at each of the depths 13..16
    assert out.num_leaves == 1 + 7 * 4
    assert np.bincount(L.depths, minlength=17)[12:].tolist() == [0, 7, 7, 7, 1 + 7]
    hit = L.log_odds[np.all(np.isclose(L.centers, voxel), axis=1)]
    assert hit.tolist() == [np.float32(np.float32(-1.0) + np.float32(om.map.logit(0.7)))]
    assert np.count_nonzero(L.log_odds == -1.0) == 28
    assert expanded_dict(out).keys() == expanded_dict(m).keys()


def test_voxel_updates_in_any_row_order_give_the_same_map():
    # sorted rows (as insert gives them) skip the sort; shuffled rows are sorted first
    rng = np.random.default_rng(3)
    m = tree.update_points(om.empty(RES), rng.uniform(-0.8, 0.8, (300, 3)), False)
    m = tree.update_points(m, (np.stack(np.meshgrid(*[np.arange(8)] * 3, indexing="ij"), -1)
                               .reshape(-1, 3) + 0.5) * RES, True)  # a coarse depth-13 leaf
    keys = np.unique(rng.integers(32760, 32776, (500, 3)), axis=0).astype(np.uint16)
    codes = np.sort(morton.keys_to_codes(keys))
    words = morton.split_codes(codes)
    deltas = np.where(rng.random(len(codes)) < 0.5, 0.85, -0.4).astype(np.float32)
    in_order = tree.apply_voxel_updates(m, words, deltas)
    perm = rng.permutation(len(codes))
    shuffled = tree.apply_voxel_updates(m, words[perm], deltas[perm])
    assert tree.equal(in_order, shuffled)
    assert in_order.num_leaves > m.num_leaves
    assert_maximally_pruned(in_order)


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 10_000))
def test_prune_expand_properties(seed):
    codes, depths, lo = random_leaves(seed, n_cells=3)
    m = om.from_leaves(codes, depths, lo, RES, capacity=8192)  # fixed buckets: compile once
    pruned = tree.prune(m)
    assert_maximally_pruned(pruned)
    assert expanded_dict(pruned) == expanded_dict(m)
    expanded = tree.expand(m, capacity=32768)
    assert set(np.asarray(expanded.depth[: expanded.num_leaves]).tolist()) <= {16}
    assert tree.equal(tree.prune(expanded), pruned)
    # padding never changes a result
    assert tree.equal(tree.prune(m.with_capacity(4 * m.capacity)), pruned)


def test_prune_never_creates_a_root_leaf_and_collapses_many_levels():
    m = tree.expand(om.from_leaves(np.array([0], np.uint64), [13], [0.5], RES))
    assert m.num_leaves == 512
    p = tree.prune(m)
    assert p.num_leaves == 1 and int(p.depth[0]) == 13
    whole = tree.expand(om.from_leaves(np.arange(8, dtype=np.uint64) << np.uint64(45), [1] * 8, [1.0] * 8, RES), 3)
    assert tree.prune(whole).num_leaves == 8


def test_lookup_finds_leaves_at_any_depth():
    codes, depths, lo = random_leaves(7)
    m = om.from_leaves(codes, depths, lo, RES)
    ref = expanded_dict(m)
    rng = np.random.default_rng(0)
    probe = rng.integers(32768, 32768 + 64, (2000, 3)).astype(np.uint16)
    pts = morton.keys_to_coords(probe, RES)
    got, known = tree.lookup(m, pts.astype(np.float32))
    want = [ref.get(int(c)) for c in morton.keys_to_codes(probe)]
    assert np.array_equal(np.asarray(known), [w is not None for w in want])
    assert np.array_equal(np.asarray(got)[np.asarray(known)], [w for w in want if w is not None])


def test_num_nodes_after_expand_matches_octomap_formula():
    codes, depths, lo = random_leaves(3)
    m = tree.prune(om.from_leaves(codes, depths, lo, RES))
    inner = tree.num_nodes(m) - m.num_leaves
    d = m.leaves().depths.astype(np.int64)
    formula = inner + int(np.sum((8 ** (17 - d) - 1) // 7))
    assert tree.num_nodes(tree.expand(m)) == formula


def test_from_voxels_sums_duplicates_and_clamps():
    pts = np.array([[0.05, 0.05, 0.05], [0.06, 0.01, 0.09], [1.0, 1.0, 1.0], [1.0, 1.0, 1.0]])
    m = tree.from_voxels(pts, [0.5, 0.25, 3.0, 3.0], RES)
    L = m.leaves()
    assert m.num_leaves == 2
    assert np.allclose(sorted(L.log_odds), [0.75, om.map.logit(0.971)])


def test_max_likelihood_and_clamp():
    m = om.from_leaves(np.array([0, 1, 2], np.uint64), [16] * 3, [-5.0, 0.0, 9.0], RES)
    ml = tree.to_max_likelihood(m).leaves().log_odds
    p = m.params
    assert ml.tolist() == [p.clamp_min_log_odds, p.clamp_max_log_odds, p.clamp_max_log_odds]
    assert tree.clamp(m).leaves().log_odds.tolist() == [p.clamp_min_log_odds, 0.0, p.clamp_max_log_odds]


def test_second_map_of_the_same_bucket_does_not_recompile():
    la, lb = random_leaves(1, n_cells=2), random_leaves(2, n_cells=2)
    cap = om.bucket_capacity(max(la[0].size, lb[0].size))
    a = om.from_leaves(*la, RES, capacity=cap)
    b = om.from_leaves(*lb, RES, capacity=cap)
    tree.prune(a)
    before = tree._prune._cache_size()
    tree.prune(b)
    assert tree._prune._cache_size() == before


def test_update_points_rejects_out_of_range_points():
    with pytest.raises(ValueError, match="outside the OctoMap key range"):
        tree.update_points(om.empty(RES), [[0.0, 0.0, 1e6]], True)


def test_leaves_cache_computes_each_maps_leaves_once_read_only():
    pts = np.array([[0.05, 0.05, 0.05], [0.15, 0.05, 0.05], [1.05, 0.05, 0.05]], np.float32)
    m = tree.from_voxels(pts, [0.5, 0.25, 3.0], RES)
    other = tree.from_voxels(pts[:2], [0.5, 0.25], RES)
    plain = m.leaves()
    assert plain.centers.flags.writeable and m.leaves() is not plain
    with leaves_cache():
        first = m.leaves()
        with leaves_cache():  # nested: the same cache
            assert m.leaves() is first
        assert not first.centers.flags.writeable and not first.log_odds.flags.writeable
        for a, b in zip(first, plain):
            np.testing.assert_array_equal(a, b)
        assert other.leaves() is not first and other.leaves().codes.shape == (2,)
    assert m.leaves() is not first and m.leaves().centers.flags.writeable


@pytest.mark.parametrize("shift", [2, 3])
def test_leaf_index_lookups_find_the_leaves_the_whole_search_finds(shift):
    """``leaf_index.lookup_keys``: leaves of depths 12-16 on both sides of the origin, keys in
    and around them, outside the box and outside the key range: the same rows and known flags
    as ``tree.lookup_words`` (a key outside the key range is unknown)."""
    import jax.numpy as jnp

    from octomerge_jax.leaf_index import key_box, leaf_index, lookup_keys

    rng = np.random.default_rng(shift)
    fine = np.unique(rng.integers(-20, 20, (3000, 3)), axis=0)
    coarse = np.array([[-64, -64, 0], [32, -32, -32], [-48, 16, -16]])  # depths 12, 13, 14 (16, 8, 4 voxels)
    sides = np.array([64, 32, 16])
    blocked = np.zeros(len(fine), bool)
    for c, w in zip(coarse, sides):
        blocked |= np.all((fine >= c) & (fine < c + w), axis=1)
    keys = np.concatenate([fine[~blocked], coarse]) + morton.KEY_OFFSET
    depths = np.concatenate([np.full((~blocked).sum(), 16), [12, 13, 14]])
    m = om.from_leaves(morton.keys_to_codes(keys.astype(np.uint64)), depths,
                       rng.normal(size=len(keys)).astype(np.float32), 0.1)
    index = leaf_index(m, shift=shift)
    assert index.shift == shift
    first, last = key_box(m)
    near = keys[rng.integers(0, len(keys), 15000)] + rng.integers(-2, 3, (15000, 3))
    inside_coarse = (coarse + morton.KEY_OFFSET)[rng.integers(0, 3, 3000)] + rng.integers(0, 16, (3000, 3))
    query = np.concatenate([rng.integers(first - 5, last + 6, (5000, 3)), near, inside_coarse,
                            [[-1, 0, 0], [70000, 32768, 32768], [32768, 32768, 65536]]]).astype(np.int32)
    row, known = lookup_keys(m, jnp.asarray(query), index)
    ref_row, ref_known = tree.lookup_words(m, morton.keys_to_words(jnp.clip(jnp.asarray(query), 0, 65535)))
    in_range = np.all((query >= 0) & (query < 65536), axis=1)
    ref_known = np.asarray(ref_known) & in_range
    np.testing.assert_array_equal(np.asarray(known), ref_known)
    np.testing.assert_array_equal(np.asarray(row)[ref_known], np.asarray(ref_row)[ref_known])
    assert 1500 < ref_known.sum() < len(query) - 1500
    assert set(np.asarray(m.depth)[np.asarray(row)[ref_known]]) >= {12, 13, 14, 16}
    with pytest.raises(ValueError, match="capacity 4 is smaller"):
        leaf_index(m, capacity=4, shift=shift)
    from octomerge_jax import budget

    with budget.memory_budget("64K"):  # building it would take over a quarter of the budget
        assert leaf_index(m, shift=shift) is None
    with pytest.raises(ValueError, match="outside the given box"):
        leaf_index(m, shift=shift, box=(first + 40, last))
