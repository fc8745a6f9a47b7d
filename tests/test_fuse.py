"""Tests of ``octomerge_jax.fusion`` against independent references: a brute-force NumPy
fusion over expanded voxels with its own maximal prune, OctoMap (pyoctomap) voxel updates,
and a greedy interval decomposition."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st


import octomerge_jax as om
from octomerge_jax import fusion as F
from octomerge_jax.fusion import _gaps, _many, _pair, _rules, _sizing
from octomerge_jax import map as omap
from octomerge_jax import morton, tree

RES = 0.1
PARAMS = omap.OccupancyParams()
LMIN = float(PARAMS.clamp_min_log_odds)
LMAX = float(PARAMS.clamp_max_log_odds)
U1 = np.uint64(1)


# ----------------------------------------------------------------------------- references


def span(depth):
    return U1 << (np.uint64(3) * (np.uint64(16) - np.asarray(depth).astype(np.uint64)))


def ref_expand(codes, depths, values):
    """Leaves -> (finest voxel codes, values), sorted."""
    n = span(depths).astype(np.int64)
    c = np.repeat(codes.astype(np.uint64), n)
    first = np.repeat(np.cumsum(n) - n, n)
    c = c + (np.arange(c.size) - first).astype(np.uint64)
    return c, np.repeat(np.asarray(values, np.float32), n)


def ref_prune(codes, depths, values):
    """Maximal prune (8 equal siblings -> parent, bottom-up, never into the root)."""
    codes = np.asarray(codes, np.uint64)
    depths = np.asarray(depths, np.int64)
    values = np.asarray(values, np.float32)
    for d in range(16, 1, -1):
        at = depths == d
        parent = codes[at] & ~(span(d - 1) - U1)
        vals = values[at]
        uniq, start, cnt = np.unique(parent, return_index=True, return_counts=True)
        # values equal within the group: min == max (np.unique sorts; groups are contiguous
        # because codes are sorted)
        vmin = np.minimum.reduceat(vals, start) if vals.size else vals
        vmax = np.maximum.reduceat(vals, start) if vals.size else vals
        ok = (cnt == 8) & (vmin == vmax)
        if not ok.any():
            continue
        collapse = np.isin(parent, uniq[ok])
        idx = np.flatnonzero(at)
        keep = np.ones(codes.size, bool)
        keep[idx[collapse]] = False
        new_codes = np.concatenate([codes[keep], uniq[ok]])
        new_depths = np.concatenate([depths[keep], np.full(int(ok.sum()), d - 1)])
        new_values = np.concatenate([values[keep], vmin[ok]])
        order = np.argsort(new_codes, kind="stable")
        codes, depths, values = new_codes[order], new_depths[order], new_values[order]
    return codes, depths.astype(np.int32), values


def ref_fuse(maps, rule="sum", weights=None, lmin=LMIN, lmax=LMAX):
    """Expand every map to depth 16, combine per voxel, clamp, prune maximally.
    ``sum`` folds map by map with a clamp after each map, as sequential ``fuse`` calls."""
    weights = [1.0] * len(maps) if weights is None else weights
    vox = [ref_expand(m.leaves().codes, m.leaves().depths, m.leaves().log_odds) for m in maps]
    allc = np.unique(np.concatenate([c for c, _ in vox]))
    acc = np.zeros(allc.size, np.float32)
    known = np.zeros(allc.size, bool)
    for k, (c, v) in enumerate(vox):
        pos = np.searchsorted(allc, c)
        has = np.zeros(allc.size, bool)
        has[pos] = True
        val = np.zeros(allc.size, np.float32)
        val[pos] = v
        if rule == "sum":
            new = np.where(known, acc + val, val)
            new = np.clip(new, np.float32(lmin), np.float32(lmax)) if k > 0 else new
        elif rule == "max":
            new = np.where(known, np.maximum(acc, val), val)
        else:
            w = np.float32(weights[k])
            new = np.where(known, acc + w * val, w * val)
        acc = np.where(has, new, np.clip(acc, lmin, lmax) if (rule == "sum" and k > 0) else acc)
        known |= has
    acc = np.clip(acc, np.float32(lmin), np.float32(lmax)).astype(np.float32)
    return ref_prune(allc, np.full(allc.size, 16), acc)


def greedy_cells(s, e):
    out = []
    while s < e:
        k = 16
        while k > 0 and (s % (8 ** k) or s + 8 ** k > e):
            k -= 1
        out.append((s, 16 - k))
        s += 8 ** k
    return out


# ----------------------------------------------------------------------------- generators

VALUES = np.array([-2.0, -1.2, -0.4, 0.0, 0.4, 0.85, 1.7, 3.5], np.float32)


def random_map(rng, roots, p_leaf=0.35, p_unknown=0.2, values=VALUES, min_depth=12,
               capacity=None):
    """A random map: under each root node (code, depth) recursively split / leaf / unknown,
    leaves at depths ``min_depth``..16; values from a small set so equal siblings occur."""
    codes, depths, vals = [], [], []

    def rec(code, d):
        r = rng.random()
        if d == 16 or (d >= min_depth and r < p_leaf):
            codes.append(code)
            depths.append(d)
            vals.append(values[rng.integers(values.size)])
            return
        if d >= min_depth and r < p_leaf + p_unknown:
            return
        step = int(span(d + 1))
        for c in range(8):
            rec(code + c * step, d + 1)

    for code, d in roots:
        rec(int(code), int(d))
    m = omap.from_leaves(np.array(codes, np.uint64), np.array(depths, np.int32),
                         np.array(vals, np.float32), RES, capacity=capacity)
    return m


def roots_near_origin(rng, n=2, depth=13):
    base = morton.keys_to_codes(np.array([32768, 32768, 32768], np.uint16))
    cell = int(span(depth))
    picks = rng.choice(16, size=n, replace=False)
    return [(int(base) + int(p) * cell, depth) for p in picks]


def assert_same_leaves(m, ref):
    lv = m.leaves()
    codes, depths, vals = ref
    assert lv.codes.size == codes.size, (lv.codes.size, codes.size)
    np.testing.assert_array_equal(lv.codes, codes)
    np.testing.assert_array_equal(lv.depths, depths)
    np.testing.assert_array_equal(lv.log_odds, vals)


CAP_IN, CAP_OUT = 2048, 4096  # fixed buckets: one compilation serves the property tests


def pair(seed, capacity=CAP_IN, **kw):
    """Two overlapping random maps: three depth-13 regions (one shared), plus a depth-12
    leaf of M1 with a random M2 subtree inside (thesis case 3 at depth 12)."""
    rng = np.random.default_rng(seed)
    roots = roots_near_origin(rng, n=3, depth=13)
    base = int(morton.keys_to_codes(np.array([32768] * 3, np.uint16)))
    coarse = base + 2 * int(span(12))
    m1 = random_map(rng, roots[:2], capacity=capacity, **kw)
    lv = m1.leaves()
    value = kw.get("values", VALUES)[rng.integers(len(kw.get("values", VALUES)))]
    m1 = omap.from_leaves(np.append(lv.codes, np.uint64(coarse)), np.append(lv.depths, 12),
                          np.append(lv.log_odds, np.float32(value)), RES, capacity=capacity)
    inner = (coarse + int(rng.integers(8)) * int(span(13)), 13)
    m2 = random_map(rng, roots[1:] + [inner], capacity=capacity, **kw)
    return m1, m2


# ----------------------------------------------------------------------------- tests


def test_gap_decomposition_matches_greedy():
    rng = np.random.default_rng(1)
    S, E = [0, 0, 8, 1, 7 * 8 ** 15], [1 << 48, 3 * 8 ** 15, 16, 8 ** 16, 1 << 48]
    for _ in range(400):
        a, b = sorted(int(x) for x in rng.integers(0, 1 << 48, 2))
        ka, kb = rng.integers(0, 17, 2)
        a, b = (a >> (3 * ka)) << (3 * ka), (b >> (3 * kb)) << (3 * kb)
        if a < b:
            S.append(a)
            E.append(b)
    s = morton.split_codes(np.array(S, np.uint64))
    e = morton.split_codes(np.array(E, np.uint64))
    total = np.asarray(jax.jit(lambda s, e: _gaps.gap_cell_count(s[:, 0], s[:, 1], e[:, 0], e[:, 1]))(s, e))
    want = [greedy_cells(a, b) for a, b in zip(S, E)]
    np.testing.assert_array_equal(total, [len(w) for w in want])
    # every cell of every interval, in one batch
    owner = np.repeat(np.arange(len(S)), total)
    t = np.arange(owner.size) - np.repeat(np.cumsum(total) - total, total)
    cell = jax.jit(lambda sh, sl, eh, el, t: _gaps.cell_code(sh, sl, eh, el, _gaps.gap_cell_info(sh, sl, eh, el, t)))
    h, lo, d = cell(jnp.asarray(s[owner, 0]), jnp.asarray(s[owner, 1]), jnp.asarray(e[owner, 0]),
                    jnp.asarray(e[owner, 1]), jnp.asarray(t, jnp.int32))
    got = list(zip(morton.join_codes(np.stack([h, lo], -1)).tolist(), np.asarray(d).tolist()))
    assert got == [c for w in want for c in w]


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), rule=st.sampled_from(F.RULES))
def test_fuse_matches_bruteforce(seed, rule):
    m1, m2 = pair(seed)
    # power-of-two weights: products are exact, so the result is bit-exact whether or not
    # the compiler fuses multiply-adds (other weights: see test_no_recompile_within_bucket)
    weights = (0.5, 2.0) if rule == "weighted" else (1.0, 1.0)
    out = F.fuse(m1, m2, rule, weights=weights, capacity=CAP_OUT)
    assert_same_leaves(out, ref_fuse([m1, m2], rule, weights))


GAP_CAP = 1024  # below CAP_OUT: the compact gap-cell list (one compilation for the examples)


@settings(max_examples=3, deadline=None)  # each example compiles its re-run's gap bucket
@given(seed=st.integers(0, 2 ** 32 - 1), rule=st.sampled_from(F.RULES))
def test_compact_gap_list_matches_bruteforce(seed, rule):
    # gap cells (parts of a split leaf the finer map does not know; most of these pairs have
    # some: a depth-12 leaf is split) laid out from a compact list instead of per output
    # slot: same leaves; a list too short on the host re-runs with room for all of them
    m1, m2 = pair(seed)
    weights = (0.5, 2.0) if rule == "weighted" else (1.0, 1.0)
    want = ref_fuse([m1, m2], rule, weights)
    out, rep = F.fuse_with_report(m1, m2, rule, weights=weights, capacity=CAP_OUT,
                                  gap_capacity=GAP_CAP)
    assert not bool(rep.overflow)
    assert_same_leaves(out, want)
    assert_same_leaves(F.fuse(m1, m2, rule, weights=weights, capacity=CAP_OUT, gap_capacity=1), want)
    # planned first, then laid out in the refinement's own bucket (the host path when the
    # cell count's bounds max(n1, n2) and n1 + n2 lie in different buckets); a list of
    # leaves with gaps too short is re-planned larger
    w1, w2 = (jnp.float32(w) for w in weights)
    for gap_capacity in (None, 1):
        out, rep = _pair.fuse_pair_planned(m1, m2, w1, w2, jnp.int32(_rules.MODE[rule]), True, gap_capacity,
                                           max(m1.num_leaves, m2.num_leaves))
        assert_same_leaves(out, want)
        assert not bool(rep.overflow) and rep.host() | {"capacity": 0} == F.fuse_with_report(
            m1, m2, rule, weights=weights, capacity=CAP_OUT)[1].host() | {"capacity": 0}
        assert out.capacity == omap.bucket_capacity(int(rep.refined_cells))


def test_fuse_same_depth_identical_leaves():
    m1, _ = pair(3)
    out = F.fuse(m1, m1, capacity=CAP_OUT)
    ref = ref_fuse([m1, m1])
    assert_same_leaves(out, ref)
    lv = m1.leaves()
    want = ref_prune(lv.codes, lv.depths, np.clip(lv.log_odds, LMIN, LMAX))
    assert_same_leaves(F.fuse(m1, m1, "max", capacity=CAP_OUT), want)


def test_report_counts_cases():
    # M1: one depth-13 leaf A, one depth-15 leaf B; M2: a voxel inside A (case 3), a depth-14
    # leaf containing B (case 4), a leaf equal to nothing (case 1) and a leaf equal to ... none
    base = int(morton.keys_to_codes(np.array([32768] * 3, np.uint16)))
    s13, s15 = int(span(13)), int(span(15))
    a, b = base, base + s13 + s15  # b inside the depth-14 cell base + s13
    m1 = omap.from_leaves(np.array([a, b], np.uint64), [13, 15], [0.4, -0.4], RES, capacity=CAP_IN)
    c2 = np.array([a + 5, base + s13, base + 2 * s13, base + 3 * s13], np.uint64)
    m2 = omap.from_leaves(c2, [16, 14, 14, 13], [0.85, 0.85, -0.4, 1.7], RES, capacity=CAP_IN)
    m3 = omap.from_leaves(np.array([base + 3 * s13], np.uint64), [13], [0.4], RES, capacity=CAP_IN)
    m1 = F.fuse(m1, m3, prune=False, capacity=CAP_OUT).with_capacity(CAP_IN)  # + an equal-depth leaf
    out, rep = F.fuse_with_report(m1, m2, capacity=CAP_OUT)
    assert_same_leaves(out, ref_fuse([m1, m2]))
    r = rep.host()
    assert r["leaves_in"] == [3, 4]
    assert r["same_depth"] == 1
    assert r["split"] == [1, 1]
    assert not r["overflow"]
    assert r["refined_cells"] == out.num_leaves + r["pruned"]


def test_refinement_cells_counts_on_the_host_what_plan_pair_counts():
    # by hand: a depth-13 leaf holding two voxels of one depth-15 node splits into the leaves
    # of a tree with internal nodes at depths 13, 14 and 15: 1 + 7 * 3 cells, 20 of them gap
    # cells; an equal leaf in both maps is one cell
    base = int(morton.keys_to_codes(np.array([32768] * 3, np.uint16)))
    a, e = base, base + int(span(13))
    m1 = omap.from_leaves(np.array([a, e], np.uint64), [13, 14], [0.4, -0.4], RES, capacity=CAP_IN)
    m2 = omap.from_leaves(np.array([a + 5, a + 6, e], np.uint64), [16, 16, 14], [0.85, 0.85, 0.4], RES,
                          capacity=CAP_IN)
    assert F.refinement_cells(m1, m2) == (23, 20) == F.refinement_cells(m2, m1)
    assert F.fuse(m1, m2, prune=False).num_leaves == 23
    # random pairs with splits at depths 12-16: what the device's first phase counts
    one = jnp.float32(1.0)
    for seed in range(6):
        m1, m2 = pair(seed)
        plan = _pair.plan_pair(m1, m2, one, one, jnp.int32(0), gap_rows=2 * CAP_IN)
        want = (int(plan.total), int(plan.gap_cells))
        assert F.refinement_cells(m1, m2) == want == F.refinement_cells(m2, m1), seed
    assert F.refinement_cells(m1, omap.empty(RES)) == (m1.num_leaves, 0)


def test_precompile_fuse_readies_the_program_fuse_lays_out_with():
    """``precompile_fuse`` (the command line's work ahead, beside a thread that fuses) compiles
    the second program a host ``fuse`` of the pair runs, so the fuse compiles none."""
    m1, m2 = pair(7, capacity=1 << 13)  # a capacity of this test's own: its programs are new
    before = _pair.emit_pair.programs()
    if not F.precompile_fuse(m1, m2, F.fuse_plan_shapes(m1, m2)):
        pytest.skip("no kernel store open (OCTOMERGE_TEST_CACHE_DIR=off)")
    ready = _pair.emit_pair.programs()
    assert ready == before + 1
    assert_same_leaves(F.fuse(m1, m2), ref_fuse([m1, m2]))
    assert _pair.emit_pair.programs() == ready


def test_short_list_of_leaves_with_gaps(monkeypatch):
    # the pair kernel lists the leaves with gaps in fewer rows than their gap cells (each has
    # at least one): a list too short for the leaves, while the cells fit, is an overflow
    # under jit and re-runs larger on the host
    m1, m2 = pair(3)
    want = ref_fuse([m1, m2], "sum", (1.0, 1.0))
    one, mode = jnp.float32(1), jnp.int32(0)
    _, short, (_, n_leaves) = _pair.pair_kernel(m1, m2, one, one, mode, CAP_OUT, True, gap_capacity=GAP_CAP,
                                                gap_leaves=1)
    assert bool(short.overflow) and int(n_leaves) > 1  # the count is exact, the list is not
    calls = []
    kernel = _pair.pair_kernel

    def spy(*args, **kw):
        calls.append(kw["gap_leaves"])
        return kernel(*args, **kw)

    monkeypatch.setattr(_sizing, "GAP_MIN", 1)
    monkeypatch.setattr(_sizing, "GAP_SHARE", CAP_OUT // GAP_CAP)  # the cell list as above
    monkeypatch.setattr(_sizing, "GAP_LEAF_SHARE", CAP_OUT)  # a 1-row default list
    monkeypatch.setattr(_pair, "pair_kernel", spy)
    out, rep = F.fuse_with_report(m1, m2, capacity=CAP_OUT)
    assert calls == [1, omap.bucket_capacity(int(n_leaves))] and not bool(rep.overflow)
    assert_same_leaves(out, want)
    # a gap list no shorter than the output is the per-slot layout: one run, nothing listed
    calls.clear()
    assert_same_leaves(F.fuse(m1, m2, capacity=CAP_OUT, gap_capacity=CAP_OUT), want)
    assert calls == [None]


def test_deep_split_is_local_and_reprunes():
    # a depth-2 leaf holding 8^14 voxels against 3 finest voxels inside it: the refinement has
    # a few hundred cells (never 8^14), and adding 0 log-odds prunes back to the one leaf.
    base = int(morton.keys_to_codes(np.array([32768] * 3, np.uint16)))
    m1 = omap.from_leaves(np.array([base], np.uint64), [2], [1.7], RES, capacity=CAP_IN)
    vox = np.array([base + 12345, base + 8 ** 10 + 7, base + 8 ** 14 - 1], np.uint64)
    zero = omap.from_leaves(vox, [16] * 3, [0.0] * 3, RES, capacity=CAP_IN)
    refined, rep = F.fuse_with_report(m1, zero, prune=False, capacity=CAP_OUT)
    n = refined.num_leaves
    assert n < 3 * 7 * 15
    # all but 3 cells are gap cells: a compact gap list too short for them re-runs with room
    # on the host, and reports overflow under jit
    for gap_capacity in (GAP_CAP, 8):
        again = F.fuse(m1, zero, prune=False, capacity=CAP_OUT, gap_capacity=gap_capacity)
        assert tree.equal(again, refined)
    _, short = jax.jit(lambda a, b: F.fuse_with_report(a, b, prune=False, capacity=CAP_OUT,
                                                       gap_capacity=8))(m1, zero)
    assert bool(short.overflow) and not bool(rep.overflow)
    lv = refined.leaves()
    assert int(np.sum(span(lv.depths).astype(np.float64))) == 8 ** 14
    assert np.all(lv.codes[1:] >= lv.codes[:-1] + span(lv.depths[:-1]))
    assert_same_leaves(F.fuse(m1, zero, capacity=CAP_OUT), (np.array([base], np.uint64), np.array([2]), np.float32([1.7])))
    # with a non-zero update the three voxels carry the sum; everything else keeps 1.7
    upd = omap.from_leaves(vox, [16] * 3, [0.4] * 3, RES, capacity=CAP_IN)
    out = F.fuse(m1, upd, capacity=CAP_OUT)
    lv = out.leaves()
    fin = lv.depths == 16
    np.testing.assert_array_equal(np.sort(lv.codes[fin & (lv.log_odds == np.float32(1.7) + np.float32(0.4))]), vox)
    assert int(np.sum(span(lv.depths).astype(np.float64))) == 8 ** 14
    assert not bool(rep.overflow)


def test_fuse_with_empty_is_identity_and_symmetry():
    m1, m2 = pair(7)
    e = omap.empty(RES)
    pruned = ref_prune(m1.leaves().codes, m1.leaves().depths,
                       np.clip(m1.leaves().log_odds, LMIN, LMAX))
    assert_same_leaves(F.fuse(m1, e.with_capacity(CAP_IN), capacity=CAP_OUT), pruned)
    assert_same_leaves(F.fuse(e.with_capacity(CAP_IN), m1, capacity=CAP_OUT), pruned)
    ab, ba = F.fuse(m1, m2, capacity=CAP_OUT), F.fuse(m2, m1, capacity=CAP_OUT)
    assert_same_leaves(ab, (ba.leaves().codes, ba.leaves().depths, ba.leaves().log_odds))


def test_clamping_bounds_hold():
    m1, m2 = pair(11, values=np.float32([-2.0, 3.5, 3.0, -1.9]))
    for a, b in ((m1, m2), (m1, m1)):
        lo = F.fuse(a, b, capacity=CAP_OUT).leaves().log_odds
        assert lo.min() >= np.float32(LMIN) and lo.max() <= np.float32(LMAX)
    # m1 + m1 doubles every value: 3.0 and 3.5 saturate at l_max, -2 and -1.9 at l_min
    assert set(lo.tolist()) == {np.float32(LMIN).item(), np.float32(LMAX).item()}


def test_padding_invariance():
    m1, m2 = pair(5)
    a = F.fuse(m1, m2, capacity=CAP_OUT)
    b = F.fuse(m1.with_capacity(4 * m1.capacity), m2.with_capacity(2 * m2.capacity))
    assert_same_leaves(b, (a.leaves().codes, a.leaves().depths, a.leaves().log_odds))
    c = F.fuse(m1, m2)  # host-planned capacity
    assert_same_leaves(c, (a.leaves().codes, a.leaves().depths, a.leaves().log_odds))
    # capacities that are not multiples of 32 (the gap flags are searched in 32-bit masks)
    d = F.fuse(m1.with_capacity(m1.num_leaves + 3), m2.with_capacity(m2.num_leaves + 17), capacity=CAP_OUT)
    assert_same_leaves(d, (a.leaves().codes, a.leaves().depths, a.leaves().log_odds))


def test_no_recompile_within_bucket():
    m1, m2 = pair(21)
    m3, m4 = pair(22)
    cap1, cap2 = max(m1.capacity, m3.capacity), max(m2.capacity, m4.capacity)
    m1, m3 = m1.with_capacity(cap1), m3.with_capacity(cap1)
    m2, m4 = m2.with_capacity(cap2), m4.with_capacity(cap2)
    F.fuse(m1, m2, capacity=4096, weights=(1.0, 0.5), rule="weighted")
    before = _pair.pair_kernel._cache_size()
    out = F.fuse(m3, m4, capacity=4096, weights=(0.3, 2.0), rule="weighted")
    assert _pair.pair_kernel._cache_size() == before
    codes, depths, vals = ref_fuse([m3, m4], "weighted", (0.3, 2.0))
    lv = out.leaves()
    np.testing.assert_array_equal(lv.codes, codes)
    np.testing.assert_array_equal(lv.depths, depths)
    np.testing.assert_allclose(lv.log_odds, vals, rtol=1e-6, atol=1e-6)  # FMA contraction


def test_overflow_is_reported_not_silent():
    m1, m2 = pair(9)
    out, rep = F.fuse_with_report(m1, m2, capacity=64)
    need = int(rep.refined_cells)
    assert need > 64 and bool(rep.overflow) and out.num_leaves <= 64
    with pytest.raises(ValueError, match="capacity 64"):
        F.fuse(m1, m2, capacity=64)


def test_resolution_mismatch_names_both():
    m1 = omap.empty(0.1)
    m2 = omap.empty(0.05)
    with pytest.raises(ValueError, match=r"m1.resolution = 0.1 m.*m2.resolution = 0.05 m"):
        F.fuse(m1, m2)
    with pytest.raises(ValueError, match="rule"):
        F.fuse(m1, m1, rule="mean")


def test_vmap_over_stacked_pairs():
    pairs = [pair(s) for s in (31, 32, 33)]
    cap1 = max(a.capacity for a, _ in pairs)
    cap2 = max(b.capacity for _, b in pairs)
    A = [a.with_capacity(cap1) for a, _ in pairs]
    B = [b.with_capacity(cap2) for _, b in pairs]
    stack = lambda ms: jax.tree.map(lambda *x: jnp.stack(x), *ms)  # noqa: E731
    out, rep = jax.vmap(lambda a, b: F.fuse_with_report(a, b, capacity=4096))(stack(A), stack(B))
    h = rep.host()  # per pair, as lists
    assert h["overflow"] == [False] * 3
    assert h["pruned"] == [r - o for r, o in zip(h["refined_cells"], h["leaves_out"])]
    for i, (a, b) in enumerate(zip(A, B)):
        mi = jax.tree.map(lambda x: x[i], out)
        assert not bool(rep.overflow[i])
        assert_same_leaves(mi, ref_fuse([a, b]))


def ref_split_counts(maps):
    """Per map, leaves strictly containing a leaf of another map (split by fusion), and the
    leaves held by two or more maps that no map splits (same depth, case 2)."""
    lvs = [(m.leaves().codes.astype(np.uint64), m.leaves().depths) for m in maps]
    split = []
    for k, (c, d) in enumerate(lvs):
        e = c + span(d)
        inner = np.zeros(c.size, bool)
        for j, (c2, d2) in enumerate(lvs):
            if j != k:
                for i in range(c.size):
                    inner[i] |= np.any((d2 > d[i]) & (c2 >= c[i]) & (c2 < e[i]))
        split.append(inner)
    whole = {}
    for (c, d), s in zip(lvs, split):
        for ci, di in zip(c[~s], d[~s]):
            whole[(int(ci), int(di))] = whole.get((int(ci), int(di)), 0) + 1
    return [int(s.sum()) for s in split], sum(v >= 2 for v in whole.values())


def many_kernel(maps, w, mode, capacity: int, do_prune: bool, gap_capacity: int | None = None):
    """The m-map kernel in one call at jit's default boundary lists (twice each map's
    capacity): ``(map, FuseReport, gap cells)``."""
    plan = _many.plan_many(maps, tuple(2 * mk.capacity for mk in maps))
    return _many.emit_many(plan, maps, w, mode, capacity, do_prune, gap_capacity)


def test_fuse_many_deep_nesting_equals_fold():
    """Five maps over the same region (chains of up to five nested leaves, a duplicated map,
    sums that hit the clamps mid-way): the one-pass kernel, with boundary lists sized on the
    host and at the jit default (2 x capacity), equals the fold and the reference."""
    rng = np.random.default_rng(3)
    roots = roots_near_origin(rng, n=2, depth=13)
    hot = np.float32([-2.0, 1.7, 3.5, 2.9])  # sums pass LMAX (3.48) and come back
    maps = [random_map(rng, roots, values=hot, min_depth=12 + k % 3, capacity=CAP_IN) for k in range(4)]
    maps.insert(2, maps[0])  # equal leaves in two maps
    fold = maps[0]
    for mk in maps[1:]:
        fold = F.fuse(fold, mk, capacity=CAP_OUT)
    want = (fold.leaves().codes, fold.leaves().depths, fold.leaves().log_odds)
    assert_same_leaves(fold, ref_fuse(maps))
    split, same = ref_split_counts(maps)
    sizes = [_sizing.list_size(int(n)) for n in np.asarray(_many.boundary_counts(tuple(maps)))]
    assert all(s < 2 * m.capacity for s, m in zip(sizes, maps))  # the host compacts the lists
    # the jit default lists (2 x capacity rows each, 20480 in all): the known intervals are
    # compacted into the CAP_OUT rows of the output; with 32768 rows they are not
    jit_default = [many_kernel(tuple(maps), jnp.ones(5, jnp.float32), jnp.int32(0), cap, True)[:2]
                   for cap in (CAP_OUT, 8 * CAP_OUT)]
    host = F.fuse_many_with_report(maps)  # counted first: laid out in its own bucket
    assert host[0].capacity == omap.bucket_capacity(int(host[1].refined_cells))
    for out, rep in [host] + jit_default:
        assert_same_leaves(out, want)
        h = rep.host()
        assert (h["split"], h["same_depth"]) == (split, same)
        assert not h["overflow"] and h["leaves_in"] == [m.num_leaves for m in maps]
    # more known intervals than output rows: an overflow, reported with a lower bound that
    # exceeds the capacity (the host re-runs larger), never a silent truncation
    _, short = F.fuse_many_with_report(maps, capacity=64)
    assert bool(short.overflow) and 64 < int(short.refined_cells) <= int(rep.refined_cells)
    with pytest.raises(ValueError, match="capacity 64"):
        F.fuse_many(maps, capacity=64)
    for rule, w in (("max", None), ("weighted", (0.5, 1.0, 2.0, 0.25, 1.5))):
        assert_same_leaves(F.fuse_many(maps, rule, weights=w), ref_fuse(maps, rule, w))


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1))
def test_fuse_many_pair_equals_fuse(seed):
    m1, m2 = pair(seed, values=np.float32([-2.0, 3.5, 1.7, -1.0, 0.4]))
    a, ra = F.fuse_with_report(m1, m2, capacity=CAP_OUT)
    # fuse_many takes the pair kernel for two maps; the m-map kernel must agree with it
    b, rb, _ = many_kernel((m1, m2), jnp.ones(2, jnp.float32), jnp.int32(0), CAP_OUT, True)
    assert_same_leaves(b, (a.leaves().codes, a.leaves().depths, a.leaves().log_odds))
    # with a compact gap list: one-cell intervals written as they are, the others decomposed
    c, rc, n_gap = many_kernel((m1, m2), jnp.ones(2, jnp.float32), jnp.int32(0), CAP_OUT, True,
                               gap_capacity=GAP_CAP)
    assert int(n_gap) <= GAP_CAP and not bool(rc.overflow)
    assert_same_leaves(c, (a.leaves().codes, a.leaves().depths, a.leaves().log_odds))
    assert_same_leaves(F.fuse_many([m1, m2], capacity=CAP_OUT),
                       (a.leaves().codes, a.leaves().depths, a.leaves().log_odds))
    ha, hb = ra.host(), rb.host()
    for key in ("leaves_in", "leaves_out", "same_depth", "split"):
        assert ha[key] == hb[key], key


def test_against_octomap_updates():
    pyoctomap = pytest.importorskip("pyoctomap")
    rng = np.random.default_rng(123)
    small = np.float32([-0.4, -0.2, 0.2, 0.4, 0.85])  # sums stay inside the clamps
    roots = roots_near_origin(rng, n=3, depth=14)
    m1 = random_map(rng, roots[:2], values=small, min_depth=14)
    m2 = random_map(rng, roots[1:], values=small, min_depth=14)
    ot = pyoctomap.OcTree(RES)
    for m in (m1, m2):
        c, v = ref_expand(m.leaves().codes, m.leaves().depths, m.leaves().log_odds)
        pts = morton.keys_to_coords(morton.codes_to_keys(c), RES)
        for p, val in zip(pts, v):
            ot.updateNode(np.asarray(p, np.float64), float(val))
    out = F.fuse(m1, m2)
    lv = out.leaves()
    got = {}
    for it in ot.begin_leafs():
        coord = np.asarray(it.getCoordinate(), np.float64)
        node = ot.search(coord)
        # leaf centres lie on the half-resolution grid
        got[(tuple(np.round(coord / (RES / 2)).astype(int)), int(it.getDepth()))] = np.float32(node.getLogOdds())
    assert len(got) == lv.codes.size
    for center, depth, val in zip(lv.centers, lv.depths, lv.log_odds):
        assert got[(tuple(np.round(center / (RES / 2)).astype(int)), int(depth))] == val


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1))
def test_one_pass_prune_equals_reference(seed):

    rng = np.random.default_rng(seed)
    roots = roots_near_origin(rng, n=3, depth=13)
    # few distinct values and mostly-split nodes: many complete equal sibling groups
    m = random_map(rng, roots, p_leaf=0.3, p_unknown=0.05, values=np.float32([0.4, -0.4]),
                   capacity=CAP_IN)
    got = tree.prune(m)
    lv = m.leaves()
    assert_same_leaves(got, ref_prune(lv.codes, lv.depths, lv.log_odds))


def test_scanned_octomap_trees_against_octomap_updates(tmp_path):
    """Two robots' maps built by OctoMap itself (pyoctomap ``insertPointCloud`` of simulated
    lab scans), written as ``.bt`` (map 1, maximum likelihood) and ``.ot`` (map 2, full
    log-odds), read back, map 2 resampled into map 1's frame: ``fuse`` equals OctoMap
    reading map 1 and applying each finest voxel of the resampled map 2 with
    ``updateNode(point, log_odds)`` (one update per voxel, so OctoMap clamps once, as
    ``fuse``), which prunes as it goes. Real tree layouts: pruned free space at several
    depths, split leaves on both sides, gaps."""
    pyoctomap = pytest.importorskip("pyoctomap")
    import octomerge_jax as om
    from octomerge_jax.sim import DepthCamera
    from octomerge_jax.sim.datasets import simulate_runs

    res = 0.1
    run1, run2, T_1_2 = simulate_runs("lab", sensor=DepthCamera(width=64, height=48), seed=2)
    paths = []
    for k, run in enumerate((run1, run2)):
        t = pyoctomap.OcTree(res)
        for pts, T in zip(run.scans, np.asarray(run.poses_map_sensor, np.float64)):
            cloud = np.asarray(pts, np.float64).reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]
            t.insertPointCloud(np.ascontiguousarray(cloud), np.ascontiguousarray(T[:3, 3]))
        paths.append(str(tmp_path / ("m1.bt" if k == 0 else "m2.ot")))
        (t.writeBinary if k == 0 else t.write)(paths[-1])
    m1 = om.load(paths[0])
    m2 = om.transform_map(om.load(paths[1]), T_1_2)
    out, rep = F.fuse_with_report(m1, m2)
    assert not bool(rep.overflow) and m1.num_leaves > 10000 and m2.num_leaves > 10000
    assert int(rep.split[0]) > 0 and int(rep.split[1]) > 0  # both maps have coarser leaves split

    ot = pyoctomap.OcTree(res)
    ot.readBinary(paths[0])
    lv = m2.leaves()
    for center, depth, val in zip(lv.centers, lv.depths, lv.log_odds):
        r = np.arange(1 << (16 - int(depth)))
        off = (np.stack(np.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3) - (r.size - 1) / 2) * res
        for p in off + center:
            ot.updateNode(np.asarray(p, np.float64), float(val))
    got = {}
    for it in ot.begin_leafs():
        coord = np.asarray(it.getCoordinate(), np.float64)
        got[(tuple(np.round(coord / (res / 2)).astype(int)), int(it.getDepth()))] = np.float32(
            ot.search(coord).getLogOdds())
    ours = out.leaves()
    assert len(got) == ours.codes.size
    for center, depth, val in zip(ours.centers, ours.depths, ours.log_odds):
        assert got[(tuple(np.round(center / (res / 2)).astype(int)), int(depth))] == val


def test_return_report_still_works_with_a_deprecation_warning():
    """``fuse(..., return_report=True)`` (earlier releases) returns ``fuse_with_report``'s
    ``FuseResult`` and warns; the plain call returns the map alone."""
    m1, m2 = pair(5)  # test_padding_invariance's pair: its programs
    with pytest.warns(DeprecationWarning, match="fuse_with_report"):
        merged, report = F.fuse(m1, m2, return_report=True)
    ref = F.fuse_with_report(m1, m2)
    assert tree.equal(merged, ref.map) and tree.equal(F.fuse(m1, m2), ref.map)
    assert report.host() == ref.report.host()
    with pytest.warns(DeprecationWarning, match="fuse_many_with_report"):
        many = F.fuse_many([m1, m2], return_report=True)
    assert isinstance(many, F.FuseResult) and tree.equal(many.map, ref.map)


# ----------------------------------------------------------------------------- every depth


def ref_fuse_cells(m1, m2, rule="sum", lmin=LMIN, lmax=LMAX):
    """Brute force for maps with coarse leaves: the common refinement of both maps' leaves
    (a node is split only where one map has finer leaves inside it), each cell combined and
    clamped, then pruned maximally. Leaves of any depth 0..16; no depth-16 expansion."""
    sides = []
    for m in (m1, m2):
        lv = m.leaves()
        sides.append((lv.codes.astype(np.uint64), lv.depths.astype(np.int64), lv.log_odds))
    out = []

    def covering(side, code, d):
        """The value of the leaf covering node (code, d), 'inside' if finer leaves lie
        within it, or None (unknown)."""
        codes, depths, vals = side
        i = int(np.searchsorted(codes, np.uint64(code), side="right")) - 1
        if i >= 0 and depths[i] <= d and code < int(codes[i]) + int(span(depths[i])):
            return vals[i]
        j = i + 1
        if j < codes.size and int(codes[j]) < code + int(span(d)):
            return "inside"
        return None

    def rec(code, d):
        a, b = covering(sides[0], code, d), covering(sides[1], code, d)
        if isinstance(a, str) or isinstance(b, str):
            for c in range(8):
                rec(code + c * int(span(d + 1)), d + 1)
            return
        if a is None and b is None:
            return
        if a is None or b is None:
            v = a if b is None else b
        else:
            v = a + b if rule == "sum" else max(a, b)
        out.append((code, d, np.clip(np.float32(v), np.float32(lmin), np.float32(lmax))))

    rec(0, 0)
    codes, depths, vals = (np.array(x) for x in zip(*out))
    return ref_prune(codes.astype(np.uint64), depths, vals.astype(np.float32))


def chain_map(rng, path_child, leaf_children, extra=()):
    """Leaves at every depth 1..16: at each depth, leaves at ``leaf_children`` of the node
    on the path, which continues into ``path_child``; at depth 16 the path node is a leaf
    too. ``extra``: more (code, depth) leaves."""
    codes, depths = [], []
    code = 0
    for d in range(1, 17):
        for c in leaf_children:
            codes.append(code + c * int(span(d)))
            depths.append(d)
        code += path_child * int(span(d))
    codes.append(code)
    depths.append(16)
    for c, d in extra:
        codes.append(c)
        depths.append(d)
    values = VALUES[rng.integers(VALUES.size, size=len(codes))]
    return omap.from_leaves(np.array(codes, np.uint64), np.array(depths), values, RES,
                            capacity=CAP_IN)


@pytest.mark.parametrize("rule", ["sum", "max"])
def test_fuse_with_leaves_at_every_depth(rule):
    """Coarse leaves of every size 1..16 in both maps, each map's coarse leaves holding the
    other's fine chain (thesis case 3 both ways), against the common-refinement reference."""
    rng = np.random.default_rng(8)
    m1 = chain_map(rng, path_child=7, leaf_children=(0, 3))  # depth-1 leaf 0 holds m2's chain
    m2 = chain_map(rng, path_child=0, leaf_children=(5, 6), extra=[(7 * int(span(1)) + 5 *
                   int(span(2)), 2)])  # depth-2 leaf inside m1's path, over m1's finer leaves
    assert sorted(set(m1.leaves().depths.tolist())) == list(range(1, 17))
    out = F.fuse(m1, m2, rule, capacity=CAP_OUT)
    assert_same_leaves(out, ref_fuse_cells(m1, m2, rule))
    # the same reference agrees with the voxel brute force where expansion is affordable
    small1, small2 = (omap.from_leaves(*(np.asarray(x)[m.leaves().depths >= 12] for x in (
        m.leaves().codes, m.leaves().depths, m.leaves().log_odds)), RES, capacity=CAP_IN)
        for m in (m1, m2))
    assert_same_leaves(F.fuse(small1, small2, rule, capacity=CAP_OUT),
                       ref_fuse([small1, small2], rule))
    assert_same_leaves(F.fuse(small1, small2, rule, capacity=CAP_OUT),
                       ref_fuse_cells(small1, small2, rule))
