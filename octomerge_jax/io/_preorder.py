"""Vectorised (NumPy) conversion between sorted leaf arrays and OctoMap's pre-order node stream.

Both OctoMap formats serialise the octree depth-first, pre-order, children visited 0..7
(``OcTreeBaseImpl::writeNodesRecurs``, ``OccupancyOcTreeBase::writeBinaryNode``). A Python
loop per node would take seconds on a million-leaf map, so both directions are whole-array
NumPy passes (I/O is host work; a jitted ``lax.scan`` over the records is no faster).

**Writing** (leaves -> stream). Pre-order visits leaves in Morton order, so the stream is the
sorted leaves with each leaf preceded by the ancestors it *opens*: the nodes on its path
deeper than its common ancestor with the previous leaf, whose depth comes from the highest
differing bit of consecutive codes. The first node a leaf opens is a later sibling in an
existing parent; every other one is the first child of the record before it. Each node's
child description (``.ot`` child mask and inner value = max of children, ``.bt`` 2-bit
child states) is a segment reduction (``ufunc.reduceat``) over its children, level by level
from depth 16 up: records of one depth, in stream order, are sorted by code, so siblings
are contiguous runs, and each run starts at a first child.

**Reading** (stream -> leaves). A pre-order stream with per-record child counts ``g`` is a
Lukasiewicz word: the pending-slot count ``h[k] = 1 + sum_{i<k} (g[i] - 1)`` stays >= 1
inside the tree and first hits 0 right after its last record, which also gives the tree's
length without a header. Record k's depth is ``k`` minus the number of subtrees that ended
before it; the subtree of record s ends right before the first later position where
``h == h[s] - 1`` (``h`` drops by at most 1 per record), and one stable radix sort over
``h`` (<= 1 + 7*16 for a depth-16 tree) counts those ends. With depths known, a record's
parent is the record before it if that one has children, else the parent of the previous
record of the same depth (its previous sibling), and codes follow top-down.
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


def validate_leaves(codes: np.ndarray, depths: np.ndarray) -> None:
    """``ValueError`` unless codes are strictly increasing, aligned to their depths and the
    leaves disjoint (the ``OccupancyMap`` invariants the writers rely on)."""
    if codes.size and not np.all(codes[1:] > codes[:-1]):
        raise ValueError("leaf codes must be strictly increasing (an invalid OccupancyMap)")
    if np.any(depths > TREE_DEPTH):
        raise ValueError("leaf depths must lie in 0..16")
    if np.any(codes & ~MASKS[depths]):
        raise ValueError("a leaf code is not aligned to its depth (not a min-corner code)")
    morton.group_sizes(codes, depths)  # raises if leaves overlap


class Layout(NamedTuple):
    """Nodes of the tree over some leaves, in pre-order (= the file's record order)."""

    depth: np.ndarray  # (T,) uint8
    child_index: np.ndarray  # (T,) uint8, index of each node within its parent (root: 0)
    opened: np.ndarray  # (T,) bool, node is its parent's first child (root: False)
    leaf_record: np.ndarray  # (n,) int64, the record of each leaf


#: ``_DIGIT_SHIFT[d]``: the octal digit of a code that selects a depth-d node in its parent.
_DIGIT_SHIFT = np.array([48] + [3 * (TREE_DEPTH - d) for d in range(1, TREE_DEPTH + 1)],
                        dtype=np.uint64)


def layout(codes: np.ndarray, depths: np.ndarray) -> Layout:
    """Pre-order node records of the tree whose leaves are ``codes``/``depths`` (sorted,
    disjoint, depth >= 1 so that the root is an inner node).

    Leaf i opens the records ``depth = D_i + 1 .. depth_i`` (``D_i`` its common depth with
    leaf i-1). The first record a leaf opens continues an existing parent (a later
    sibling); every other record is the first child of the record before it.
    """
    counts = morton.group_sizes(codes, depths)
    total = int(counts.sum())
    ends = np.cumsum(counts)
    starts = ends - counts
    depths8 = depths.astype(np.int8)
    step = np.ones(total, dtype=np.int8)  # depth increments along the stream
    step[0] = 0
    step[starts[1:]] = (depths8[1:] - counts[1:].astype(np.int8) + 1) - depths8[:-1]
    rec_depth = np.cumsum(step, dtype=np.int8).view(np.uint8)
    opened = np.ones(total, dtype=bool)
    opened[starts] = False
    child_index = ((np.repeat(codes, counts) >> _DIGIT_SHIFT[rec_depth]) & _U64(7)).astype(
        np.uint8)
    return Layout(rec_depth, child_index, opened, ends - 1)


def levels(lay: Layout):
    """Yield, for depth ``e`` = 16..1, ``(kids, starts, parents, child_index)``: ``kids`` the
    records at depth e in stream order (siblings are contiguous runs), ``starts`` the start
    of each run within ``kids`` (its first child), ``parents`` each run's parent record
    (the record before its first child), ``child_index`` (0..7) of each kid."""
    order = np.argsort(lay.depth, kind="stable")  # radix sort: uint8 keys
    bounds = np.concatenate([[0], np.cumsum(np.bincount(lay.depth, minlength=TREE_DEPTH + 1))])
    for e in range(TREE_DEPTH, 0, -1):
        kids = order[bounds[e]: bounds[e + 1]]
        if kids.size == 0:
            continue
        starts = np.flatnonzero(lay.opened[kids])
        yield kids, starts, kids[starts] - 1, lay.child_index[kids]


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
    for kids, starts, parents, ci in levels(lay):
        # OctoMap's max starts at -FLT_MAX and takes ``l > max``: fmax ignores NaN likewise.
        value[parents] = np.fmax.reduceat(value[kids], starts)
        mask[parents] = np.bitwise_or.reduceat(bit[ci], starts)
    rec = 5 + payload_extra
    out = np.zeros((total, rec), dtype=np.uint8)
    out[:, :4] = value.astype("<f4").view(np.uint8).reshape(total, 4)
    out[:, rec - 1] = mask
    return out.reshape(-1), total


# ----------------------------------------------------------------------------- stream -> tree


def tree_length(degree: np.ndarray) -> tuple[int, np.ndarray]:
    """Length ``N`` of the pre-order tree at the start of a record stream with child counts
    ``degree``, and the pending-slot path ``h[0..N]`` (``h[N] == 0``).

    Raises ``StreamError`` if the stream ends before the tree does, or the path climbs past
    what a depth-16 tree allows (at the record where it does).
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


def record_depths(h: np.ndarray) -> np.ndarray:
    """Depth ``(N,)`` int64 of each record of a valid pre-order tree from its path ``h``.

    ``depth[k] = depth[k-1] + 1 - closes[k-1]`` where ``closes[j]`` counts the subtrees
    ending at record j, so ``depth[k] = k - sum_{j<k} closes[j]``. Subtree of record s
    ends right before the first later position where ``h == h[s] - 1`` (``h`` drops by at
    most 1 per record). Sorting entries ``2 h[m]`` (positions) and ``2 (h[s] - 1)`` (subtree
    starts) stably by key (one radix sort over uint8) puts every subtree start just before
    the position that ends it, so ``closes`` is a count between consecutive positions.
    """
    n = h.size - 1
    key = np.empty(2 * n + 1, dtype=np.uint8)
    key[0::2] = 2 * h
    key[1::2] = 2 * h[:n] - 2
    order = np.argsort(key, kind="stable")
    is_start = (order & 1).astype(bool)
    starts_before = np.cumsum(is_start)
    positions = np.flatnonzero(~is_start)
    ends_here = np.diff(starts_before[positions], prepend=0)
    closes_before = np.zeros(n + 1, dtype=np.int64)  # at position m: subtrees ending at m-1
    closes_before[order[positions] >> 1] = ends_here
    return np.arange(n, dtype=np.int64) - np.cumsum(closes_before[:n])


class StreamLayout(NamedTuple):
    """Records of a parsed stream: depth, min-corner code, and the depth-major order."""

    depth: np.ndarray  # (N,) uint8
    code: np.ndarray  # (N,) uint64
    order: np.ndarray  # (N,) int64: records sorted by depth, stream order within a depth
    bounds: np.ndarray  # (18,) start of each depth in ``order``


def stream_layout(child_mask: np.ndarray, h: np.ndarray, max_depth: int) -> StreamLayout:
    """Depth and Morton code of each record of a pre-order stream.

    ``child_mask[k]`` has bit j set iff child j of record k is itself a record (follows in
    the stream); ``h`` from ``tree_length``. A record's parent is the previous record if
    that one has children (it is a first child), else the parent of its previous sibling,
    which is the previous record of the same depth; its rank among the siblings gives its
    child index (the rank-th set bit of the parent's mask). Codes follow top-down, one depth
    at a time. Records deeper than ``max_depth`` raise ``StreamError``.
    """
    n = child_mask.size
    depth = record_depths(h)
    too_deep = np.flatnonzero(depth > max_depth)
    if too_deep.size:
        k = int(too_deep[0])
        raise StreamError(k - 1, f"a node at depth {int(depth[k]) - 1} has children "
                                 f"(deeper than {max_depth} levels)")
    depth8 = depth.astype(np.uint8)
    order = np.argsort(depth8, kind="stable")
    d_sorted = depth8[order].astype(np.int64)
    first_child = np.empty(n, dtype=bool)
    first_child[0] = True
    first_child[1:] = child_mask[:-1] != 0
    fc_sorted = first_child[order]
    # parent: forward-fill "previous record" from each first child along its depth block
    # (offset by depth so the running max never crosses into the next block)
    key = np.where(fc_sorted, d_sorted * (n + 1) + order - 1, -1)
    parent = np.maximum.accumulate(key) - d_sorted * (n + 1)
    idx = np.arange(n, dtype=np.int64)
    rank = idx - np.maximum.accumulate(np.where(fc_sorted, idx, 0))
    parent[0] = 0
    child = NTH_BIT8.reshape(-1)[child_mask[parent].astype(np.int64) * 8 + rank]
    bounds = np.searchsorted(d_sorted, np.arange(TREE_DEPTH + 2))
    code = np.zeros(n, dtype=np.uint64)
    for e in range(1, TREE_DEPTH + 1):
        a, b = int(bounds[e]), int(bounds[e + 1])
        if a == b:
            break
        code[order[a:b]] = code[parent[a:b]] | (child[a:b].astype(np.uint64)
                                                << _U64(3 * (TREE_DEPTH - e)))
    return StreamLayout(depth8, code, order, bounds)


# ----------------------------------------------------------------------------- .bt, fused


def _merge_sorted(a_codes, a_vals, b_codes, b_vals):
    """Merge two code-sorted runs (disjoint codes) into one."""
    if not b_codes.size:
        return a_codes, a_vals
    if not a_codes.size:
        return b_codes, b_vals
    codes = np.concatenate([a_codes, b_codes])
    order = np.argsort(codes, kind="stable")  # two sorted runs: a linear merge
    return codes[order], np.concatenate([a_vals, b_vals])[order]


def run_starts(keys: np.ndarray):
    """Runs of equal values in sorted ``keys (n,)``, ``n >= 1``: ``(starts, lengths)``."""
    new_run = np.empty(keys.size, bool)
    new_run[0] = True
    np.not_equal(keys[1:], keys[:-1], out=new_run[1:])
    starts = np.flatnonzero(new_run)
    return starts, np.diff(np.append(starts, keys.size))


def equal_sibling_blocks(parent: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Indices ``(k, 8)`` of the complete sibling groups whose values are all equal (exact
    float ``==``, like ``OcTreeNode::operator==``): runs of exactly 8 equal entries of sorted
    ``parent (n,)`` (the parents' codes of sorted leaves of one depth), ``values (n,)``."""
    starts, lengths = run_starts(parent)
    block = starts[lengths == 8][:, None] + np.arange(8)
    vals = values[block]
    return block[np.all(vals == vals[:, :1], axis=1)]


def encode_bt_pruned(codes, depths, log_odds, threshold, clamp_min, clamp_max):
    """``.bt`` body of OctoMap's ``toMaxLikelihood(); prune(); writeBinaryConst()`` for the
    tree over the given leaves (sorted codes, depth >= 1), in one bottom-up pass.

    Level by level from depth 16: the children of depth ``e - 1`` nodes are the leaves of
    depth e and the inner nodes found at the level below. While pruning is on, a parent
    whose 8 children are leaves of equal maximum-likelihood value becomes a leaf of depth
    ``e - 1`` (``pruneNode``); the first level with no such parent turns pruning off
    (``prune()`` stops there; the root, depth 0, is never pruned). The other parents are
    inner nodes; their 2-bit child states are a segment OR. Inner nodes are then put in
    pre-order, sorted by (code, depth). Returns (bytes array, node count).
    """
    values = np.where(log_odds >= threshold, clamp_max, clamp_min).astype(np.float32)
    order = np.argsort(depths, kind="stable")
    bounds = np.searchsorted(depths[order], np.arange(TREE_DEPTH + 2))
    pruning = True
    carry_codes = np.zeros(0, np.uint64)  # leaves made by pruning at the level below
    carry_vals = np.zeros(0, np.float32)
    inner_codes = np.zeros(0, np.uint64)  # inner nodes of the current depth, sorted
    inner_words = np.zeros(0, np.uint16)
    out_codes, out_words, out_depths = [], [], []
    n_leaves = 0
    for e in range(TREE_DEPTH, 0, -1):
        idx = order[bounds[e]: bounds[e + 1]]
        leaf_codes, leaf_vals = _merge_sorted(codes[idx], values[idx], carry_codes, carry_vals)
        carry_codes, carry_vals = np.zeros(0, np.uint64), np.zeros(0, np.float32)
        if not leaf_codes.size and not inner_codes.size:
            pruning = False  # nothing to collapse at depth e - 1: prune() stops here
            continue
        mask = MASKS[e - 1]
        if pruning and e >= 2:
            collapsed = False
            if leaf_codes.size >= 8:
                parent = leaf_codes & mask
                block = equal_sibling_blocks(parent, leaf_vals)
                if block.size:
                    collapsed = True
                    first = block[:, 0]
                    carry_codes, carry_vals = parent[first], leaf_vals[first]
                    keep = np.ones(parent.size, bool)
                    keep[block] = False
                    leaf_codes, leaf_vals = leaf_codes[keep], leaf_vals[keep]
            pruning = collapsed
        n_leaves += leaf_codes.size
        leaf_state = np.where(leaf_vals >= threshold, 2, 1).astype(np.uint16)
        kid_codes, kid_state = _merge_sorted(leaf_codes, leaf_state, inner_codes,
                                             np.full(inner_codes.size, 3, np.uint16))
        if not kid_codes.size:
            inner_codes, inner_words = np.zeros(0, np.uint64), np.zeros(0, np.uint16)
            continue
        parent = kid_codes & mask
        starts, _ = run_starts(parent)
        child = ((kid_codes >> _U64(3 * (TREE_DEPTH - e))) & _U64(7)).astype(np.uint16)
        inner_words = np.bitwise_or.reduceat(kid_state << (2 * child), starts)
        inner_codes = parent[starts]
        out_codes.append(inner_codes)
        out_words.append(inner_words)
        out_depths.append(np.full(inner_codes.size, e - 1, np.uint64))
    if not out_codes:
        return np.zeros(0, np.uint8), 0
    all_codes = np.concatenate(out_codes)
    key = (all_codes << _U64(5)) | np.concatenate(out_depths)  # pre-order: (code, depth)
    words = np.concatenate(out_words)[np.argsort(key, kind="stable")]
    return words.astype("<u2").view(np.uint8), n_leaves + int(all_codes.size)
