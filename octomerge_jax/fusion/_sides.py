"""The pair kernel's per-leaf plan: one merge of the two sorted leaf lists tells every leaf
of each map which leaf of the other map starts at or before it, hence whether it is covered
by an equal or coarser leaf (thesis §5.2.3 case 2 / 3), strictly contains finer leaves
(case 3 for M1, case 4 for M2: it is *split* and emits no cell itself), or lies in unknown
space (case 1); and which leaves have *gaps* (parts of a coarser leaf of the other map
before or after them that no leaf of their own map covers), listed compactly.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from .. import morton
from .._ops import any_of, count_true, cumsum, materialize
from ..map import OccupancyMap
from ._gaps import gap_cell_count
from ._layout import excl_at
from ._rules import combine, single


class SideStats(NamedTuple):
    """A side's report counts, int32 scalars."""

    equal: jax.Array  # leaves equal to a leaf of the other map (counted on side 0 only)
    split: jax.Array  # leaves split by finer leaves of the other map
    both: jax.Array  # own cells known to both maps
    new_self: jax.Array  # own cells unknown to the other map


class Side(NamedTuple):
    """Per-leaf plan of map A against map B, ``(Ca,)`` arrays (``Ca``: A's capacity)."""

    valid: jax.Array  # bool, a real leaf
    self_emit: jax.Array  # bool, the leaf emits its own cell (not split, not the 2nd of an equal pair)
    self_val: jax.Array  # float32, its combined, clamped log-odds
    le_other: jax.Array  # int32, B leaves with code <= the leaf's code
    has_gap: jax.Array  # bool, a nonempty gap before or after it inside a coarser B leaf
    any_gap: jax.Array  # () bool, any leaf has one
    stats: SideStats


class Pair(NamedTuple):
    """Both maps, the rule and both sides' plans."""

    maps: tuple  # (m1, m2) OccupancyMaps
    weights: tuple  # (w1, w2), () float32 each
    mode: jax.Array  # () int32 rule (``_rules.MODE``)
    clamp: tuple  # (lo, hi) () float32 log-odds, m1's clamping bounds
    sides: tuple  # (Side of m1 against m2, Side of m2 against m1)
    before: tuple  # ((C1,) int32 m2 leaves < each m1 leaf, (C2,) int32 m1 leaves <= each m2 leaf)


class LeafGaps(NamedTuple):
    """The gaps around listed leaves: before it ``[s, e)`` and after it, word columns
    ``(s_hi, s_lo, e_hi, e_lo)`` of ``(rows,)`` int32 each (empty: ``[x, x)``)."""

    before: tuple  # 4 x (rows,) int32
    after: tuple  # 4 x (rows,) int32
    value: jax.Array  # (rows,) float32 log-odds of their cells (the coarser leaf's, clamped)


class GapList(NamedTuple):
    """The leaves of both sides with a nonempty gap, in order (side 0's first), ``rows`` rows."""

    side: jax.Array  # (rows,) int32 0 / 1
    i: jax.Array  # (rows,) int32 leaf index on its side
    at: tuple  # 2 x (rows,) int32: ``i`` clipped into each side's rows
    ok: jax.Array  # (rows,) bool, a leaf is listed on the row
    gaps: LeafGaps
    n_before: jax.Array  # (rows,) int32 cells of the gap before (0 unless ``ok``)
    n_after: jax.Array  # (rows,) int32 cells of the gap after (0 unless ``ok``)
    leaves: jax.Array  # () int32 leaves with gaps in all
    missed: jax.Array  # () int32 those past the list (each has at least one gap cell)


def pair_sides(m1: OccupancyMap, m2: OccupancyMap, w1, w2, mode) -> Pair:
    """The merge of the two leaf lists (merge path, ``morton.merge_ranks``) and both sides'
    plans."""
    h1, l1, h2, l2 = m1.code[:, 0], m1.code[:, 1], m2.code[:, 0], m2.code[:, 1]
    lt2, le1 = morton.merge_ranks(h1, l1, h2, l2, (m1.count, m2.count))  # #m2 < m1_i, #m1 <= m2_j
    k = jnp.clip(lt2, 0, m2.capacity - 1)
    le2 = lt2 + ((lt2 < m2.count) & (h2[k] == h1) & (l2[k] == l1)).astype(jnp.int32)
    clamp = (m1.params.clamp_min_log_odds, m1.params.clamp_max_log_odds)
    sides = (_side(True, m1, m2, le2, mode, w1, w2, clamp), _side(False, m2, m1, le1, mode, w2, w1, clamp))
    return Pair((m1, m2), (w1, w2), mode, clamp, sides, (lt2, le1))


def _side(first: bool, A: OccupancyMap, B: OccupancyMap, le_b, mode, w_a, w_b, clamp) -> Side:
    """Per-leaf plan of map A against map B (``first``: A is M1, equal pairs emit from A).

    ``le_b[i]`` = number of B leaves with code <= A's code i. A leaf emits, in order: the gap
    before it inside a coarser B leaf, itself (unless split), the gap after it (if it is the
    last A leaf inside that B leaf).
    """
    ca, cb = A.capacity, B.capacity
    na, nb = A.count, B.count
    valid = jnp.arange(ca, dtype=jnp.int32) < na
    ah, al = A.code[:, 0], A.code[:, 1]
    aeh, ael = morton.code_end(ah, al, A.depth)
    j = le_b - 1  # the last B leaf starting at or before A's leaf
    jc = jnp.clip(j, 0, cb - 1)
    jn = jnp.clip(j + 1, 0, cb - 1)
    gate = na >= 0
    bh, bl, bd, bv, bnh, bnl = materialize(gate, lambda: (
        B.code[jc, 0], B.code[jc, 1], B.depth[jc], B.log_odds[jc], B.code[jn, 0], B.code[jn, 1]))
    beh, bel = morton.code_end(bh, bl, bd)
    cov = valid & (j >= 0) & (j < nb) & morton.code_less(ah, al, beh, bel)
    equal = cov & (bd == A.depth)
    inside_b = cov & (bd < A.depth)  # B's leaf strictly contains A's (A finer)
    finer_at_start = cov & (bd > A.depth)
    next_inside = (j + 1 < nb) & morton.code_less(bnh, bnl, aeh, ael)
    split = valid & (finer_at_start | (~cov & next_inside))
    self_emit = materialize(gate, lambda: valid & ~split & ~(equal & (not first)))

    va = A.log_odds
    both = combine(mode, va, bv, w_a, w_b) if first else combine(mode, bv, va, w_b, w_a)
    self_val = jnp.clip(jnp.where(cov, both, single(mode, va, w_a)), *clamp)

    # which leaves have a nonempty gap, from flags on the boundaries between neighbours (word
    # arrays shifted by one cost a pass each; one byte per boundary is shifted instead):
    # leaf k+1 is inside the B leaf that holds leaf k's start iff its last B leaf is the same
    # (``same``) and it is inside a B leaf; it starts where leaf k ends (``contig``).
    same = le_b[1:] == le_b[:-1]
    contig = (ah[1:] == aeh[:-1]) & (al[1:] == ael[:-1])
    link = materialize(gate, lambda: (same.astype(jnp.int8) | jnp.left_shift(contig.astype(jnp.int8), 1)
                                       | jnp.left_shift((same & inside_b[1:]).astype(jnp.int8), 2)))
    zero = jnp.zeros((1,), jnp.int8)
    prev, nxt = materialize(gate, lambda: (jnp.concatenate([zero, link]), jnp.concatenate([link, zero])))
    # before: from the previous leaf's end if it lies in the same B leaf, else from B's start
    gap_before = jnp.where((prev & 1) == 1, (prev & 2) == 0, (bh != ah) | (bl != al))
    gap_after = ((nxt & 4) == 0) & ((beh != aeh) | (bel != ael))  # A's last leaf in B's
    has_gap = inside_b & (gap_before | gap_after)
    stats = SideStats(equal=count_true(equal & first), split=count_true(split),
                      both=count_true(self_emit & cov), new_self=count_true(self_emit & ~cov))
    return Side(valid, self_emit, self_val, le_b, has_gap, any_of(has_gap), stats)


def _gaps_at(pair: Pair, k: int, i) -> LeafGaps:
    """The gaps inside B's coarser leaf (cells known only to B) before leaf ``i`` of side
    ``k`` (A) and, if it is the last A leaf inside, after it, for leaves ``i`` (any shape,
    inside ``[0, Ca)``, leaves with ``has_gap``), from a few gathers; a gap is empty
    (``[x, x)``) unless A is strictly inside B's leaf."""
    A, B, le_b, w_b = pair.maps[k], pair.maps[1 - k], pair.sides[k].le_other, pair.weights[1 - k]
    ca, cb, na = A.capacity, B.capacity, A.count
    ip, inext = jnp.maximum(i - 1, 0), jnp.minimum(i + 1, ca - 1)
    jj = jnp.clip(le_b[i] - 1, 0, cb - 1)
    a_h, a_l, b_h, b_l = A.code[i, 0], A.code[i, 1], B.code[jj, 0], B.code[jj, 1]
    ae_h, ae_l = morton.code_end(a_h, a_l, A.depth[i])
    pe_h, pe_l = morton.code_end(A.code[ip, 0], A.code[ip, 1], A.depth[ip])  # the previous leaf's end
    be_h, be_l = morton.code_end(b_h, b_l, B.depth[jj])
    use_prev = (i > 0) & morton.code_less(b_h, b_l, pe_h, pe_l)  # it lies in B's leaf too
    last = (i + 1 >= na) | ~morton.code_less(A.code[inext, 0], A.code[inext, 1], be_h, be_l)
    return LeafGaps(before=(jnp.where(use_prev, pe_h, b_h), jnp.where(use_prev, pe_l, b_l), a_h, a_l),
                    after=(ae_h, ae_l, jnp.where(last, be_h, ae_h), jnp.where(last, be_l, ae_l)),
                    value=jnp.clip(single(pair.mode, B.log_odds[jj], w_b), *pair.clamp))


def gap_entries(pair: Pair, rows: int) -> GapList:
    """The leaves of both sides with a nonempty gap as a list of ``rows``: the ``r``-th found
    by a binary search in the prefix count of ``has_gap`` over blocks of 32 leaves, then by
    popcounts in its block's bit mask; their gaps and gap cell counts."""
    sides = pair.sides
    ca = sides[0].valid.shape[0]
    flags = jnp.concatenate([s.has_gap for s in sides])
    pad = -flags.shape[0] % 32
    flags = jnp.concatenate([flags, jnp.zeros((pad,), bool)]) if pad else flags
    # the flags as 32-bit masks: the block of the r-th flag by a binary search in the
    # blocks' prefix count (n / 32 entries), then its bit by popcounts of the mask
    bit = jnp.left_shift(jnp.uint32(1), jnp.arange(32, dtype=jnp.uint32))
    mask = jnp.sum(jnp.where(flags.reshape(-1, 32), bit, jnp.uint32(0)), axis=1, dtype=jnp.uint32)
    found = cumsum(jax.lax.population_count(mask).astype(jnp.int32))
    r = jnp.arange(rows, dtype=jnp.int32)
    blk = jnp.minimum(jnp.searchsorted(found, r, side="right", method="scan"), found.shape[0] - 1)
    k = (r - excl_at(found, blk)).astype(jnp.uint32)  # the flag's rank in its block
    w = mask[blk]
    pos = jnp.zeros_like(k)
    for step in (16, 8, 4, 2, 1):  # the largest p with popcount(w below bit p) <= k
        m = pos + step
        below = jax.lax.population_count(w & (jnp.left_shift(jnp.uint32(1), m) - 1))
        pos = jnp.where(below <= k, m, pos)
    e = (blk * 32 + pos.astype(jnp.int32)).astype(jnp.int32)
    ok = r < found[-1]
    side = (e >= ca).astype(jnp.int32)
    i = jnp.where(side == 1, e - ca, e)
    at = tuple(jnp.clip(i, 0, s.valid.shape[0] - 1) for s in sides)  # i, in range on each side

    def gaps():  # into memory once (the counts' and the cells' consumers would recompute it)
        per_side = [_gaps_at(pair, s, a) for s, a in enumerate(at)]
        gap = jax.tree.map(lambda a, b: jnp.where(side == 1, b, a), *per_side)
        return (gap, jnp.where(ok, gap_cell_count(*gap.before), 0),
                jnp.where(ok, gap_cell_count(*gap.after), 0))

    gap, nb, na = materialize(found[-1] >= 0, gaps)
    return GapList(side=side, i=i, at=at, ok=ok, gaps=gap, n_before=nb, n_after=na,
                   leaves=found[-1].astype(jnp.int32),
                   missed=jnp.maximum(found[-1] - rows, 0).astype(jnp.int32))


def to_leaves(g: GapList, k: int, n: int, x):
    """``x`` (int32, per list row) of the listed leaves of side ``k`` scattered to their
    leaves: ``(n,)``, 0 for the others."""
    at = jnp.where(g.ok & (g.side == k), g.i, n)
    return jnp.zeros((n,), jnp.int32).at[at].set(x, mode="drop")
