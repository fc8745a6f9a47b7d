"""The package's array helpers (``octomerge_jax._ops``) against NumPy."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from octomerge_jax._ops import cond_with_shapes, cummax, cumsum, materialize


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
