"""Padded-array primitives shared by the kernels, and the capacity-bucket policy.

Arrays are padded to static power-of-two capacities (``bucket_capacity``) so that maps of
similar size share one compiled function and stack under ``vmap``; padding rows carry the
sentinel code ``(morton.SENTINEL_HI, 0)`` that sorts after every real code. The scans here run
along axis 0 of int32 arrays; the shifts move rows along axis 0. All are jittable and
vmappable. Why blocked scans and ``materialize`` exist: ``docs/design.md``, "Blocked scans"
and "Materialised intermediates".
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from . import morton

__all__ = [
    "MIN_CAPACITY",
    "bucket_capacity",
    "is_traced",
    "shift_up",
    "shift_down",
    "materialize",
    "cumsum",
    "cummax",
    "cummin",
    "any_of",
    "all_of",
    "count_true",
    "nonzero_rows",
    "column_extent",
    "padding_rows",
    "float_bits",
    "quarter_octave_capacity",
]

MIN_CAPACITY = 256


def bucket_capacity(n: int, minimum: int = MIN_CAPACITY) -> int:
    """Smallest power of two ``>= max(n, minimum)``: the static capacity for ``n`` rows."""
    n = max(int(n), int(minimum), 1)
    return 1 << math.ceil(math.log2(n))


def is_traced(*xs) -> bool:
    """Whether any of ``xs`` is a JAX tracer (the caller runs under ``jit``/``vmap``), so
    host-side sizing must not read its value."""
    return any(isinstance(x, jax.core.Tracer) for x in xs)


def to_device(x, dtype=None):
    """``x`` as a JAX array of ``dtype`` (default: its own, canonicalised): a JAX array (or
    tracer) through ``jnp.asarray``, a host value converted by NumPy and sent with
    ``jax.device_put``. ``jnp.asarray`` of a host array compiles a small program per shape and
    dtype (``jit(stage)``, ``jit(convert_element_type)``); ``device_put`` compiles none."""
    if isinstance(x, jax.Array):
        return jnp.asarray(x, dtype)
    a = np.asarray(x, dtype)
    return jax.device_put(a.astype(jax.dtypes.canonicalize_dtype(a.dtype), copy=False))


def shift_up(x, k: int, fill):
    """``y[i] = x[i + k]`` along axis 0 (rows past the end take ``fill``); ``k`` static >= 1."""
    pad = jnp.full((k,) + x.shape[1:], fill, x.dtype)
    return jnp.concatenate([x[k:], pad], axis=0)


def shift_down(x, k: int, fill):
    """``y[i] = x[i - k]`` along axis 0 (the first ``k`` rows take ``fill``); ``k`` static >= 1."""
    pad = jnp.full((k,) + x.shape[1:], fill, x.dtype)
    return jnp.concatenate([pad, x[:-k]], axis=0)


def zeros_of(shapes):
    """Zeros shaped like ``shapes`` (a pytree of arrays or ``jax.ShapeDtypeStruct``)."""
    return jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)


def cond_with_shapes(pred, true_fn, false_fn):
    """``lax.cond(pred, true_fn, lambda: false_fn(shapes))``, ``shapes`` the
    ``jax.ShapeDtypeStruct`` pytree of ``true_fn()``'s result, with ``true_fn`` traced once
    (``jax.eval_shape`` would trace it a second time; it is the fallback should the cond trace
    the false branch first)."""
    seen = []

    def true_branch():
        out = true_fn()
        seen.append(jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), out))
        return out

    return jax.lax.cond(pred, true_branch, lambda: false_fn(seen[0] if seen else jax.eval_shape(true_fn)))


def materialize(gate, fn):
    """``fn()`` (an array or a pytree of arrays) computed once into memory.

    ``gate`` is a traced True (e.g. ``m.count >= 0``): ``fn`` runs inside a ``lax.cond`` on
    it, so XLA cannot fuse (and so recompute) its ops into each consumer. A performance hint
    only: the value is ``fn()``, and under ``vmap`` the cond becomes a select."""
    return cond_with_shapes(gate, fn, zeros_of)


_SCANS = {"add": (jax.lax.cumsum, jnp.add, 0),
          "max": (jax.lax.cummax, jnp.maximum, np.iinfo(np.int32).min),
          "min": (jax.lax.cummin, jnp.minimum, np.iinfo(np.int32).max)}


def _scan(kind: str, x, reverse: bool = False, block: int = 4, levels: int = 2):
    """Inclusive scan of int32 ``x`` along axis 0 in blocks: ``lax.cum*`` inside blocks of
    ``block`` rows, the block totals scanned the same way for ``levels`` levels, then by one
    ``lax.cum*`` (docs/design.md, "Blocked scans")."""
    if reverse:
        return _scan(kind, x[::-1], block=block, levels=levels)[::-1]
    cum, op, ident = _SCANS[kind]
    n = x.shape[0]
    if levels == 0 or n <= block or n % block:
        return cum(x, axis=0)
    within = cum(x.reshape((n // block, block) + x.shape[1:]), axis=1)
    total = _scan(kind, within[:, -1], block=block, levels=levels - 1)
    carry = jnp.concatenate([jnp.full((1,) + x.shape[1:], ident, x.dtype), total[:-1]])
    return op(within, carry[:, None]).reshape(x.shape)


def _cumsum_by_products(x, block: int = 16):
    """Inclusive prefix sum of int32 ``x (n, ...)`` along axis 0 as integer matrix products:
    each block of ``block`` rows times an upper-triangular matrix of ones, the block totals
    the same way, then each block's carry added (docs/design.md, "Blocked scans")."""
    n = x.shape[0]
    if n % block:
        return jax.lax.cumsum(x, axis=0)
    if n == block:
        tri = jnp.triu(jnp.ones((n, n), x.dtype))
        return jnp.tensordot(tri, x, axes=((0,), (0,)), preferred_element_type=x.dtype)
    rows = x.reshape((n // block, block) + x.shape[1:])
    tri = jnp.triu(jnp.ones((block, block), x.dtype))
    within = jnp.moveaxis(jnp.tensordot(rows, tri, axes=((1,), (0,)), preferred_element_type=x.dtype), -1, 1)
    total = _cumsum_by_products(within[:, -1], block)
    carry = jnp.concatenate([jnp.zeros((1,) + x.shape[1:], x.dtype), total[:-1]])
    return (within + carry[:, None]).reshape(x.shape)


def cumsum(x, reverse: bool = False):
    """Inclusive prefix sum of int32 ``x (n, ...)`` along axis 0: on the CPU as blocked
    integer matrix products (half the compile time of a blocked ``lax.cumsum``), elsewhere
    the blocked scan."""
    if reverse:
        return cumsum(x[::-1])[::-1]
    x = jnp.asarray(x)
    return jax.lax.platform_dependent(x, cpu=_cumsum_by_products, default=lambda v: _scan("add", v))


def cummax(x, reverse: bool = False):
    """Inclusive running maximum of int32 ``x (n, ...)`` along axis 0 (blocked scan)."""
    return _scan("max", x, reverse)


def cummin(x, reverse: bool = False):
    """Inclusive running minimum of int32 ``x (n, ...)`` along axis 0 (blocked scan)."""
    return _scan("min", x, reverse)


def any_of(x):
    """Whether any element of bool ``x`` (any shape) is true: a scalar bool, ``False`` when
    ``x`` is empty. Reduced as bytes, not as ``jnp.any``: XLA:CPU compiles a boolean
    reduction of a large array ten times slower
    (docs/design.md, "Reductions XLA:CPU compiles fast")."""
    return jnp.max(jnp.asarray(x).astype(jnp.uint8), initial=0) > 0


def all_of(x):
    """Whether every element of bool ``x`` (any shape) is true: a scalar bool, ``True`` when
    ``x`` is empty (``jnp.all`` as bytes, as ``any_of``)."""
    return jnp.min(jnp.asarray(x).astype(jnp.uint8), initial=1) > 0


def count_true(x):
    """How many elements of bool ``x`` (any shape) are true, as an int32 scalar. Summed in
    float32 when ``x`` has fewer than 2^24 elements (every partial sum an integer below 2^24, so
    exact in any order): XLA:CPU compiles an integer sum of a large array as a tree of
    reduce-window kernels, several times slower to compile than a float sum
    (docs/design.md, "Reductions XLA:CPU compiles fast")."""
    x = jnp.asarray(x)
    if x.size < 1 << 24:
        return jnp.sum(x, dtype=jnp.float32).astype(jnp.int32)
    return jnp.sum(x, dtype=jnp.int32)


def nonzero_rows(mask, size: int, fill: int):
    """The indices of the true elements of bool ``mask (n,)`` in order, as int32 ``(size,)``:
    the first ``size`` of them, the rows after the last one ``fill``. ``jnp.nonzero(mask,
    size=size, fill_value=fill)[0]`` from one prefix sum and one scatter (``jnp.nonzero``
    takes two prefix sums, a histogram and a sum, and compiles slower;
    docs/design.md, "Reductions XLA:CPU compiles fast")."""
    mask = jnp.asarray(mask)
    n = mask.shape[0]
    pos = jnp.where(mask, cumsum(mask.astype(jnp.int32)) - 1, size)  # past the end: dropped
    return jnp.full((size,), fill, jnp.int32).at[pos].set(jnp.arange(n, dtype=jnp.int32), mode="drop")


def column_extent(x, valid):
    """``(lo, hi)``, each int32 ``(k,)``: the smallest and largest value of each column of int32
    ``x (n, k)`` over the rows where ``valid (n,)`` is true, ``(0, 0)`` where none is. Every
    value must be exact in float32 (below 2^24 in magnitude, or an int32 made from a float32,
    as cell indices from ``floor``): the columns are reduced in float32, which XLA:CPU compiles
    in half the time of an integer min / max (docs/design.md, "Reductions XLA:CPU compiles fast")."""
    xf = jnp.asarray(x).astype(jnp.float32)
    lo = jnp.min(jnp.where(valid[:, None], xf, jnp.inf), axis=0)
    hi = jnp.max(jnp.where(valid[:, None], xf, -jnp.inf), axis=0)
    some = any_of(valid)
    return jnp.where(some, lo, 0.0).astype(jnp.int32), jnp.where(some, hi, 0.0).astype(jnp.int32)


def padding_rows(capacity: int):
    """``(code (capacity, 2) int32, depth (capacity,) int32, log_odds (capacity,) float32)``
    holding only padding rows (code ``(SENTINEL_HI, 0)``, depth 16, log-odds 0): buffers to
    scatter leaves into."""
    return (jnp.broadcast_to(jnp.array([morton.SENTINEL_HI, 0], jnp.int32), (capacity, 2)),
            jnp.full((capacity,), morton.TREE_DEPTH, jnp.int32), jnp.zeros((capacity,), jnp.float32))


def float_bits(x):
    """The IEEE-754 bits of ``x`` as float32, as int32 (to carry floats in integer sorts)."""
    return jax.lax.bitcast_convert_type(x.astype(jnp.float32), jnp.int32)


# ----------------------------------------------------------------------------- list capacities


def quarter_octave_capacity(n: int, minimum: int) -> int:
    """Smallest ``q 2^k >= max(n, minimum, 4)`` with ``q`` in 4..8 (four steps per octave).

    For work arrays whose padding costs per row (every DDA step runs on every padded ray;
    large tables are paid in first-touch pages): pads by <= 25 % instead of <= 50 % for
    ``bucket_capacity``, at the price of more distinct compiled shapes."""
    n = max(int(n), int(minimum), 4)
    k = max(n.bit_length() - 3, 0)
    return -(-n // (1 << k)) * (1 << k)
