"""Vectorised (NumPy) conversion between sorted leaf arrays and OctoMap's pre-order node stream.

Both OctoMap formats serialise the octree depth-first, pre-order, children visited 0..7
(``OcTreeBaseImpl::writeNodesRecurs``, ``OccupancyOcTreeBase::writeBinaryNode``). A Python
loop per node would take seconds on a million-leaf map, so both directions are written as
whole-array NumPy passes (I/O is host work; measured faster than a jitted ``lax.scan``, whose
per-step overhead is ~1 us on CPU):

**Writing** (leaves -> stream). Pre-order visits leaves in Morton order, so the stream is the
sorted leaves with each leaf preceded by the ancestors it *opens*: the nodes on its path
deeper than its common ancestor with the previous leaf. That common depth comes from the
highest differing bit of consecutive codes, so the records are one ``np.repeat``. Each
node's child description (``.ot`` child mask, ``.bt`` 2-bit child states, ``.ot`` inner
value = max of children) is a segment reduction (``ufunc.reduceat``) over its children,
done level by level from depth 16 up (records of one depth, in stream order, are sorted by
code, so siblings are contiguous runs).

**Reading** (stream -> leaves). A pre-order stream with per-record child counts ``g`` is a
Lukasiewicz word: the pending-slot count ``h[k] = 1 + sum_{i<k} (g[i] - 1)`` stays >= 1
inside the tree and first hits 0 right after its last record, which also gives the tree's
length without a header. ``h`` drops by at most 1 per record, so the end of the subtree
rooted at record ``k`` is the first later position where ``h == h[k] - 1`` (the "next
drop"); with ``h <= 1 + 7*16`` for a depth-16 tree, all next drops come from one stable
radix sort by ``h``. A node's first child is the next record and each further child starts
where the previous child's subtree ends, so a breadth-first pass over at most 17 levels
assigns every record its depth and Morton code.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .. import morton

TREE_DEPTH = morton.TREE_DEPTH
MAX_PENDING = 1 + 7 * TREE_DEPTH  # largest pending-slot count of a valid depth-16 tree

_U64 = np.uint64
_BITS48 = (1 << 48) - 1
#: ``MASKS[d]`` keeps the top ``d`` octal digits of a 48-bit code (min corner at depth d).
MASKS = np.array([_BITS48 & ~((1 << (3 * (TREE_DEPTH - d))) - 1) for d in range(TREE_DEPTH + 1)],
                 dtype=np.uint64)
#: ``POPCOUNT8[m]``: number of set bits of a byte.
POPCOUNT8 = np.array([bin(i).count("1") for i in range(256)], dtype=np.uint8)
#: ``NTH_BIT8[m, r]``: index of the r-th set bit of byte m (0 where it has fewer bits).
NTH_BIT8 = np.zeros((256, 8), dtype=np.uint8)
for _m in range(256):
    _bits = [j for j in range(8) if _m >> j & 1]
    NTH_BIT8[_m, : len(_bits)] = _bits
del _m, _bits


class StreamError(Exception):
    """Structural error at record ``record`` of a stream (converted to ``MapFormatError``)."""

    def __init__(self, record: int, reason: str):
        super().__init__(reason)
        self.record = int(record)
        self.reason = reason


# ----------------------------------------------------------------------------- leaves -> tree


def common_depths(codes: np.ndarray) -> np.ndarray:
    """Depth of the deepest common ancestor of consecutive sorted codes, ``(n-1,)`` int64.

    For distinct codes the highest differing bit ``b`` lies in octal digit ``b // 3`` from
    the bottom, i.e. the codes part below depth ``15 - b // 3``.
    """
    x = codes[1:] ^ codes[:-1]
    if x.size and not x.all():
        raise ValueError("leaf codes must be distinct")
    _, bitlen = np.frexp(x.astype(np.float64))  # exact: x < 2^48; bitlen = b + 1
    return 15 - (bitlen.astype(np.int64) - 1) // 3


def group_sizes(codes: np.ndarray, depths: np.ndarray) -> np.ndarray:
    """Per leaf, how many stream records it opens (its new ancestors and itself), ``(n,)``.

    Raises ``ValueError`` if leaves overlap (a leaf inside another's volume).
    """
    depths = depths.astype(np.int64)
    d_common = np.concatenate([[-1], common_depths(codes)])
    if np.any(d_common[1:] >= np.minimum(depths[1:], depths[:-1])):
        raise ValueError("leaves overlap: one leaf lies inside another")
    return depths - d_common


def num_nodes(codes, depths) -> int:
    """OctoMap ``size()`` of the tree whose leaves are the given sorted, disjoint leaves:
    leaves plus every distinct ancestor, root included (0 for no leaves)."""
    codes = np.asarray(codes, dtype=np.uint64)
    if codes.size == 0:
        return 0
    return int(group_sizes(codes, np.asarray(depths)).sum())


class Layout(NamedTuple):
    """Nodes of the tree over some leaves, in pre-order (= the file's record order)."""

    depth: np.ndarray  # (T,) uint8
    code: np.ndarray  # (T,) uint64 min-corner code of each node
    is_leaf: np.ndarray  # (T,) bool
    leaf_record: np.ndarray  # (n,) int64, the record of each leaf


def layout(codes: np.ndarray, depths: np.ndarray) -> Layout:
    """Pre-order node records of the tree whose leaves are ``codes``/``depths`` (sorted,
    disjoint, depth >= 1 so that the root is an inner node)."""
    counts = group_sizes(codes, depths)
    total = int(counts.sum())
    ends = np.cumsum(counts)
    starts = ends - counts
    first_depth = depths.astype(np.int64) - counts + 1  # depth of the first record opened
    rec_depth = (np.arange(total, dtype=np.int64)
                 - np.repeat(starts - first_depth, counts)).astype(np.uint8)
    rec_code = np.repeat(codes, counts) & MASKS[rec_depth]
    is_leaf = np.zeros(total, dtype=bool)
    leaf_record = ends - 1
    is_leaf[leaf_record] = True
    return Layout(rec_depth, rec_code, is_leaf, leaf_record)


def levels(lay: Layout):
    """Yield, for depth ``e`` = 16..1, ``(e, kids, starts, parents, child_index)``:
    ``kids`` the records at depth e in stream order, ``starts`` the start of each sibling run
    within ``kids``, ``parents`` the record of each run's parent, ``child_index`` (0..7) of
    each kid within its parent."""
    order = np.argsort(lay.depth, kind="stable")  # radix sort: uint8 keys
    bounds = np.concatenate([[0], np.cumsum(np.bincount(lay.depth, minlength=TREE_DEPTH + 1))])
    for e in range(TREE_DEPTH, 0, -1):
        kids = order[bounds[e]: bounds[e + 1]]
        if kids.size == 0:
            continue
        kid_codes = lay.code[kids]
        pc = kid_codes & MASKS[e - 1]
        new_run = np.empty(kids.size, dtype=bool)
        new_run[0] = True
        np.not_equal(pc[1:], pc[:-1], out=new_run[1:])
        starts = np.flatnonzero(new_run)
        above = order[bounds[e - 1]: bounds[e]]
        parents = above[~lay.is_leaf[above]]
        if parents.size != starts.size:  # pragma: no cover - impossible for a valid layout
            raise AssertionError("inconsistent layout")
        child_index = ((kid_codes >> _U64(3 * (TREE_DEPTH - e))) & _U64(7)).astype(np.uint8)
        yield e, kids, starts, parents, child_index


def encode_ot(codes, depths, log_odds, payload_extra: int = 0) -> tuple[np.ndarray, int]:
    """``.ot`` body of the tree over the given leaves (``depth >= 1``): per node in pre-order
    float32 log-odds (inner node = max of its children, ``getMaxChildLogOdds``), then
    ``payload_extra`` zero bytes, then the child mask byte. Returns (bytes array, nodes)."""
    if codes.size == 0:
        return np.zeros(0, np.uint8), 0
    lay = layout(codes, depths)
    total = lay.depth.size
    value = np.empty(total, dtype=np.float32)
    value[lay.leaf_record] = log_odds
    mask = np.zeros(total, dtype=np.uint8)
    bit = (np.uint8(1) << np.arange(8, dtype=np.uint8))
    for _e, kids, starts, parents, ci in levels(lay):
        # OctoMap's max starts at -FLT_MAX and takes ``l > max``: fmax ignores NaN likewise.
        value[parents] = np.fmax.reduceat(value[kids], starts)
        mask[parents] = np.bitwise_or.reduceat(bit[ci], starts)
    rec = 5 + payload_extra
    out = np.zeros((total, rec), dtype=np.uint8)
    out[:, :4] = value.astype("<f4").view(np.uint8).reshape(total, 4)
    out[:, rec - 1] = mask
    return out.reshape(-1), total


def encode_bt(codes, depths, occupied) -> tuple[np.ndarray, int]:
    """``.bt`` body of the tree over the given leaves (``depth >= 1``): per *inner* node in
    pre-order two bytes of 2-bit child states (``writeBinaryNode``: 0 unknown, 1 free leaf,
    2 occupied leaf, 3 inner; child j at bits 2(j%4) of byte j//4). Returns (bytes, nodes)."""
    if codes.size == 0:
        return np.zeros(0, np.uint8), 0
    lay = layout(codes, depths)
    total = lay.depth.size
    state = np.full(total, 3, dtype=np.uint16)
    state[lay.leaf_record] = np.where(occupied, 2, 1).astype(np.uint16)
    word = np.zeros(total, dtype=np.uint16)
    for _e, kids, starts, parents, ci in levels(lay):
        contrib = state[kids] << (2 * ci.astype(np.uint16))
        word[parents] = np.bitwise_or.reduceat(contrib, starts)
    inner = word[~lay.is_leaf]
    return inner.astype("<u2").view(np.uint8), total


# ----------------------------------------------------------------------------- stream -> tree


def tree_length(degree: np.ndarray) -> tuple[int, np.ndarray]:
    """Length ``N`` of the pre-order tree at the start of a record stream with child counts
    ``degree``, and the pending-slot path ``h[0..N]``.

    Raises ``StreamError`` if the stream ends before the tree does, or the path climbs past
    what a depth-16 tree allows (the record where it does).
    """
    n = degree.size
    h = np.empty(n + 1, dtype=np.int64)
    h[0] = 1
    np.cumsum(degree.astype(np.int64) - 1, out=h[1:])
    h[1:] += 1
    zeros = np.flatnonzero(h[1:] == 0)
    length = int(zeros[0]) + 1 if zeros.size else n
    h = h[: length + 1]
    high = np.flatnonzero(h > MAX_PENDING)
    if high.size:
        raise StreamError(max(int(high[0]) - 1, 0),
                          "the tree is deeper than 16 levels (corrupt child flags)")
    if not zeros.size:
        raise StreamError(n, f"data ends inside the tree ({int(h[-1])} more child nodes "
                             "announced than present): truncated")
    return length, h


def next_drop(h: np.ndarray) -> np.ndarray:
    """``out[k]`` = first ``m > k`` with ``h[m] == h[k] - 1`` (the end of record k's subtree),
    for a path with ``h[:-1] >= 1``, ``h[-1] == 0``, steps >= -1 and values <= 255.

    One stable (radix) sort groups positions by value; within group ``v - 1`` the answer
    is the first position after ``k`` (``searchsorted`` with sorted needles).
    """
    n1 = h.size
    order = np.argsort(h.astype(np.uint8), kind="stable")
    hv = h[order]
    first = int(np.searchsorted(hv, 1))  # group 0 holds only the final position
    keys = hv * n1 + order
    needles = order[first:]
    found = np.searchsorted(keys, (hv[first:] - 1) * n1 + needles, side="right")
    out = np.empty(n1 - 1, dtype=np.int64)
    out[needles] = order[found]
    return out


def breadth_first(child_mask: np.ndarray, nxt: np.ndarray, max_depth: int):
    """Depth ``(N,)`` uint8 and min-corner code ``(N,)`` uint64 of each stream record.

    ``child_mask[k]`` has bit j set iff child j of record k is itself a record (follows in
    the stream); ``nxt`` from ``next_drop``. Records deeper than ``max_depth`` raise
    ``StreamError``.
    """
    n = child_mask.size
    degree = POPCOUNT8[child_mask]
    depth = np.zeros(n, dtype=np.uint8)
    code = np.zeros(n, dtype=np.uint64)
    front = np.zeros(1, dtype=np.int64)
    front_code = np.zeros(1, dtype=np.uint64)
    visited = 0
    for d in range(TREE_DEPTH + 1):
        depth[front] = d
        code[front] = front_code
        visited += front.size
        g = degree[front]
        has = g > 0
        if not has.any():
            break
        if d + 1 > max_depth:
            raise StreamError(int(front[has][0]), f"a node at depth {d} has children "
                                                  f"(deeper than {max_depth} levels)")
        pos, cc, g = front[has] + 1, front_code[has], g[has]
        m = child_mask[front[has]]
        shift = _U64(3 * (TREE_DEPTH - 1 - d))
        kids, kid_codes = [], []
        for r in range(8):
            if r:
                sel = g > r
                if not sel.any():
                    break
                pos, cc, g, m = nxt[pos[sel]], cc[sel], g[sel], m[sel]
            kids.append(pos)
            kid_codes.append(cc | (NTH_BIT8[m, r].astype(np.uint64) << shift))
        front = np.concatenate(kids)
        front_code = np.concatenate(kid_codes)
    if visited != n:  # pragma: no cover - guaranteed by a valid pending-slot path
        raise StreamError(0, "inconsistent tree structure")
    return depth, code
