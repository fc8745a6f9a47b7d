"""Stable argsort by several small unsigned keys, as single-operand sorts (jittable, vmappable).

XLA's CPU backend sorts one integer array several times faster than the same array with a
payload or a second key, because a multi-operand sort runs a generic comparator
(``docs/design.md``, "Single-operand sorts"). So an argsort by
``(key_1, key_2, ...)`` is done here as an LSD radix sort whose digits are single ``uint32``
sorts: each pass packs a ``32 - r``-bit digit of the keys above the ``r = ceil(log2 n)``-bit
current position of the row, sorts that one word, and reads the new order from its low bits.
Equal digits keep their positions, so every pass is stable, and so is the whole sort.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["lexsort_rows"]


def lexsort_rows(fields, first=None):
    """Permutation ``(n,) int32`` that orders rows by ``fields``, ties in ``first`` order.

    ``fields``: ``((key (n,) integer array, bits), ...)``, most significant first; each key
    holds non-negative values below ``2**bits`` (``bits`` static, 1..32; other bits are
    ignored). ``first``: ``(n,) int32`` permutation giving the order of rows with equal keys
    (default: row order). Takes ``ceil(sum(bits) / (32 - r))`` sorts of ``n`` words, ``r =
    ceil(log2 n)``."""
    fields = [(jnp.asarray(k).astype(jnp.uint32), int(b)) for k, b in fields]
    n = fields[0][0].shape[0]
    r = max(1, (n - 1).bit_length())
    digit = 32 - r
    if digit < 1:
        raise ValueError(f"lexsort_rows: {n} rows leave no bits for the keys")
    total = sum(b for _, b in fields)
    offsets, o = [], total  # bit offset of each field's least significant bit in the packed key
    for _, b in fields:
        if not 1 <= b <= 32:
            raise ValueError(f"lexsort_rows: key widths must lie in 1..32 bits, got {b}")
        o -= b
        offsets.append(o)
    position = jnp.arange(n, dtype=jnp.uint32)
    low = np.uint32((1 << r) - 1)
    perm = first
    for lo in range(0, total, digit):
        hi = min(total, lo + digit)
        word = jnp.zeros((n,), jnp.uint32)
        for (key, b), o in zip(fields, offsets):
            a, e = max(lo, o), min(hi, o + b)  # the field's bits [a, e) of the packed key
            if a < e:
                part = jnp.right_shift(key, np.uint32(a - o)) & np.uint32((1 << (e - a)) - 1)
                word = word | jnp.left_shift(part, np.uint32(a - lo))
        if perm is not None:
            word = word[perm]
        s = jax.lax.sort(jnp.left_shift(word, np.uint32(r)) | position)
        idx = (s & low).astype(jnp.int32)
        perm = idx if perm is None else perm[idx]
    return jnp.arange(n, dtype=jnp.int32) if perm is None else perm.astype(jnp.int32)
