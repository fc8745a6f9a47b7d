"""The capacity policies of fusion, in one place: how many rows the output, the lists of gap
cells and of leaves with gaps, and ``fuse_many``'s boundary lists get, and the host loops
that re-run a kernel larger when a list proved short, and the host count of the common
refinement that sizes the output before the device counts it. Why these sizes:
``docs/design.md``, "Gap-cell lists" and "Bucket sizing of the output".
"""

from __future__ import annotations

import numpy as np

from .. import morton
from .._ops import bucket_capacity
from ..budget import check_allocation

# Host defaults, shares of the output's rows with a floor: gap cells are a few per cent of a
# refinement at most, and leaves with gaps fewer than their cells.
GAP_SHARE = 8  # gap-cell list: capacity / 8 rows
GAP_LEAF_SHARE = 16  # the pair kernel's list of leaves with gaps: capacity / 16 rows
GAP_MIN = 512  # floor of both lists, so small outputs never re-run for a few gaps
ROW_BYTES = 192  # host/device bytes per output row at the pair kernel's peak (estimate)


def default_gap_capacity(capacity: int) -> int | None:
    """Rows of the gap-cell list for an output of ``capacity`` rows, so that the gap layout
    runs on a short list instead of every output slot: ``max(capacity / 8, 512)``, or
    ``None`` (the per-slot layout) when the list would not be smaller."""
    room = max(int(capacity) // GAP_SHARE, GAP_MIN)
    return room if room < capacity else None


def default_gap_leaves(capacity: int) -> int:
    """Rows of the pair kernel's list of leaves with gaps for an output of ``capacity`` rows,
    so that only those leaves compute their gaps: ``max(capacity / 16, 512)``."""
    return max(int(capacity) // GAP_LEAF_SHARE, GAP_MIN)


def list_size(n: int) -> int:
    """Rows of a ``fuse_many`` boundary list of ``n`` entries, sized to the maps' contents
    rather than their capacities: ``n`` rounded up to an eighth of its power-of-two bucket
    (8 sizes per octave, so few compilations)."""
    step = max(bucket_capacity(n) // 8, 64)
    return -(-max(int(n), 1) // step) * step


def sized_gaps(kernel, cap: int, traced: bool, gap_capacity):
    """``kernel(cap, gap_capacity, gap_leaves) -> (map, report, (gap cells, leaves with
    gaps))`` with the gap lists sized: on the host (``gap_capacity=None``)
    ``default_gap_capacity`` cells and ``default_gap_leaves`` leaves, re-run with room for all
    when there are more; under ``jit``/``vmap`` as given (``None``: every slot, never short;
    the leaf list as long as the cell list). Returns ``(map, report)``."""
    leaves = None
    if not traced:
        gap_capacity = default_gap_capacity(cap) if gap_capacity is None else gap_capacity
        if gap_capacity is not None and gap_capacity >= cap:
            gap_capacity = None  # no shorter than the output: the per-slot layout, never short
        leaves = None if gap_capacity is None else min(gap_capacity, default_gap_leaves(cap))
    out, rep, (n_gap, n_leaves) = kernel(cap, gap_capacity, leaves)
    # the cell count is exact when the list held every leaf with gaps, else a lower bound
    # (the pair kernel), so a second re-run may be needed
    while not traced and gap_capacity is not None:
        n_gap, n_leaves = int(n_gap), int(n_leaves)
        if n_gap <= gap_capacity and n_leaves <= leaves:
            break
        leaves = max(leaves, bucket_capacity(n_leaves))
        if n_gap > gap_capacity:
            more = bucket_capacity(n_gap)
            gap_capacity = more if more < cap else None
        out, rep, (n_gap, n_leaves) = kernel(cap, gap_capacity, leaves)
    return out, rep


def sized_output(run, guess: int, capacity: int | None, traced: bool, what: str):
    """``run(cap) -> (map, report)`` at ``capacity`` rows, or, when it is ``None`` (host
    only), at the bucket of ``guess`` cells, re-run at the refinement's own bucket while it
    does not fit. Returns ``(map, report)``; raises ``ValueError`` naming ``what`` when no
    capacity is given under ``jit``/``vmap``."""
    if capacity is not None:
        if not traced:
            _check_rows(int(capacity), what)
        return run(int(capacity))
    if traced:
        raise ValueError(f"{what}: pass a static capacity= when calling under jit/vmap")
    cap = bucket_capacity(guess)
    _check_rows(cap, what)
    out, rep = run(cap)
    while int(rep.refined_cells) > cap:  # a lower bound when it overflowed: re-run larger
        cap = bucket_capacity(int(rep.refined_cells))
        _check_rows(cap, what)
        out, rep = run(cap)
    return out, rep


def _check_rows(cap: int, what: str) -> None:
    """``budget.check_allocation`` for an output of ``cap`` rows (``ROW_BYTES`` each)."""
    check_allocation(cap * ROW_BYTES, f"{what}: the union of the maps' leaves ({cap} rows)")


def _host_leaves(m) -> tuple[np.ndarray, np.ndarray]:
    """A map's leaves on the host: ``(codes (n,) int64, depths (n,) int64)``, in Morton order."""
    n = int(m.count)
    return morton.join_codes(np.asarray(m.code)[:n]).astype(np.int64), np.asarray(m.depth)[:n].astype(np.int64)


def _split_leaves(codes, depths, codes_b, depths_b) -> tuple[int, int, int]:
    """The leaves ``(codes, depths)`` of one map strictly inside a coarser leaf of the other map
    ``(codes_b, depths_b)`` (both sorted): ``(how many coarse leaves hold them, how many they
    are, the cells those coarse leaves split into)``. Inside a coarse leaf the cells are the
    leaves of the smallest tree holding the finer leaves, 1 + 7 per internal node, and the
    internal nodes are the finer leaves' distinct ancestors from the coarse leaf's depth down."""
    if len(codes) == 0 or len(codes_b) == 0:
        return 0, 0, 0
    j = np.clip(np.searchsorted(codes_b, codes, side="right") - 1, 0, len(codes_b) - 1)
    end = codes_b[j] + (np.int64(1) << (3 * (morton.TREE_DEPTH - depths_b[j])))
    inside = (codes >= codes_b[j]) & (codes < end) & (depths_b[j] < depths)
    fine, fine_depth, coarse_depth = codes[inside], depths[inside], depths_b[j[inside]]
    split = len(np.unique(j[inside]))
    internal = 0
    for depth in range(morton.TREE_DEPTH):
        at = (fine_depth > depth) & (coarse_depth <= depth)
        if at.any():
            node = fine[at] >> (3 * (morton.TREE_DEPTH - depth))  # sorted: count the changes
            internal += 1 + int(np.count_nonzero(node[1:] != node[:-1]))
    return split, len(fine), split + 7 * internal


def refinement_cells(m1, m2) -> tuple[int, int]:
    """The cells of two maps' common refinement and how many of them are gap cells, counted on
    the host from their leaves in ``O(n log n)`` (``plan_pair`` counts them on the device as
    ``total`` and ``gap_cells``): ``(cells, gap cells)``. Leaves of equal code and depth make
    one cell; a leaf inside a coarser leaf of the other map splits that leaf into the leaves of
    the smallest tree holding every finer leaf inside it, and those no finer leaf fills are gap
    cells (thesis §5.2.3, case 1 inside cases 3 / 4). Raises ``budget.MemoryBudgetError`` when
    its host arrays (about 64 bytes per leaf) would pass the memory budget."""
    check_allocation((int(m1.count) + int(m2.count)) * 64,
                     f"counting the common refinement of {int(m1.count)} + {int(m2.count)} leaves on the host")
    (c1, d1), (c2, d2) = _host_leaves(m1), _host_leaves(m2)
    k1, k2 = c1 * 32 + d1, c2 * 32 + d2  # unique and sorted: the leaves of a map are disjoint
    shared = 0
    if len(k1) and len(k2):
        shared = int(np.count_nonzero(k1[np.clip(np.searchsorted(k1, k2), 0, len(k1) - 1)] == k2))
    cells, gaps = len(c1) + len(c2) - shared, 0
    for side in ((c1, d1, c2, d2), (c2, d2, c1, d1)):
        split, fine, split_cells = _split_leaves(*side)
        cells += split_cells - split - fine  # the coarse leaf's cells replace it and the finer leaves
        gaps += split_cells - fine
    return cells, gaps
