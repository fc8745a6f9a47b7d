"""lexsort_rows: a stable argsort by packed unsigned keys (single-operand sorts), against NumPy."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from octomerge_jax._sort import lexsort_rows


@pytest.mark.parametrize("n", [1, 7, 1000, 4096, 50_000])
@pytest.mark.parametrize("widths", [(1,), (21,), (3, 5), (18, 31), (32, 32, 7)])
def test_matches_numpy_stable_lexsort(n, widths):
    rng = np.random.default_rng(n + sum(widths))
    # few distinct values in the leading key, so that ties are common
    keys = [rng.integers(0, min(1 << w, 5 if i == 0 else 1 << w), n, dtype=np.uint64).astype(np.uint32)
            for i, w in enumerate(widths)]
    got = np.asarray(jax.jit(lambda *k: lexsort_rows(tuple(zip(k, widths))))(*keys))
    want = np.lexsort((np.arange(n), *keys[::-1]))
    np.testing.assert_array_equal(got, want)


def test_ties_follow_first_and_bits_above_the_width_are_ignored():
    rng = np.random.default_rng(0)
    n = 2048
    key = rng.integers(0, 4, n).astype(np.uint32)
    noisy = key | (rng.integers(0, 8, n).astype(np.uint32) << 2)  # bits above width 2
    first = rng.permutation(n).astype(np.int32)
    got = np.asarray(lexsort_rows(((jnp.asarray(noisy), 2),), first=jnp.asarray(first)))
    rank = np.empty(n, np.int64)
    rank[first] = np.arange(n)
    np.testing.assert_array_equal(got, np.lexsort((rank, key)))


def test_vmap_and_bad_widths():
    rng = np.random.default_rng(1)
    a = rng.integers(0, 1 << 20, (3, 500)).astype(np.int32)
    b = rng.integers(0, 1 << 30, (3, 500)).astype(np.int32)
    got = np.asarray(jax.vmap(lambda x, y: lexsort_rows(((x, 20), (y, 30))))(a, b))
    for i in range(3):
        np.testing.assert_array_equal(got[i], np.lexsort((np.arange(500), b[i], a[i])))
    with pytest.raises(ValueError, match="1..32 bits"):
        lexsort_rows(((jnp.zeros(4, jnp.int32), 33),))
