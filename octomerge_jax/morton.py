"""Keys, Morton codes and metric coordinates, exactly as OctoMap computes them.

OctoMap (``OcTreeBaseImpl.h``) addresses a finest voxel by a key of three 16-bit integers,
``key = floor(coord * (1 / res)) + 32768`` per axis, and a node at depth ``d`` (0 = root,
16 = finest) covers the ``2^(16-d)``-wide cube of keys sharing their top ``d`` bits.

We order leaves by the **Morton code** of their minimum-corner finest key: the 48-bit
interleave ``... z1 y1 x1 z0 y0 x0`` (x in the lowest bit, matching OctoMap's child index
``bit0 = x, bit1 = y, bit2 = z``). Pre-order traversal of an octree visits leaves in
increasing Morton order, so the file formats and our flat arrays share one order.

**64-bit without touching the user's JAX config.** 48 bits do not fit JAX's default 32-bit
integers and we never flip ``jax_enable_x64`` (``jax_explicit_x64_dtypes`` exists in JAX
0.10 but ``asarray`` still truncates there). So a code is two non-negative ``int32`` words,
``words[..., 0] = hi`` (the interleave of the top 8 key bits per axis, i.e. the depth-8
cell) and ``words[..., 1] = lo`` (the interleave of the low 8 bits), each < 2^24. Pairs
sort with ``lax.sort(..., num_keys=2)`` and compare lexicographically. On the host (NumPy)
a code is a plain ``uint64``; ``split_codes`` / ``join_codes`` convert.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

TREE_DEPTH = 16
KEY_OFFSET = 32768  # OctoMap's tree_max_val
WORD_BITS = 24
WORD_MASK = (1 << WORD_BITS) - 1
SENTINEL_HI = 1 << WORD_BITS  # padding rows: hi word past every real code, so they sort last
SENTINEL_CODE = np.uint64(SENTINEL_HI) << np.uint64(WORD_BITS)

__all__ = [
    "TREE_DEPTH",
    "KEY_OFFSET",
    "SENTINEL_HI",
    "SENTINEL_CODE",
    "coords_to_keys",
    "keys_to_coords",
    "keys_to_codes",
    "codes_to_keys",
    "split_codes",
    "join_codes",
    "leaf_centers",
    "leaf_cell_counts",
    "leaf_cell_codes",
    "node_size",
    "level_shift",
    "keys_to_words",
    "words_to_keys",
    "truncate_words",
    "child_index_words",
    "or_offset_words",
    "end_words",
    "top_bit",
    "common_depths",
    "group_sizes",
    "words_less",
    "words_equal",
    "partition_point",
    "searchsorted_words",
    "merge_ranks",
    "merge_sorted",
    "points_to_keys",
    "low_bit_masks", "code_less", "code_digit", "code_low_masks", "code_low_nonzero", "code_truncate",
    "code_put_digit", "code_end", "code_digit_sum",
]


# ----------------------------------------------------------------------------- host (NumPy)


def node_size(depth, resolution: float):
    """Edge length in metres of a node at ``depth`` (OctoMap ``getNodeSize``)."""
    return resolution * np.exp2(TREE_DEPTH - np.asarray(depth, dtype=np.float64))


def level_shift(depth):
    """Number of low Morton bits a node at ``depth`` spans: ``3 * (16 - depth)``."""
    return 3 * (TREE_DEPTH - np.asarray(depth))


def coords_to_keys(points, resolution: float, *, name: str = "points") -> np.ndarray:
    """Metric points ``(..., 3)`` [m] -> finest keys ``(..., 3)`` uint16, as OctoMap's
    ``coordToKeyChecked`` (``floor(coord * (1/res)) + 32768``, double precision).

    Raises ``ValueError`` naming the first offending value when a coordinate is not finite
    or lies outside ``[-32768 res, 32768 res)``.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.shape[-1:] != (3,):
        raise ValueError(f"{name}: expected shape (..., 3), got {p.shape}")
    factor = 1.0 / float(resolution)
    with np.errstate(invalid="ignore", over="ignore"):
        scaled = np.floor(p * factor) + KEY_OFFSET
    bad = ~np.isfinite(scaled) | (scaled < 0) | (scaled >= 2 * KEY_OFFSET)
    if bad.any():
        idx = np.argwhere(bad)[0]
        value = float(p[tuple(idx)])
        raise ValueError(
            f"{name}: coordinate {value!r} (index {tuple(int(i) for i in idx)}) is outside the "
            f"OctoMap key range [-{KEY_OFFSET * resolution:g}, {KEY_OFFSET * resolution:g}) m "
            f"for resolution {resolution:g} m; move the map to a local frame"
        )
    return scaled.astype(np.uint16)


def keys_to_coords(keys, resolution: float, depth=TREE_DEPTH) -> np.ndarray:
    """Centre [m] of the node at ``depth`` containing finest ``keys`` (OctoMap ``keyToCoord``).

    ``(floor((key - 32768) / 2^(16-d)) + 0.5) * nodeSize(d)``; depth 0 gives 0.0.
    Returns float64 (OctoMap rounds to float32 when it builds a ``point3d``).
    """
    k = np.asarray(keys, dtype=np.int64) - KEY_OFFSET
    d = np.asarray(depth, dtype=np.int64)
    if d.ndim:
        d = d[..., None]
    shift = TREE_DEPTH - d
    size = resolution * np.exp2(shift.astype(np.float64))
    centers = ((k >> shift).astype(np.float64) + 0.5) * size
    return np.where(d == 0, 0.0, centers)


def _spread3(v: np.ndarray) -> np.ndarray:
    """Spread the low 16 bits of ``v`` to every third bit (uint64)."""
    v = v.astype(np.uint64) & np.uint64(0xFFFF)
    v = (v | (v << np.uint64(32))) & np.uint64(0x1F00000000FFFF)
    v = (v | (v << np.uint64(16))) & np.uint64(0x1F0000FF0000FF)
    v = (v | (v << np.uint64(8))) & np.uint64(0x100F00F00F00F00F)
    v = (v | (v << np.uint64(4))) & np.uint64(0x10C30C30C30C30C3)
    v = (v | (v << np.uint64(2))) & np.uint64(0x1249249249249249)
    return v


def _compact3(v: np.ndarray) -> np.ndarray:
    """Inverse of ``_spread3``: gather every third bit into the low 16 bits."""
    v = v.astype(np.uint64) & np.uint64(0x1249249249249249)
    v = (v | (v >> np.uint64(2))) & np.uint64(0x10C30C30C30C30C3)
    v = (v | (v >> np.uint64(4))) & np.uint64(0x100F00F00F00F00F)
    v = (v | (v >> np.uint64(8))) & np.uint64(0x1F0000FF0000FF)
    v = (v | (v >> np.uint64(16))) & np.uint64(0x1F00000000FFFF)
    v = (v | (v >> np.uint64(32))) & np.uint64(0xFFFF)
    return v


def keys_to_codes(keys) -> np.ndarray:
    """Finest keys ``(..., 3)`` -> 48-bit Morton codes ``(...,)`` uint64 (x lowest)."""
    k = np.asarray(keys)
    return _spread3(k[..., 0]) | (_spread3(k[..., 1]) << np.uint64(1)) | (_spread3(k[..., 2]) << np.uint64(2))


def codes_to_keys(codes) -> np.ndarray:
    """48-bit Morton codes ``(...,)`` -> finest keys ``(..., 3)`` uint16."""
    c = np.asarray(codes, dtype=np.uint64)
    return np.stack(
        [_compact3(c), _compact3(c >> np.uint64(1)), _compact3(c >> np.uint64(2))], axis=-1
    ).astype(np.uint16)


def split_codes(codes) -> np.ndarray:
    """uint64 codes ``(...,)`` -> int32 words ``(..., 2)`` = (hi, lo), 24 bits each."""
    c = np.asarray(codes, dtype=np.uint64)
    hi = (c >> np.uint64(WORD_BITS)).astype(np.int32)
    lo = (c & np.uint64(WORD_MASK)).astype(np.int32)
    return np.stack([hi, lo], axis=-1)


def join_codes(words) -> np.ndarray:
    """int32 words ``(..., 2)`` -> uint64 codes ``(...,)``."""
    w = np.asarray(words).astype(np.uint64)
    return (w[..., 0] << np.uint64(WORD_BITS)) | w[..., 1]


def leaf_centers(codes, depths, resolution: float) -> np.ndarray:
    """Centres ``(n, 3)`` float64 [m] of leaves given min-corner codes and depths."""
    return keys_to_coords(codes_to_keys(codes), resolution, np.asarray(depths))


def leaf_cell_counts(depths) -> np.ndarray:
    """Host: ``(n,)`` int64, the finest (depth-16) cells in a leaf at each of ``depths (n,)``:
    ``8^(16 - d)``."""
    return np.int64(1) << (3 * (TREE_DEPTH - np.asarray(depths).astype(np.int64)))


def leaf_cell_codes(codes, depths, index=None) -> tuple[np.ndarray, np.ndarray]:
    """Host: the finest (depth-16) cells inside leaves, without expanding a tree. A leaf of
    min-corner code ``c`` at depth ``d`` holds the ``8^(16-d)`` consecutive codes from ``c``;
    number the cells of ``codes (n,)`` / ``depths (n,)`` in leaf order. ``index``: sorted int64
    cell numbers to return (e.g. a random subset; default all of them). Returns ``(cell codes
    (m,) uint64, leaf (m,) int64: the row of the leaf holding each)``."""
    codes = np.asarray(codes, np.uint64)
    cells = leaf_cell_counts(depths)
    starts = np.cumsum(cells) - cells
    index = np.arange(int(cells.sum()), dtype=np.int64) if index is None else np.asarray(index, np.int64)
    leaf = np.searchsorted(starts, index, side="right") - 1
    return codes[leaf] + (index - starts[leaf]).astype(np.uint64), leaf


# ----------------------------------------------------------------------------- host: tree shape

#: ``_COMMON_DEPTH[b]``: deepest common depth of two codes whose highest differing bit is b.
_COMMON_DEPTH = np.array([15 - b // 3 for b in range(48)], dtype=np.int64)


def common_depths(codes: np.ndarray) -> np.ndarray:
    """Depth of the deepest common ancestor of consecutive sorted codes, ``(n-1,)`` int64.

    For distinct codes the highest differing bit ``b`` lies in octal digit ``b // 3`` from
    the bottom, i.e. the codes part below depth ``15 - b // 3``.
    """
    x = codes[1:] ^ codes[:-1]
    if x.size and not x.all():
        raise ValueError("leaf codes must be distinct")
    # floor(log2 x) from the float64 exponent bits (exact: 0 < x < 2^48)
    high_bit = (x.astype(np.float64).view(np.int64) >> 52) - 1023
    return _COMMON_DEPTH[high_bit]


def group_sizes(codes: np.ndarray, depths: np.ndarray) -> np.ndarray:
    """Per leaf, how many stream records it opens (its new ancestors and itself), ``(n,)``.

    Raises ``ValueError`` if leaves overlap (a leaf inside another's volume).
    """
    depths = depths.astype(np.int64)
    d_common = np.concatenate([[-1], common_depths(codes)])
    if np.any(d_common[1:] >= np.minimum(depths[1:], depths[:-1])):
        raise ValueError("leaves overlap: one leaf lies inside another")
    return depths - d_common


# ----------------------------------------------------------------------------- device (JAX)


def _spread3_u32(v):
    """Spread the low 8 bits of a uint32 to every third bit (24-bit result)."""
    v = v & jnp.uint32(0xFF)
    v = (v | (v << 8)) & jnp.uint32(0x0300F00F)
    v = (v | (v << 4)) & jnp.uint32(0x030C30C3)
    v = (v | (v << 2)) & jnp.uint32(0x09249249)
    return v


def _compact3_u32(v):
    v = v & jnp.uint32(0x09249249)
    v = (v | (v >> 2)) & jnp.uint32(0x030C30C3)
    v = (v | (v >> 4)) & jnp.uint32(0x0300F00F)
    v = (v | (v >> 8)) & jnp.uint32(0xFF)
    return v


def _interleave8(x, y, z):
    return _spread3_u32(x) | (_spread3_u32(y) << 1) | (_spread3_u32(z) << 2)


def keys_to_words(keys):
    """Finest keys ``(..., 3)`` (any int dtype, values < 65536) -> code words ``(..., 2)`` int32."""
    k = jnp.asarray(keys).astype(jnp.uint32)
    x, y, z = k[..., 0], k[..., 1], k[..., 2]
    hi = _interleave8(x >> 8, y >> 8, z >> 8)
    lo = _interleave8(x, y, z)
    return jnp.stack([hi, lo], axis=-1).astype(jnp.int32)


def words_to_keys(words):
    """Code words ``(..., 2)`` -> finest keys ``(..., 3)`` int32."""
    w = jnp.asarray(words).astype(jnp.uint32)
    hi, lo = w[..., 0], w[..., 1]
    axes = [(_compact3_u32(hi >> a) << 8) | _compact3_u32(lo >> a) for a in range(3)]
    return jnp.stack(axes, axis=-1).astype(jnp.int32)


def points_to_keys(points, resolution):
    """Metric points ``(..., 3)`` -> (finest keys ``(..., 3)`` int32, in-range mask ``(...,)``).

    The jittable counterpart of ``coords_to_keys`` (in the points' float dtype; out-of-range
    or non-finite points are flagged rather than raised, since nothing raises inside jit).
    """
    p = jnp.asarray(points)
    scaled = jnp.floor(p * (1.0 / resolution)) + KEY_OFFSET
    ok = jnp.all(jnp.isfinite(scaled) & (scaled >= 0) & (scaled < 2 * KEY_OFFSET), axis=-1)
    keys = jnp.clip(jnp.where(jnp.isfinite(scaled), scaled, 0), 0, 2 * KEY_OFFSET - 1)
    return keys.astype(jnp.int32), ok


def low_bit_masks(shift):
    """(hi_mask, lo_mask) int32 selecting the low ``shift`` bits (0..48) of a code."""
    shift = jnp.asarray(shift, jnp.int32)
    lo_bits = jnp.minimum(shift, WORD_BITS)
    hi_bits = jnp.clip(shift - WORD_BITS, 0, WORD_BITS)
    lo_mask = (jnp.left_shift(jnp.int32(1), lo_bits) - 1).astype(jnp.int32)
    hi_mask = (jnp.left_shift(jnp.int32(1), hi_bits) - 1).astype(jnp.int32)
    return hi_mask, lo_mask


def truncate_words(words, depth):
    """Min-corner code of the depth-``depth`` node containing ``words`` (clears low bits)."""
    k = TREE_DEPTH - jnp.asarray(depth, jnp.int32)
    return jnp.stack(code_truncate(words[..., 0], words[..., 1], k), axis=-1)


def child_index_words(words, depth):
    """Child index (0..7) within its parent of the depth-``depth`` node containing ``words``
    (``depth >= 1``; bit0 = x, bit1 = y, bit2 = z as OctoMap's ``computeChildIdx``)."""
    return code_digit(words[..., 0], words[..., 1], TREE_DEPTH - jnp.asarray(depth, jnp.int32))


def or_offset_words(words, k, shift):
    """``code | (k << shift)`` for non-negative int32 ``k`` whose shifted bits are free in
    ``code`` (children of an aligned node). ``shift`` in 0..45."""
    k = jnp.asarray(k, jnp.int32)
    shift = jnp.asarray(shift, jnp.int32)
    big = shift >= WORD_BITS
    # shift < 24: lo gets the low (24 - shift) bits of k, hi the rest; shift >= 24: all to hi.
    lo_bits = jnp.where(big, 0, WORD_BITS - shift)
    lo_part = jnp.where(big, 0, jnp.left_shift(k & (jnp.left_shift(1, lo_bits) - 1), shift))
    hi_part = jnp.where(big, jnp.left_shift(k, jnp.maximum(shift - WORD_BITS, 0)), jnp.right_shift(k, lo_bits))
    return jnp.stack([words[..., 0] | hi_part, words[..., 1] | lo_part], axis=-1)


def end_words(words, depth):
    """Exclusive end ``code + 8^(16 - depth)`` of nodes as words ``(..., 2)``; the end of the
    whole key space (2^48) is ``(SENTINEL_HI, 0)``."""
    return jnp.stack(code_end(words[..., 0], words[..., 1], jnp.asarray(depth, jnp.int32)), axis=-1)


def top_bit(hi, lo):
    """Highest set bit (0..47) of the 48-bit code ``(hi, lo)`` (24-bit words); -1 for 0."""
    return jnp.where(hi != 0, 55 - jax.lax.clz(hi), 31 - jax.lax.clz(lo))


def words_less(a, b):
    """Lexicographic ``a < b`` on code words ``(..., 2)``."""
    return (a[..., 0] < b[..., 0]) | ((a[..., 0] == b[..., 0]) & (a[..., 1] < b[..., 1]))


def words_equal(a, b):
    return (a[..., 0] == b[..., 0]) & (a[..., 1] == b[..., 1])


def searchsorted_words(sorted_words, query_words, side: str = "right"):
    """``jnp.searchsorted`` for code words: sorted ``(n, 2)``, queries ``(..., 2)`` -> int32.

    ``side="right"``: number of entries ``<= q``; ``"left"``: number of entries ``< q``.
    A branch-free binary search (``ceil(log2(n + 1))`` gathers), vectorised over queries.
    """
    n = sorted_words.shape[0]
    q = jnp.asarray(query_words)
    steps = max(1, int(np.ceil(np.log2(n + 1))))

    def before(mid):  # the entry at ``mid`` is counted
        m = sorted_words[jnp.clip(mid, 0, max(n - 1, 0))]
        return ~words_less(q, m) if side == "right" else words_less(m, q)

    return partition_point(jnp.zeros(q.shape[:-1], jnp.int32), jnp.full(q.shape[:-1], n, jnp.int32), before, steps)


# ----------------------------------------------------------------------------- merge path


def code_less(ah, al, bh, bl):
    """Lexicographic ``a < b`` on codes given as word columns ``(hi, lo)``."""
    return (ah < bh) | ((ah == bh) & (al < bl))


def partition_point(lo, hi, pred, steps: int):
    """``lo + #{i in [lo, hi): pred(i)}`` for a predicate true then false on ``[lo, hi)``
    (int32 arrays of one shape): ``steps`` (static, ``>= log2(max width + 1)``) halvings,
    vectorised. ``pred`` also sees ``i == hi`` (its result is then unused): clip gathers."""

    def body(_, state):
        lo, hi = state
        mid = jnp.right_shift(lo + hi, 1)
        go = (mid < hi) & pred(mid)
        return jnp.where(go, mid + 1, lo), jnp.where(go, hi, mid)

    return jax.lax.fori_loop(0, steps, body, (lo, hi))[0]


_CHUNK = 128  # merge-path chunk: each chunk is merged sequentially, all chunks at once


def _merge_scan(ah, al, bh, bl, counts=None):
    """Merge path of two sorted code lists ``a (Ca,)``, ``b (Cb,)`` (word columns; ties:
    ``a`` first): ``(key, rank)``, ``(_CHUNK, chunks)`` each: at step ``t`` chunk ``c`` takes
    merged element ``c * _CHUNK + t``, ``key`` = its index in ``a``, or ``~index`` in ``b``
    (``~Cb``: none, past the end), ``rank`` = its rank in the other list.

    The merged sequence is cut into chunks of ``_CHUNK``; where each cut falls in ``a`` and
    ``b`` is one binary search per cut (few). Then all chunks are merged at once, one
    element per chunk and step. ``O(Ca + Cb)`` work, no binary search per element.

    ``counts=(na, nb)`` (traced): only the first ``na`` / ``nb`` rows are merged (the rest is
    padding, sorted last); the chunks are then ``ceil((na + nb) / chunks)`` long and the
    steps past that are not run (a ``while`` loop), so the work follows the valid rows, not
    the capacities. Elements not merged have key ``~Cb`` (none).
    """
    ca, cb = ah.shape[0], bh.shape[0]
    n = ca + cb
    chunks = -(-n // _CHUNK)
    if counts is None:
        na, nb, length = ca, cb, _CHUNK
    else:
        na, nb = (jnp.asarray(c, jnp.int32) for c in counts)
        length = -(-(na + nb) // chunks)  # <= _CHUNK
    d = jnp.minimum(jnp.arange(chunks + 1, dtype=jnp.int32) * length, na + nb)

    def a_before_cut(i):  # a_i is among the first d merged iff a_i <= b[d - i - 1]
        jb = d - i - 1
        jc, ic = jnp.clip(jb, 0, cb - 1), jnp.clip(i, 0, ca - 1)
        return (jb >= nb) | ((jb >= 0) & ~code_less(bh[jc], bl[jc], ah[ic], al[ic]))

    x = partition_point(jnp.maximum(d - nb, 0), jnp.minimum(d, na), a_before_cut, int(ca).bit_length())
    y = d - x  # cut k: x[k] a's and y[k] b's precede it
    a, b = jnp.stack([ah, al], -1), jnp.stack([bh, bl], -1)

    def step(state):
        i, j = state  # next a and b of each chunk
        ai, bj = a[jnp.minimum(i, ca - 1)], b[jnp.minimum(j, cb - 1)]
        take_a = (i < x[1:]) & ((j >= y[1:]) | ~code_less(bj[:, 0], bj[:, 1], ai[:, 0], ai[:, 1]))
        take_b = ~take_a & (j < y[1:])
        key = jnp.where(take_a, i, ~jnp.where(take_b, j, cb))
        return (i + take_a.astype(jnp.int32), j + take_b.astype(jnp.int32)), (key, jnp.where(take_a, j, i))

    if counts is None:
        _, (key, rank) = jax.lax.scan(lambda s, _: step(s), (x[:-1], y[:-1]), None, length=_CHUNK)
        return key, rank

    def body(carry):
        t, state, key, rank = carry
        state, (k, r) = step(state)
        return (t + 1, state, jax.lax.dynamic_update_index_in_dim(key, k, t, 0),
                jax.lax.dynamic_update_index_in_dim(rank, r, t, 0))

    empty = jnp.full((_CHUNK, chunks), ~cb, jnp.int32)
    _, _, key, rank = jax.lax.while_loop(lambda c: c[0] < length, body,
                                         (jnp.int32(0), (x[:-1], y[:-1]), empty, jnp.zeros_like(empty)))
    return key, rank


def merge_ranks(ah, al, bh, bl, counts=None):
    """Merge two sorted code lists ``a (Ca,)``, ``b (Cb,)`` (word columns; ties: ``a`` first):
    returns ``(#b < a_i, #a <= b_j)``, each element's rank in the other list.

    Merge path, no sort (``_merge_scan``); one scatter puts both lists' ranks in place.
    ``counts=(na, nb)``: the valid rows (padding ``(SENTINEL_HI, 0)`` after them); only those
    are merged, and padding rows get the ranks a full merge gives them (``nb``, ``Ca``).
    """
    ca, cb = ah.shape[0], bh.shape[0]
    key, rank = (x.reshape(-1) for x in _merge_scan(ah, al, bh, bl, counts))
    # one scatter into both lists' ranks, a's rows then b's (~Cb, "none", lands past them)
    ranks = jnp.zeros((ca + cb,), jnp.int32).at[jnp.where(key >= 0, key, ca + ~key)].set(rank, mode="drop")
    lt_a, le_b = ranks[:ca], ranks[ca:]
    if counts is not None:
        na, nb = counts
        lt_a = jnp.where(jnp.arange(ca) < na, lt_a, nb)
        le_b = jnp.where(jnp.arange(cb) < nb, le_b, ca)
    return lt_a, le_b


def merge_sorted(a, b):
    """Stable merge of two sorted record lists ``(hi, lo, *payload)`` (tuples of ``(n,)``
    int32 arrays, duplicates allowed, padding sorted last); ties keep ``a`` first. The merge
    path (``_merge_scan``) yields each merged position's source record, so every column is
    one gather from ``a`` or ``b``: no sort, no scatter. Returns a tuple of ``(Ca + Cb,)``
    arrays."""
    ca, cb = a[0].shape[0], b[0].shape[0]
    key, _ = _merge_scan(a[0], a[1], b[0], b[1])
    src = key.T.reshape(-1)[:ca + cb]  # chunk-major: merged order
    from_a = src >= 0
    ia, ib = jnp.clip(src, 0, ca - 1), jnp.clip(~src, 0, cb - 1)
    return tuple(jnp.where(from_a, x[ia], y[ib]) for x, y in zip(a, b))


# ----------------------------------------------------------------------------- two-word code arithmetic on word columns
# A code is (hi, lo) int32 words of 24 bits = 8 octal digits each; digit k (0 = finest level)
# lives in lo for k < 8, in hi for 8 <= k < 16, and digit 16 (only for the end 2^48 of the
# whole volume) is bit 24 of hi. Level indices k may be traced. Everything below is
# elementwise and loop-free (XLA fuses it into one pass).


def _digit_position(k):
    """``(in_hi, shift within the word)`` of octal digit ``k`` (0..16)."""
    in_hi = k >= 8
    return in_hi, jnp.where(in_hi, 3 * (k - 8), 3 * k)


def code_digit(hi, lo, k):
    """Octal digit ``k`` (0 = finest level, 16 = the bit of 2^48) of codes ``(hi, lo)``."""
    in_hi, sh = _digit_position(k)
    return jnp.right_shift(jnp.where(in_hi, hi, lo), sh) & 7


def code_low_masks(k):
    """``(hi_mask, lo_mask)`` of the octal digits below level ``k`` (0..16)."""
    return low_bit_masks(3 * k)


def code_low_nonzero(hi, lo, k):
    """Any digit below level ``k`` non-zero (``code mod 8^k != 0``)."""
    hm, lm = code_low_masks(k)
    return ((lo & lm) != 0) | ((hi & hm) != 0)


def code_truncate(hi, lo, k):
    """Codes ``(hi, lo)`` with the digits below level ``k`` cleared (the min corner of the
    enclosing node at depth ``16 - k``)."""
    hm, lm = code_low_masks(k)
    return hi & ~hm, lo & ~lm


def code_put_digit(hi, lo, k, val):
    """Or ``val`` (0..7) into digit ``k`` (which must be clear) of codes ``(hi, lo)``."""
    in_hi, sh = _digit_position(k)
    v = jnp.left_shift(val, sh)
    return jnp.where(in_hi, hi | v, hi), jnp.where(in_hi, lo, lo | v)


def code_end(hi, lo, depth):
    """Exclusive end ``code + 8^(16 - depth)`` of nodes at ``depth`` as words ``(hi, lo)``;
    the end of the whole key space (2^48) is ``(SENTINEL_HI, 0)``."""
    shift = 3 * (TREE_DEPTH - depth)
    small = shift < WORD_BITS
    lo = lo + jnp.where(small, jnp.left_shift(1, jnp.minimum(shift, WORD_BITS - 1)), 0)
    carry = jnp.right_shift(lo, WORD_BITS)
    hi = hi + jnp.where(small, carry, jnp.left_shift(1, jnp.maximum(shift - WORD_BITS, 0)))
    return hi, lo & WORD_MASK


def code_digit_sum(hi, lo):
    """Sum of the 16 octal digits of codes ``(hi, lo)``, loop-free: SWAR sums of digit pairs,
    then of quads, in each word."""

    def word(w):
        v = (w & 0o07070707) + (jnp.right_shift(w, 3) & 0o07070707)
        v = (v & 0o00770077) + (jnp.right_shift(v, 6) & 0o00770077)
        return (v & 0xFFF) + jnp.right_shift(v, 12)

    return word(hi) + word(lo)
