import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from octomerge_jax import morton

keys_strategy = arrays(np.uint16, st.tuples(st.integers(1, 64), st.just(3)))


@settings(max_examples=30, deadline=None)
@given(keys_strategy)
def test_code_round_trips_host_and_device(keys):
    codes = morton.keys_to_codes(keys)
    assert np.array_equal(morton.codes_to_keys(codes), keys)
    words = morton.split_codes(codes)
    assert np.array_equal(morton.join_codes(words), codes)
    # on the device padded to the strategy's 64 rows: one compiled program for every example
    n = keys.shape[0]
    padded = np.zeros((64, 3), np.int32)
    padded[:n] = keys
    device_words = np.asarray(_keys_to_words(jnp.asarray(padded)))[:n]
    assert np.array_equal(device_words, words)
    padded_words = np.zeros((64, 2), np.int32)
    padded_words[:n] = words
    assert np.array_equal(np.asarray(_words_to_keys(jnp.asarray(padded_words)))[:n], keys)


_keys_to_words, _words_to_keys = jax.jit(morton.keys_to_words), jax.jit(morton.words_to_keys)


def test_interleave_puts_x_in_the_lowest_bit_like_octomap_child_index():
    keys = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [0x8000, 0, 0]], np.uint16)
    assert morton.keys_to_codes(keys).tolist() == [1, 2, 4, 1 << 45]


def test_searchsorted_words_matches_numpy():
    rng = np.random.default_rng(0)
    codes = np.sort(rng.integers(0, 1 << 48, 500).astype(np.uint64))
    queries = np.concatenate([codes[::5], rng.integers(0, 1 << 48, 100).astype(np.uint64)])
    words = jnp.asarray(morton.split_codes(codes))
    q = jnp.asarray(morton.split_codes(queries))
    for side in ("left", "right"):
        got = np.asarray(morton.searchsorted_words(words, q, side=side))
        assert np.array_equal(got, np.searchsorted(codes, queries, side=side))


@pytest.mark.parametrize("depth", range(17))
def test_truncate_and_child_index(depth):
    rng = np.random.default_rng(depth)
    codes = rng.integers(0, 1 << 48, 200).astype(np.uint64)
    w = jnp.asarray(morton.split_codes(codes))
    shift = np.uint64(3 * (16 - depth))
    assert np.array_equal(morton.join_codes(np.asarray(morton.truncate_words(w, depth))),
                          (codes >> shift) << shift)
    if depth > 0:
        assert np.array_equal(np.asarray(morton.child_index_words(w, depth)), (codes >> shift) & np.uint64(7))


@pytest.mark.parametrize("shift", [0, 3, 21, 24, 27, 45])
def test_or_offset_words(shift):
    k = np.random.default_rng(shift).integers(0, 1 << min(48 - shift, 30), 100)
    got = morton.or_offset_words(jnp.zeros((100, 2), jnp.int32), jnp.asarray(k.astype(np.int32)), shift)
    assert np.array_equal(morton.join_codes(np.asarray(got)), k.astype(np.uint64) << np.uint64(shift))


def test_keys_follow_octomap_coord_to_key_and_key_to_coord():
    res = 0.05
    keys = morton.coords_to_keys([[0.0, -0.05, 1.0], [-1e-9, 0.049999, 1638.39]], res)
    assert keys.tolist() == [[32768, 32767, 32788], [32767, 32768, 65535]]
    # centre of a finest key and of its depth-14 ancestor (OctoMap keyToCoord(key, depth))
    assert np.allclose(morton.keys_to_coords(keys[0], res), [0.025, -0.025, 1.025])
    assert np.allclose(morton.keys_to_coords(keys[0], res, 14), [0.1, -0.1, 1.1])
    assert np.allclose(morton.keys_to_coords(keys[0], res, 0), 0.0)


@pytest.mark.parametrize("bad", [1638.4, -1638.41, np.nan, np.inf])
def test_out_of_range_coordinate_names_the_value(bad):
    with pytest.raises(ValueError, match="outside the OctoMap key range"):
        morton.coords_to_keys([[0.0, 0.0, 0.0], [0.0, bad, 0.0]], 0.05)
    _, ok = morton.points_to_keys(jnp.array([[0.0, bad, 0.0]], jnp.float32), 0.05)
    assert not bool(ok[0])


def _sorted_records(rng, n, n_valid, span):
    """``n`` rows sorted by (hi, lo) with duplicates; rows past ``n_valid`` are padding."""
    hi = np.sort(rng.integers(0, span, n_valid)).astype(np.int32)
    lo = rng.integers(0, 3, n_valid).astype(np.int32)
    order = np.lexsort((lo, hi))
    hi, lo = hi[order], lo[order]
    pad = n - n_valid
    hi = np.concatenate([hi, np.full(pad, morton.SENTINEL_HI, np.int32)])
    lo = np.concatenate([lo, np.zeros(pad, np.int32)])
    return hi, lo


@pytest.mark.parametrize("ca,cb", [(1, 1), (5, 300), (300, 5), (128, 128), (129, 383), (1000, 1000)])
def test_merge_sorted_and_ranks_match_a_stable_sort(ca, cb):
    rng = np.random.default_rng(ca * 7919 + cb)
    span = max(2, (ca + cb) // 4)  # many ties within and across the lists
    ah, al = _sorted_records(rng, ca, max(ca - 3, 1), span)
    bh, bl = _sorted_records(rng, cb, max(cb - 2, 1), span)
    a = (ah, al, np.arange(ca, dtype=np.int32))  # payload: source row (a >= 0, b < 0)
    b = (bh, bl, ~np.arange(cb, dtype=np.int32))
    got = [np.asarray(x) for x in morton.merge_sorted(tuple(map(jnp.asarray, a)),
                                                      tuple(map(jnp.asarray, b)))]
    hi, lo, src = (np.concatenate([x, y]) for x, y in zip(a, b))
    order = np.lexsort((np.arange(ca + cb), lo, hi))  # stable: ties keep a first, then order
    for g, want in zip(got, (hi[order], lo[order], src[order])):
        np.testing.assert_array_equal(g, want)
    key = lambda h, l: h.astype(np.int64) << 24 | l  # noqa: E731
    lt_a, le_b = (np.asarray(x) for x in morton.merge_ranks(*map(jnp.asarray, (ah, al, bh, bl))))
    kb = np.sort(key(bh, bl))
    ka = np.sort(key(ah, al))
    np.testing.assert_array_equal(lt_a, np.searchsorted(kb, key(ah, al), side="left"))
    np.testing.assert_array_equal(le_b, np.searchsorted(ka, key(bh, bl), side="right"))
    # with the valid counts only those rows are merged (shorter chunks): the same ranks
    counts = (max(ca - 3, 1), max(cb - 2, 1))
    ranks = jax.jit(lambda *x: morton.merge_ranks(*x[:4], x[4:]))(ah, al, bh, bl, *counts)
    for g, want in zip(ranks, (lt_a, le_b)):
        np.testing.assert_array_equal(np.asarray(g), want)


def test_leaf_cell_codes_are_the_cells_of_each_leaf():
    """Every finest cell of every leaf once, in leaf order, with the leaf that holds it; a
    subset by cell number picks the same cells (checked against keys enumerated per leaf)."""
    rng = np.random.default_rng(3)
    depths = rng.integers(13, 17, 40)
    keys = rng.integers(0, 1 << 12, (40, 3)).astype(np.uint16) << 4  # 16-aligned: any depth >= 12
    codes = morton.keys_to_codes(keys)
    cells, leaf = morton.leaf_cell_codes(codes, depths)
    expected = []
    for k, d in zip(keys.astype(np.int64), depths):
        s = 1 << (16 - int(d))
        o = np.stack(np.meshgrid(*(np.arange(s),) * 3, indexing="ij"), -1).reshape(-1, 3)
        expected.append(np.sort(morton.keys_to_codes((k + o).astype(np.uint16))))
    assert cells.shape[0] == sum(8 ** (16 - int(d)) for d in depths)
    for i, e in enumerate(expected):
        np.testing.assert_array_equal(cells[leaf == i], e)  # consecutive codes from the leaf's own
    assert np.all(np.diff(leaf) >= 0)
    idx = np.sort(rng.choice(cells.shape[0], 100, replace=False))
    sub, sub_leaf = morton.leaf_cell_codes(codes, depths, idx)
    np.testing.assert_array_equal(sub, cells[idx])
    np.testing.assert_array_equal(sub_leaf, leaf[idx])


def test_code_arithmetic_on_word_columns_matches_uint64():
    """``code_*``: digits, masks, truncation, digit insertion, ends, order and digit sums of
    codes given as (hi, lo) word columns, against plain uint64 arithmetic."""
    rng = np.random.default_rng(0)
    codes = np.concatenate([rng.integers(0, 1 << 48, 200, dtype=np.uint64),
                            np.array([0, (1 << 48) - 1, 1 << 24, (1 << 24) - 1], np.uint64)])
    k = rng.integers(0, 16, codes.size).astype(np.int32)
    hi, lo = (jnp.asarray(x) for x in morton.split_codes(codes).T)
    kj = jnp.asarray(k)
    c = codes.astype(np.uint64)
    shift = (3 * k).astype(np.uint64)
    low = (np.uint64(1) << shift) - np.uint64(1)
    digits = (c >> shift) & np.uint64(7)

    def join(h, l):
        return morton.join_codes(np.stack([np.asarray(h), np.asarray(l)], -1))

    np.testing.assert_array_equal(np.asarray(morton.code_digit(hi, lo, kj)), digits)
    np.testing.assert_array_equal(np.asarray(morton.code_low_nonzero(hi, lo, kj)), (c & low) != 0)
    trunc = c & ~low
    np.testing.assert_array_equal(join(*morton.code_truncate(hi, lo, kj)), trunc)
    val = rng.integers(0, 8, codes.size).astype(np.int32)
    th, tl = (jnp.asarray(x) for x in morton.split_codes(trunc).T)
    put = morton.code_put_digit(th, tl, kj, jnp.asarray(val))
    np.testing.assert_array_equal(join(*put), trunc | (val.astype(np.uint64) << shift))
    depth = 16 - k
    np.testing.assert_array_equal(join(*morton.code_end(th, tl, jnp.asarray(depth))),
                                  trunc + (np.uint64(1) << shift))
    np.testing.assert_array_equal(join(*morton.code_end(jnp.zeros(1, jnp.int32), jnp.zeros(1, jnp.int32),
                                                        jnp.zeros(1, jnp.int32))), [1 << 48])
    want_sum = sum((c >> np.uint64(3 * j)) & np.uint64(7) for j in range(16))
    np.testing.assert_array_equal(np.asarray(morton.code_digit_sum(hi, lo)), want_sum)
    perm = rng.permutation(codes.size)
    np.testing.assert_array_equal(np.asarray(morton.code_less(hi, lo, hi[perm], lo[perm])), c < c[perm])


def test_end_words_at_every_depth():
    """``end_words`` = code + 8^(16 - depth) for aligned codes at each depth 0..16, including
    the carry from the low word into the high one and the end of the key space."""
    codes, depths = [], []
    for depth in range(17):
        span = 1 << (3 * (16 - depth))
        top = (1 << 48) - span  # the last aligned node
        cells = [0, span, top, top - span, (1 << 24) - span]  # the last: ends at the word boundary
        cells += [(((1 << 48) - 1) // 7 * k) & ~(span - 1) for k in range(1, 7)]
        cells = sorted({c for c in cells if c >= 0})
        codes += cells
        depths += [depth] * len(cells)
    codes = np.array(codes, np.uint64)
    spans = np.uint64(1) << (np.uint64(3) * (16 - np.array(depths, np.uint64)))
    ends = np.asarray(morton.end_words(jnp.asarray(morton.split_codes(codes)), jnp.asarray(depths)))
    # 2^48 splits into (SENTINEL_HI, 0), the documented end of the key space
    np.testing.assert_array_equal(ends, morton.split_codes(codes + spans))
