"""The package's array helpers (``octomerge_jax._ops``) against NumPy."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from octomerge_jax._ops import (all_of, any_of, column_extent, cond_with_shapes, count_true, cummax, cumsum,
                                materialize, nonzero_rows)


def test_materialize_returns_the_value_and_traces_it_once():
    calls = []

    def fn(x):
        calls.append(1)
        return {"a": x * 2, "b": (x > 3).astype(jnp.int8)}

    x = jnp.arange(8, dtype=jnp.int32)
    out = jax.jit(lambda x: materialize(x[0] >= 0, lambda: fn(x)))(x)
    np.testing.assert_array_equal(out["a"], np.arange(8) * 2)
    np.testing.assert_array_equal(out["b"], (np.arange(8) > 3).astype(np.int8))
    assert len(calls) == 1
    batched = jax.vmap(lambda x: materialize(x[0] >= 0, lambda: fn(x)))(jnp.stack([x, x + 1]))
    np.testing.assert_array_equal(batched["a"], np.stack([np.arange(8), np.arange(1, 9)]) * 2)


def test_cond_with_shapes_hands_the_false_branch_the_true_branch_shapes():
    x = jnp.arange(5, dtype=jnp.float32)
    f = jax.jit(lambda x, p: cond_with_shapes(p, lambda: (x + 1, jnp.sum(x)),
                                              lambda s: (jnp.full(s[0].shape, -1.0, s[0].dtype), s[1].dtype.type(0))))
    a, b = f(x, True)
    np.testing.assert_array_equal(a, np.arange(5) + 1.0)
    assert float(b) == 10.0
    a, b = f(x, False)
    np.testing.assert_array_equal(a, -np.ones(5))
    assert float(b) == 0.0


def test_blocked_scans_match_numpy():
    rng = np.random.default_rng(0)
    for n in (1, 3, 4, 64, 1000, 4096):
        x = rng.integers(-50, 50, n).astype(np.int32)
        np.testing.assert_array_equal(cumsum(jnp.asarray(x)), np.cumsum(x))
        np.testing.assert_array_equal(cumsum(jnp.asarray(x), reverse=True), np.cumsum(x[::-1])[::-1])
        np.testing.assert_array_equal(cummax(jnp.asarray(x)), np.maximum.accumulate(x))


def test_cumsum_by_products_is_exact_on_rows_overflow_and_vmap():
    rng = np.random.default_rng(1)
    for shape in ((16,), (17,), (48, 3), (4096, 4), (1 << 16,), (1 << 20,)):
        x = rng.integers(-1000, 1000, shape).astype(np.int32)
        got = np.asarray(jax.jit(cumsum)(x))
        assert got.dtype == np.int32
        np.testing.assert_array_equal(got, np.cumsum(x, axis=0))
    x = np.full(4096, 2**30, np.int32)  # wraps as int32 arithmetic does
    np.testing.assert_array_equal(cumsum(x), np.cumsum(x, dtype=np.int32))
    rows = rng.integers(0, 9, (3, 256)).astype(np.int32)
    np.testing.assert_array_equal(jax.vmap(cumsum)(rows), np.cumsum(rows, axis=1))


def test_count_true_matches_numpy():
    rng = np.random.default_rng(2)
    for shape in ((0,), (7,), (1 << 20,), (300, 3)):
        x = rng.random(shape) < 0.3
        got = jax.jit(count_true)(x)
        assert got.dtype == jnp.int32 and int(got) == int(x.sum())
    assert int(count_true(np.ones(1 << 22, bool))) == 1 << 22


def test_any_of_and_all_of_match_jnp_any_and_all():
    rng = np.random.default_rng(3)
    cases = [np.zeros((0,), bool), np.zeros((5,), bool), np.ones((7,), bool), np.zeros((2, 0, 3), bool)]
    for n in (1, 31, 1000, 1 << 16):
        for p in (0.0, 1e-4, 0.5, 1.0):
            cases.append(rng.random(n) < p)
    cases.append(rng.random((64, 8, 8)) < 0.999)
    for x in cases:
        assert bool(jax.jit(any_of)(x)) == bool(np.any(x)), (x.shape, x.sum())
        assert bool(jax.jit(all_of)(x)) == bool(np.all(x)), (x.shape, x.sum())
        assert jax.jit(any_of)(x).dtype == bool and jax.jit(any_of)(x).shape == ()
    # a single true (false) row anywhere is seen
    for i in (0, 12345, (1 << 16) - 1):
        x = np.zeros(1 << 16, bool)
        x[i] = True
        assert bool(any_of(x)) and not bool(all_of(x)) and bool(any_of(~x)) and not bool(all_of(~x))


def test_nonzero_rows_matches_jnp_nonzero_with_size():
    rng = np.random.default_rng(4)
    for n, p in ((1, 1.0), (100, 0.0), (100, 0.3), (4096, 0.9), (1 << 16, 0.01)):
        mask = rng.random(n) < p
        for size, fill in ((n, n), (max(n // 3, 1), -1), (2 * n, 7)):
            got = jax.jit(nonzero_rows, static_argnums=(1, 2))(mask, size, fill)
            want = jnp.nonzero(mask, size=size, fill_value=fill)[0]
            assert got.dtype == jnp.int32 and got.shape == (size,)
            np.testing.assert_array_equal(got, want)


def test_column_extent_matches_numpy_over_valid_rows():
    rng = np.random.default_rng(5)
    x = rng.integers(-(1 << 23), 1 << 23, (5000, 3)).astype(np.int32)
    x[7] = [2**31 - 128, -(2**31), 123]  # int32 values made from float32 floors are exact too
    for p in (1.0, 0.5, 0.001):
        valid = rng.random(5000) < p
        valid[7] = True
        lo, hi = jax.jit(column_extent)(x, valid)
        assert lo.dtype == jnp.int32 and hi.dtype == jnp.int32
        np.testing.assert_array_equal(lo, x[valid].min(axis=0))
        np.testing.assert_array_equal(hi, x[valid].max(axis=0))
    lo, hi = column_extent(x, np.zeros(5000, bool))
    np.testing.assert_array_equal(lo, 0)
    np.testing.assert_array_equal(hi, 0)
