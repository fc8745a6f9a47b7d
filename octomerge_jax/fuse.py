"""Log-odds fusion of occupancy maps across octree depths (thesis §5.2.3, Alg. 8, §6.5).

``fuse(m1, m2)`` integrates a map already in M1's frame (the output of ``transform_map``)
into M1. The result is, exactly, "expand both maps to depth 16, combine the log-odds where
both know a voxel, keep the one value where only one does, clamp to M1's
``[clamp_min, clamp_max]`` (eq. 2.10), prune maximally" - reached with **local expansion
only**, as the thesis asks: a leaf is split only where the other map holds finer leaves inside
it, and only into the few cells needed.

How, on flat Morton intervals (a leaf at depth ``d`` covers ``[code, code + 8^(16-d))``):

1. One merge of the two sorted leaf lists (merge path: each leaf's rank in the other list by
   a short binary search inside its merge-path chunk; nothing is re-sorted) tells every
   leaf which leaf of the other map starts at or before it: hence whether it is covered by
   an equal or coarser leaf (thesis case 2 / 3), strictly contains finer leaves (case 3 for
   M1, case 4 for M2: it is *split*), or lies in unknown space (case 1).
2. A split leaf emits no cell itself. Each finer leaf inside it emits itself (with both
   values combined, eqs. 5.17 / 5.19) plus the *gap* before it (and after it, if it is the
   last one) inside the split leaf: the part of the coarse leaf that the finer map does not
   know, which keeps the coarse value alone (eq. 5.16 / 5.18 then case 1, eq. 5.14). A gap
   ``[s, e)`` is cut into the minimal set of aligned octree cells (at most 7 per level and
   side), counted and enumerated in closed form from the octal digits of ``-s`` and ``e``
   (digit sums, no loop over levels).
3. Cell counts per leaf, one prefix sum in merged order: every leaf scatters its own cell to
   its slot, every non-empty gap its interval to its first slot, and each gap slot finds its
   gap by a cumulative max and computes its cell: the common refinement comes out already
   sorted. Gap cells are few (0-7.5 % of the refinement measured, most with .bt inputs): when
   no leaf has one, their counts and layout are skipped altogether (``lax.cond``); otherwise
   the few leaves with a gap are found from one byte of flags per leaf (a prefix count and a
   binary search), and only they compute their gaps, on a list of ``max(capacity / 16, 512)``
   rows on the host; their cell counts are scattered back for the prefix sum, and each gap
   cell, on a list of ``max(capacity / 8, 512)`` rows, finds its leaf by a cumulative max
   (either list re-run with room for all if there are more).
   Values are combined per rule, clamped, and pruned maximally in one pass
   (``tree.prune``: a node collapses iff its interval lies in one run of contiguous,
   equal-valued leaves).

Rules (``rule=``):

- ``"sum"`` (default): ``L1 + L2`` where both maps know a voxel (eq. 5.15): the Bayesian
  update for independent observations with prior 0.5 (eq. 2.6). Use for maps built from
  different sensor data.
- ``"max"``: ``max(L1, L2)``: conservative, for maps that are not independent (built from
  shared data, or a map fused with itself), so evidence is not counted twice.
- ``"weighted"``: ``w1 L1 + w2 L2`` (a log-linear opinion pool; a map that does not know a
  voxel contributes log-odds 0, the prior, so a voxel known only to map k gets ``w_k L_k``).
  Use to discount a robot with worse localisation (e.g. ``weights=(1.0, 0.5)``).
  ``weights=(1, 1)`` equals ``"sum"``. Weights are traced (no recompilation).

Unknown space never becomes free or occupied: only leaves of the inputs produce cells.
The thesis code's bugs (adding probabilities where M2 is finer, forcing M2's occupied leaves
to p = 0.6) are not reproduced.

``fuse_many(maps)`` fuses m maps in one pass: the maps' leaf boundaries (every start, and
the ends no next leaf starts at) merged into one sorted list (a merge tree, no sort; lists
sized to the maps' contents on the host), elementary intervals, one common refinement. The
leaves covering an interval are nested, so a running count of open leaves gives its nesting
level, and one cumulative max per level present (not per map) finds its leaves, kept for
the known intervals only (compacted: several boundary rows per interval where maps
overlap). The exact cell count is planned before the layout. One combined value per cell
(two maps: the pair kernel above, which is that refinement, ~2x faster for two). For
``"sum"`` it is bit-identical to folding ``fuse`` left to right (values are accumulated in
map order with a clamp after each map, as the fold does).

Everything is jitted with static capacities; a refinement larger than the capacity is
reported in ``FuseReport.overflow`` (and raised on the host when no report is requested),
never silently truncated. On the host without ``capacity=``, the output gets the
refinement's own power-of-two bucket: ``fuse_many`` counts the cells first (its first
phase), and so does ``fuse`` when the count's bounds ``max(n1, n2)`` and ``n1 + n2`` lie in
different buckets (else it runs in one program at the bucket of ``n1 + n2``).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from . import morton, tree
from ._ops import cummax, cummin, cumsum, float_bits, is_traced, materialize, padding_rows
from .map import OccupancyMap, bucket_capacity

__all__ = ["RULES", "FuseReport", "fuse", "fuse_many"]

RULES = ("sum", "max", "weighted")

_D = morton.TREE_DEPTH
_MASK = (1 << morton.WORD_BITS) - 1
_SENT = morton.SENTINEL_HI
_NONE = np.iinfo(np.int32).min  # payload of padding boundaries (fuse_many)
_TAG_BITS, _TAGS = 6, 64  # fuse_many boundary keys: lo * 64 + tag


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class FuseReport:
    """Counts of a fusion (thesis §5.2.3 cases), all int32 device scalars (vmappable).

    - ``leaves_in``: ``(m,)`` valid leaves of each input map.
    - ``refined_cells``: cells of the common refinement before pruning (the capacity needed).
    - ``leaves_out``: leaves of the fused, pruned map.
    - ``same_depth``: leaf pairs at the same depth in both maps (case 2, eq. 5.15).
    - ``split``: ``(m,)`` leaves of each map split because another map is finer inside them
      (pair: ``split[0]`` = case 3, M1 coarser; ``split[1]`` = case 4, M2 coarser).
    - ``cells_both``: refined cells known in at least two maps (combined by the rule).
    - ``cells_new``: refined cells unknown in the first map (case 1, eq. 5.14).
    - ``overflow``: bool, the refinement did not fit ``capacity``, or its gap cells did not
      fit a ``gap_capacity`` given under ``jit`` (result truncated).
    Static: ``capacity``, rows of the output map.
    """

    leaves_in: jax.Array
    refined_cells: jax.Array
    leaves_out: jax.Array
    same_depth: jax.Array
    split: jax.Array
    cells_both: jax.Array
    cells_new: jax.Array
    overflow: jax.Array
    capacity: int = dataclasses.field(metadata=dict(static=True), default=0)

    @property
    def pruned(self):
        """Refined cells removed by pruning."""
        return self.refined_cells - self.leaves_out

    def host(self) -> dict:
        """The counts as Python ints / lists (for logs and CLIs)."""
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            out[f.name] = np.asarray(v).tolist() if f.name != "capacity" else v
        out["pruned"] = np.asarray(self.pruned).tolist()  # a list for a vmapped report
        return out


# ----------------------------------------------------------------------------- code arithmetic
# A code is (hi, lo) int32 words of 24 bits = 8 octal digits each; digit k (0 = finest level)
# lives in lo for k < 8, in hi for 8 <= k < 16, and digit 16 (only for the end 2^48 of the
# whole volume) is bit 24 of hi. Level indices k may be traced. Everything below is
# elementwise and loop-free (XLA fuses it into one pass).


def _word_shift(k):
    """(in_hi, shift within the word) of digit ``k``."""
    in_hi = k >= 8
    return in_hi, jnp.where(in_hi, 3 * (k - 8), 3 * k)


def _digit(hi, lo, k):
    in_hi, sh = _word_shift(k)
    return jnp.right_shift(jnp.where(in_hi, hi, lo), sh) & 7


def _low_masks(k):
    """(hi_mask, lo_mask) of the digits below level ``k``."""
    lo_bits = jnp.minimum(3 * k, 24)
    hi_bits = jnp.maximum(3 * k - 24, 0)
    return jnp.left_shift(1, hi_bits) - 1, jnp.left_shift(1, lo_bits) - 1


def _low_nonzero(hi, lo, k):
    """Any digit below level ``k`` non-zero (``code mod 8^k != 0``)."""
    hm, lm = _low_masks(k)
    return ((lo & lm) != 0) | ((hi & hm) != 0)


def _trunc(hi, lo, k):
    """Clear the digits below level ``k``."""
    hm, lm = _low_masks(k)
    return hi & ~hm, lo & ~lm


def _put_digit(hi, lo, k, val):
    """Or ``val`` (0..7) into digit ``k`` (which must be clear)."""
    in_hi, sh = _word_shift(k)
    v = jnp.left_shift(val, sh)
    return jnp.where(in_hi, hi | v, hi), jnp.where(in_hi, lo, lo | v)


def _end(hi, lo, depth):
    """Exclusive end ``code + 8^(16-depth)`` of leaves as words; may equal 2^48."""
    shift = 3 * (_D - depth)
    small = shift < 24
    lo = lo + jnp.where(small, jnp.left_shift(1, jnp.minimum(shift, 23)), 0)
    hi = hi + jnp.where(small, jnp.right_shift(lo, 24), jnp.left_shift(1, jnp.maximum(shift - 24, 0)))
    return hi, lo & _MASK


def _less(ah, al, bh, bl):
    return (ah < bh) | ((ah == bh) & (al < bl))


def _digit_sum(hi, lo):
    """Sum of the octal digits of a code (SWAR: pairs, then quads of digits, in each word)."""

    def word(w):
        v = (w & 0o07070707) + (jnp.right_shift(w, 3) & 0o07070707)
        v = (v & 0o00770077) + (jnp.right_shift(v, 6) & 0o00770077)
        return (v & 0xFFF) + jnp.right_shift(v, 12)

    return word(hi) + word(lo)


def _gap_top(sh, sl, eh, el):
    """Top level ``p`` of the canonical decomposition of ``[s, e)`` and helpers: the top octal
    digit where ``s - 1`` and ``e`` differ (16 when ``s = 0``): ``[s, e]`` holds a multiple of
    ``8^k`` exactly for ``k <= p``. Returns ``(nonempty, p, base)``, ``base`` = first
    digit of the level-``p`` cells (``d_p(s - 1) + 1``, or 0 when ``s = 0``)."""
    nonempty = _less(sh, sl, eh, el)
    zero = (sh == 0) & (sl == 0)
    borrow = sl == 0
    mh = sh - borrow.astype(jnp.int32)
    ml = jnp.where(borrow, _MASK, sl - 1)
    xh = mh ^ eh
    xl = ml ^ el
    top_bit = jnp.where(xh != 0, 55 - jax.lax.clz(xh), 31 - jax.lax.clz(xl))
    p = jnp.where(zero, _D, jax.lax.div(jnp.maximum(top_bit, 0), 3))
    p = jnp.where(nonempty, p, 0)
    base = jnp.where(zero, 0, _digit(mh, ml, p) + 1)
    return nonempty, p, base


def _gap_terms(sh, sl, eh, el):
    """The decomposition of ``[s, e)`` into maximal aligned cells, in closed form: ascending
    from ``s``, ``L_k`` cells at each level ``k < p`` where ``L = (-s) mod 8^p`` (octal digits
    ``L_k``); then ``n_mid = d_p(e) - base`` cells at level ``p``; then descending to ``e``,
    ``R_k`` cells at level ``k`` where ``R = e mod 8^p``. Returns ``(nonempty, p, base, L, R,
    n_mid)`` with ``L``, ``R`` as word pairs."""
    nonempty, p, base = _gap_top(sh, sl, eh, el)
    hm, lm = _low_masks(p)
    neg_h = (-sh - (sl != 0).astype(jnp.int32)) & _MASK
    neg_l = (-sl) & _MASK
    return nonempty, p, base, (neg_h & hm, neg_l & lm), (eh & hm, el & lm), _digit(eh, el, p) - base


def _gap_plan(sh, sl, eh, el):
    """Number of cells of the canonical decomposition of Morton intervals ``[s, e)`` into
    maximal aligned octree cells (0 for empty intervals): ``digitsum(L) + n_mid +
    digitsum(R)`` (``_gap_terms``), at most 7 per level and side."""
    nonempty, _, _, L, R, n_mid = _gap_terms(sh, sl, eh, el)
    return jnp.where(nonempty, _digit_sum(*L) + n_mid + _digit_sum(*R), 0)


def _level_search(xh, xl, y):
    """Largest ``j`` in 0..15 with ``digitsum(x mod 8^j) <= y`` (a 4-step binary search; the
    digit sums of ``x``'s low digits grow with ``j``), and that digit sum."""
    j = jnp.zeros_like(y)
    s = jnp.zeros_like(y)
    for step in (8, 4, 2, 1):
        hm, lm = _low_masks(j + step)
        v = _digit_sum(xh & hm, xl & lm)
        ok = v <= y
        j = jnp.where(ok, j + step, j)
        s = jnp.where(ok, v, s)
    return j, s


def _gap_cell_info(sh, sl, eh, el, t):
    """The ``t``-th cell (Morton order) of the decomposition of ``[s, e)``, packed in one int32
    (one output, so XLA computes it once): ``level | digit << 5 | from_s << 8``. The cell's
    digits above ``level`` are those of ``s`` (ascending part) or ``e``, its digit at
    ``level`` is ``digit``, the rest are 0 (``_cell_code``). ``t`` must be below the count."""
    _, p, base, L, R, n_mid = _gap_terms(sh, sl, eh, el)
    ds_l, ds_r = _digit_sum(*L), _digit_sum(*R)
    up = t < ds_l
    mid = ~up & (t < ds_l + n_mid)
    u = t - ds_l - n_mid  # index among the descending cells
    # ascending cell t sits at the level j where the digit sums of L's low digits pass t;
    # descending cell u at the level j where those of R's high digits pass u.
    j, s_j = _level_search(jnp.where(up, L[0], R[0]), jnp.where(up, L[1], R[1]),
                           jnp.where(up, t, ds_r - u - 1))
    # ascending: digit j = d_j(s) + [s mod 8^j != 0] + i; descending: digit j = i;
    # middle (level p): digit p = base + i
    d_up = _digit(sh, sl, j) + _low_nonzero(sh, sl, j).astype(jnp.int32) + t - s_j
    d_down = u - ds_r + s_j + _digit(R[0], R[1], j)
    digit = jnp.where(up, d_up, jnp.where(mid, base + t - ds_l, d_down))
    level = jnp.where(mid, p, j)
    return level | jnp.left_shift(jnp.clip(digit, 0, 7), 5) | jnp.left_shift(up.astype(jnp.int32), 8)


def _cell_code(sh, sl, eh, el, info):
    """``(hi, lo, depth)`` of a cell from ``_gap_cell_info``."""
    level = info & 31
    digit = jnp.right_shift(info, 5) & 7
    from_s = (jnp.right_shift(info, 8) & 1) == 1
    h, l = _trunc(jnp.where(from_s, sh, eh), jnp.where(from_s, sl, el), jnp.minimum(level + 1, _D))
    h, l = _put_digit(h, l, jnp.minimum(level, _D - 1), digit)
    whole = level >= _D  # [0, 2^48): the root cell
    return jnp.where(whole, 0, h), jnp.where(whole, 0, l), _D - level


def _gap_cell(sh, sl, eh, el, t):
    """The ``t``-th cell (Morton order) of the decomposition of ``[s, e)``:
    ``(hi, lo, depth)``. ``t`` must be below the interval's cell count."""
    return _cell_code(sh, sl, eh, el, _gap_cell_info(sh, sl, eh, el, t))


# ----------------------------------------------------------------------------- rules


# The rule is traced (one compiled kernel serves all rules): ``mode`` is 0 sum, 1 max,
# 2 weighted; "sum" runs as "weighted" with weights 1, which is exact in IEEE arithmetic.
_MODE = {"sum": 0, "max": 1, "weighted": 2}


def _combine(mode, a, b, wa, wb):
    # note: XLA on CPU may contract w*a + w*b into a fused multiply-add, so "weighted" can
    # differ from separately rounded float32 products by an ulp (exact for power-of-two w)
    return jnp.where(mode == 1, jnp.maximum(a, b), wa * a + wb * b)


def _single(mode, a, wa):
    return jnp.where(mode == 1, a, wa * a)


def _check_rule(rule):
    if rule not in RULES:
        raise ValueError(f"rule must be one of {RULES}, got {rule!r}")


# ----------------------------------------------------------------------------- scans, merge




def _shift_down(x, fill):
    """``y[i] = x[i - 1]``, ``y[0] = fill``."""
    return jnp.concatenate([jnp.full((1,), fill, x.dtype), x[:-1]])


def _shift_up(x, fill):
    """``y[i] = x[i + 1]``, last = ``fill``."""
    return jnp.concatenate([x[1:], jnp.full((1,), fill, x.dtype)])


# ----------------------------------------------------------------------------- pair kernel


def _side(first: bool, A: OccupancyMap, B: OccupancyMap, le_b, rule, w_a, w_b, lo_c, hi_c):
    """Per-leaf plan of map A against map B (``first``: A is M1, equal pairs emit from A).

    ``le_b[i]`` = number of B leaves with code <= A's code i. A leaf emits, in order: the gap
    before it inside a coarser B leaf, itself (unless split), the gap after it (if it is the
    last A leaf inside that B leaf). Arrays ``(Ca,)``; ``has_gap`` flags the leaves with a
    nonempty gap, whose gaps ``gap_at(i)`` computes for a few leaf indices ``i``.
    """
    ca, cb = A.capacity, B.capacity
    na, nb = A.count, B.count
    ia = jnp.arange(ca, dtype=jnp.int32)
    valid = ia < na
    ah, al = A.code[:, 0], A.code[:, 1]
    aeh, ael = _end(ah, al, A.depth)
    j = le_b - 1  # the last B leaf starting at or before A's leaf
    jc = jnp.clip(j, 0, cb - 1)
    jn = jnp.clip(j + 1, 0, cb - 1)
    gate = na >= 0
    bh, bl, bd, bv, bnh, bnl = materialize(gate, lambda: (
        B.code[jc, 0], B.code[jc, 1], B.depth[jc], B.log_odds[jc], B.code[jn, 0], B.code[jn, 1]))
    beh, bel = _end(bh, bl, bd)
    cov = valid & (j >= 0) & (j < nb) & _less(ah, al, beh, bel)
    equal = cov & (bd == A.depth)
    inside_b = cov & (bd < A.depth)  # B's leaf strictly contains A's (A finer)
    finer_at_start = cov & (bd > A.depth)
    next_inside = (j + 1 < nb) & _less(bnh, bnl, aeh, ael)
    split = valid & (finer_at_start | (~cov & next_inside))
    self_emit = materialize(gate, lambda: valid & ~split & ~(equal & (not first)))

    va = A.log_odds
    both = _combine(rule, va, bv, w_a, w_b) if first else _combine(rule, bv, va, w_b, w_a)
    self_val = jnp.clip(jnp.where(cov, both, _single(rule, va, w_a)), lo_c, hi_c)

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

    def gap_at(i):
        """The gaps inside B's coarser leaf (cells known only to B) before A's leaf ``i`` and,
        if it is the last A leaf inside, after it, for leaves ``i`` (any shape, inside ``[0,
        Ca)``, leaves with ``has_gap``), from a few gathers: ``(gb_hi, gb_lo, a_hi, a_lo,
        ae_hi, ae_lo, ga_hi, ga_lo, value)``; a gap is empty (``[x, x)``) unless A is
        strictly inside B's leaf."""
        ip, inext = jnp.maximum(i - 1, 0), jnp.minimum(i + 1, ca - 1)
        jj = jnp.clip(le_b[i] - 1, 0, cb - 1)
        a_h, a_l, b_h, b_l = A.code[i, 0], A.code[i, 1], B.code[jj, 0], B.code[jj, 1]
        ae_h, ae_l = _end(a_h, a_l, A.depth[i])
        pe_h, pe_l = _end(A.code[ip, 0], A.code[ip, 1], A.depth[ip])  # the previous leaf's end
        be_h, be_l = _end(b_h, b_l, B.depth[jj])
        use_prev = (i > 0) & _less(b_h, b_l, pe_h, pe_l)  # it lies in B's leaf too
        last = (i + 1 >= na) | ~_less(A.code[inext, 0], A.code[inext, 1], be_h, be_l)
        return (jnp.where(use_prev, pe_h, b_h), jnp.where(use_prev, pe_l, b_l), a_h, a_l,
                ae_h, ae_l, jnp.where(last, be_h, ae_h), jnp.where(last, be_l, ae_l),
                jnp.clip(_single(rule, B.log_odds[jj], w_b), lo_c, hi_c))

    return dict(
        valid=valid, self_emit=self_emit, self_row=(A.code, A.depth, self_val),
        has_gap=has_gap, gap_at=gap_at, any_gap=jnp.any(has_gap),
        stats=dict(equal=jnp.sum(equal & first), split=jnp.sum(split),
                   both=jnp.sum(self_emit & cov), new_self=jnp.sum(self_emit & ~cov)),
    )


def _pair_cells(sides, rows: int, with_gaps: bool):
    """Every leaf's cells in the pair kernel's refinement (the gap before it, its own, the gap
    after it), prefix-summed per side: ``(p, g, after)``. ``with_gaps``: the leaves with gaps
    are listed in ``rows`` rows (``g``, ``_gap_entries``) and their cell counts scattered
    back, ``after[k]`` the cells after each leaf; else ``g`` is ``None``, ``after`` zeros."""
    emit = [s["self_emit"].astype(jnp.int32) for s in sides]
    if not with_gaps:
        return tuple(cumsum(e) for e in emit), None, (0, 0)
    g = _gap_entries(sides, rows)
    cells, after = [], []
    for k, e in enumerate(emit):
        packed = _to_leaves(g, k, e.shape[0], g["nb"] | jnp.left_shift(g["na"], 16))
        after.append(jnp.right_shift(packed, 16))
        cells.append((packed & 0xFFFF) + e + after[-1])
    return tuple(cumsum(c) for c in cells), g, tuple(after)


def _to_leaves(g, k, n: int, x):
    """``x`` (int32) of the listed leaves of side ``k`` (``_gap_entries`` ``g``) scattered to
    their leaves: ``(n,)``, 0 for the others."""
    at = jnp.where(g["ok"] & (g["side"] == k), g["i"], n)
    return jnp.zeros((n,), jnp.int32).at[at].set(x, mode="drop")


def _pair_write(maps, emit, vals, before, p, g, after, capacity: int, cell_rows: int):
    """The refinement laid out in ``capacity`` rows (unpruned): the leaves' own cells at their
    slots and, with a gap list ``g``, the gap cells (``_pair_gap_cells``, a list of
    ``cell_rows``). Merged order: m1 leaf i comes after the m2 leaves with code < its code;
    m2 leaf j after the m1 leaves with code <= its code (``before``; ties: m1 first, one of a
    tied pair emits nothing or the pair is equal and only m1 emits). ``after``: the cells
    after each leaf (``None``: from ``g``). Returns ``(map, total cells, gap cells needed,
    gap cells of side 0)``; the total is a lower bound when ``g`` missed leaves."""
    excl = [_excl_at(p[1 - k], before[k]) for k in range(2)]  # the other side's cells before
    total = p[0][-1] + p[1][-1]
    code, depth, val = padding_rows(capacity)
    n_gap = new = jnp.int32(0)
    if g is None:
        after = (0, 0)
    else:
        side, at = g["side"], g["at"]
        if after is None:
            after = tuple(_to_leaves(g, k, e.shape[0], g["na"]) for k, e in enumerate(emit))
        pick = lambda x: jnp.where(side == 1, x[1][at[1]], x[0][at[0]])  # noqa: E731
        emits = pick(emit).astype(jnp.int32)
        first = pick(p) - (g["nb"] + emits + g["na"]) + pick(excl)
        code, depth, val, n_gap = _pair_gap_cells(g, first, emits, code, depth, val, capacity, cell_rows)
        total = total + g["missed"]
        new = jnp.sum(jnp.where(side == 0, g["nb"] + g["na"], 0)).astype(jnp.int32)
    selfs = [(jnp.where(emit[k], p[k] - 1 - after[k] + excl[k], capacity), m.code, m.depth, vals[k])
             for k, m in enumerate(maps)]
    m1 = maps[0]
    out = _put_selfs(code, depth, val, selfs, total, capacity, m1.params, m1.resolution, m1.tree_depth)
    return out, total.astype(jnp.int32), n_gap, new


def _gap_entries(sides, rows: int):
    """The leaves of both sides with a nonempty gap, in order (side 0's first), as a list of
    ``rows``: the ``r``-th found by a binary search in the prefix count of ``has_gap`` over
    blocks of 32 leaves, then by popcounts in its block's bit mask. Per row: ``side``, leaf
    ``i`` (``at``: clipped into each side), ``ok`` (a leaf is there), the gaps (``gap_at``)
    and their cell counts ``nb``, ``na`` (0 unless ``ok``); ``leaves``: leaves with gaps in
    all, ``missed``: those past the list (each has at least one gap cell)."""
    ca = sides[0]["valid"].shape[0]
    flags = jnp.concatenate([s["has_gap"] for s in sides])
    pad = -flags.shape[0] % 32
    flags = jnp.concatenate([flags, jnp.zeros((pad,), bool)]) if pad else flags
    # the flags as 32-bit masks: the block of the r-th flag by a binary search in the
    # blocks' prefix count (n / 32 entries), then its bit by popcounts of the mask
    bit = jnp.left_shift(jnp.uint32(1), jnp.arange(32, dtype=jnp.uint32))
    mask = jnp.sum(jnp.where(flags.reshape(-1, 32), bit, jnp.uint32(0)), axis=1, dtype=jnp.uint32)
    found = cumsum(jax.lax.population_count(mask).astype(jnp.int32))
    r = jnp.arange(rows, dtype=jnp.int32)
    blk = jnp.minimum(jnp.searchsorted(found, r, side="right", method="scan"), found.shape[0] - 1)
    k = (r - _excl_at(found, blk)).astype(jnp.uint32)  # the flag's rank in its block
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
    at = [jnp.clip(i, 0, s["valid"].shape[0] - 1) for s in sides]  # i, in range on each side

    def gaps():  # into memory once (the counts' and the cells' consumers would recompute it)
        per_side = (s["gap_at"](a) for s, a in zip(sides, at))
        gap = tuple(jnp.where(side == 1, b, a) for a, b in zip(*per_side))
        return gap, jnp.where(ok, _gap_plan(*gap[0:4]), 0), jnp.where(ok, _gap_plan(*gap[4:8]), 0)

    gap, nb, na = materialize(found[-1] >= 0, gaps)
    return dict(side=side, i=i, at=at, ok=ok, gap=gap, nb=nb, na=na,
                leaves=found[-1].astype(jnp.int32),
                missed=jnp.maximum(found[-1] - rows, 0).astype(jnp.int32))


def _gap_cell_once(gate, bounds, t):
    """``_gap_cell`` of the intervals ``bounds() = (s_hi, s_lo, e_hi, e_lo)`` (a function:
    its gathers run inside), the bounds and the cells' closed form computed once into memory
    (``_materialize`` on a traced True ``gate``): fused into each consumer (the code, depth
    and value scatters), XLA computed them again per consumer (robots pairs 1.04-1.08x)."""
    def once():
        b = bounds()
        return b + (_gap_cell_info(*b, t),)

    *b, info = materialize(gate, once)
    return _cell_code(*b, info)


def _pair_gap_cells(g, first, emits, code, depth, val, capacity: int, rows: int):
    """Write the gap cells of the leaves in ``g`` (``_gap_entries``) at their slots: the gap
    before a listed leaf from its first slot ``first``, the gap after it after its own cell
    (``emits``: 1 if it has one). Each of ``rows`` gap cells finds its leaf by a cumulative
    max over the leaves' first cells and computes its cell in closed form. Returns ``(code,
    depth, val, gap cells needed)``."""
    nb, na = g["nb"], g["na"]
    e, t, n_cells = _cell_owners(nb + na, rows)  # the leaf of each gap cell
    q = jnp.arange(rows, dtype=jnp.int32)
    nb_e = nb[e]
    bef = t < nb_e
    tt = jnp.where(bef, t, t - nb_e)
    gap = g["gap"]
    ch, cl, cd = _gap_cell_once(n_cells >= 0, lambda: tuple(
        jnp.where(bef, gap[k][e], gap[k + 4][e]) for k in range(4)), tt)
    slot = first[e] + jnp.where(bef, t, nb_e + emits[e] + tt)
    dst = jnp.where(q < n_cells, slot, capacity)
    code = code.at[dst].set(jnp.stack([ch, cl], -1), mode="drop")
    depth = depth.at[dst].set(cd, mode="drop")
    val = val.at[dst].set(gap[8][e], mode="drop")
    return code, depth, val, (n_cells + g["missed"]).astype(jnp.int32)


def _emit(capacity: int, total, selfs, gaps, params, resolution, tree_depth,
          gap_capacity: int | None = None):
    """Lay out the common refinement (``capacity`` rows, Morton order) as an unpruned map.

    ``selfs``: ``(slot, code (n, 2), depth, value)`` cells written as they are; ``gaps``: ``(slot,
    count, s_hi, s_lo, e_hi, e_lo, value)``: the ``count`` cells of ``[s, e)`` from ``slot``
    on. Slots past ``capacity`` are dropped (``total > capacity`` is the overflow). Cells are
    scattered; every slot of a gap finds its gap by a cumulative max over gap start slots and
    computes its cell in closed form (``_gap_cell``). With ``gap_capacity`` (static, below
    ``capacity``) that is done on a compact list of at most ``gap_capacity`` gap cells
    (``_gap_cells``; more is an overflow the caller reports), not on every slot.
    """
    if not gaps:
        code, depth, val = padding_rows(capacity)
        return _put_selfs(code, depth, val, selfs, total, capacity, params, resolution, tree_depth)
    if gap_capacity is not None and gap_capacity < capacity:
        code, depth, val = _gap_cells(capacity, gap_capacity, gaps)
        return _put_selfs(code, depth, val, selfs, total, capacity, params, resolution, tree_depth)
    cap = capacity
    gap_rows = jnp.zeros((cap, 6), jnp.int32)  # s_hi, s_lo, e_hi, e_lo, value, start slot + 1
    for slot, n, sh, sl, eh, el, v in gaps:
        slot = jnp.where(n > 0, slot, cap)
        gap_rows = gap_rows.at[slot].set(jnp.stack([sh, sl, eh, el, float_bits(v), slot + 1], -1),
                                         mode="drop")
    q = jnp.arange(cap, dtype=jnp.int32)
    start = cummax(gap_rows[:, 5]) - 1
    g = gap_rows[jnp.maximum(start, 0)]
    g0, g1, g2, g3 = g[:, 0], g[:, 1], g[:, 2], g[:, 3]
    info = materialize(total >= 0, lambda: _gap_cell_info(g0, g1, g2, g3, q - start))
    ch, cl, cd = _cell_code(g0, g1, g2, g3, info)
    ok = q < total
    code = jnp.stack([jnp.where(ok, ch, _SENT), jnp.where(ok, cl, 0)], -1)
    depth = jnp.where(ok, cd, _D)
    val = jnp.where(ok, jax.lax.bitcast_convert_type(g[:, 4], jnp.float32), 0.0)
    return _put_selfs(code, depth, val, selfs, total, cap, params, resolution, tree_depth)


def _put_selfs(code, depth, val, selfs, total, cap, params, resolution, tree_depth):
    """The leaves' own cells written over the slots they own (whatever the gap fill put
    there): their code and depth are the input arrays, no stacked copy."""
    for slot, c, d, v in selfs:
        code = code.at[slot].set(c, mode="drop")
        depth = depth.at[slot].set(d, mode="drop")
        val = val.at[slot].set(v, mode="drop")
    return OccupancyMap(code, depth, val, jnp.minimum(total, cap).astype(jnp.int32),
                        params, resolution, tree_depth)


def _cell_owners(n, rows: int):
    """Cells laid out owner after owner (owner ``k`` has ``n[k]`` of them, in order), in a
    list of ``rows``: ``(owner, index within the owner, cells in all)`` per row, by a
    cumulative max over the owners' first rows (rows past the cells repeat the last owner)."""
    first = cumsum(n) - n  # the owner's first row
    mark = jnp.zeros((rows,), jnp.int32).at[jnp.where(n > 0, first, rows)].set(
        jnp.arange(n.shape[0], dtype=jnp.int32) + 1, mode="drop")
    owner = jnp.maximum(cummax(mark) - 1, 0)
    return owner, jnp.arange(rows, dtype=jnp.int32) - first[owner], first[-1] + n[-1]


def _gap_cells(capacity: int, gap_capacity: int, gaps):
    """Gap cells from a compact list: ``(code (capacity, 2), depth, value)`` holding the first
    ``gap_capacity`` gap cells at their slots and padding elsewhere (the leaves' own cells go
    on top, ``_put_selfs``).

    Gaps are rare in practice (a leaf split by finer leaves that do not tile it), but the
    per-slot layout of ``_emit`` costs a row table, a scan and the cell arithmetic on every
    slot of the output. Here only nonempty gaps are gathered (the ``r``-th one by a binary
    search in the prefix count of nonempty gaps, concatenated over the gap lists), then each
    gap cell finds its gap by a cumulative max over a ``gap_capacity``-row list.
    """
    cap, gcap = capacity, gap_capacity
    lens = [g[1].shape[0] for g in gaps]
    offs = np.cumsum([0] + lens)
    nonempty = cumsum(jnp.concatenate([(g[1] > 0).astype(jnp.int32) for g in gaps]))
    r = jnp.arange(gcap, dtype=jnp.int32)
    gi = jnp.searchsorted(nonempty, r, side="right", method="scan").astype(jnp.int32)
    which = sum((gi >= int(o)).astype(jnp.int32) for o in offs[1:-1])
    fields = []
    for f in range(7):  # slot, count, s_hi, s_lo, e_hi, e_lo, value of the r-th nonempty gap
        x = None
        for j, g in enumerate(gaps):
            xj = g[f][jnp.clip(gi - int(offs[j]), 0, lens[j] - 1)]
            x = xj if x is None else jnp.where(which == j, xj, x)
        fields.append(x)
    slot, n, sh, sl, eh, el, v = fields
    n = jnp.where(r < nonempty[-1], n, 0)
    g, t, n_cells = _cell_owners(n, gcap)  # the gap of each gap cell
    ch, cl, cd = _gap_cell_once(n_cells >= 0, lambda: (sh[g], sl[g], eh[g], el[g]), t)
    dst = jnp.where(r < n_cells, slot[g] + t, cap)
    code, depth, val = padding_rows(cap)
    return (code.at[dst].set(jnp.stack([ch, cl], -1), mode="drop"),
            depth.at[dst].set(cd, mode="drop"), val.at[dst].set(v[g], mode="drop"))


def _excl_at(incl, idx):
    """``sum(count[:idx])`` from the inclusive prefix sum ``incl`` (0 for ``idx <= 0``)."""
    return jnp.where(idx > 0, incl[jnp.clip(idx - 1, 0, incl.shape[0] - 1)], 0)


def _pair_sides(m1: OccupancyMap, m2: OccupancyMap, w1, w2, rule):
    """The merge of the two leaf lists and both sides' plans (``_side``): ``(sides, before)``,
    ``before[k]`` per leaf of side ``k`` the other side's leaves before it (ranks)."""
    h1, l1, h2, l2 = m1.code[:, 0], m1.code[:, 1], m2.code[:, 0], m2.code[:, 1]
    lt2, le1 = morton.merge_ranks(h1, l1, h2, l2, (m1.count, m2.count))  # #m2 < m1_i, #m1 <= m2_j
    k = jnp.clip(lt2, 0, m2.capacity - 1)
    le2 = lt2 + ((lt2 < m2.count) & (h2[k] == h1) & (l2[k] == l1)).astype(jnp.int32)
    lo_c, hi_c = m1.params.clamp_min_log_odds, m1.params.clamp_max_log_odds
    return (_side(True, m1, m2, le2, rule, w1, w2, lo_c, hi_c),
            _side(False, m2, m1, le1, rule, w2, w1, lo_c, hi_c)), (lt2, le1)


def _pair_report(m1, m2, stats, total, out, new_gap_cells, overflow, capacity: int):
    """The pair kernel's ``FuseReport`` from both sides' ``stats`` and the layout's counts."""
    st1, st2 = stats
    return FuseReport(
        leaves_in=jnp.stack([m1.count, m2.count]).astype(jnp.int32),
        refined_cells=total,
        leaves_out=out.count,
        same_depth=st1["equal"].astype(jnp.int32),
        split=jnp.stack([st1["split"], st2["split"]]).astype(jnp.int32),
        cells_both=(st1["both"] + st2["both"]).astype(jnp.int32),
        cells_new=(st2["new_self"] + new_gap_cells).astype(jnp.int32),
        overflow=overflow,
        capacity=capacity,
    )


@functools.partial(jax.jit, static_argnames=("capacity", "do_prune", "gap_capacity", "gap_leaves"))
def _fuse_pair(m1: OccupancyMap, m2: OccupancyMap, w1, w2, rule, capacity: int, do_prune: bool,
               gap_capacity: int | None = None, gap_leaves: int | None = None):
    """The pair kernel, one program: ``(map, FuseReport, (gap cells, leaves with gaps))``.
    ``gap_capacity``: rows of the list of gap cells (``None``: room for all); ``gap_leaves``:
    rows of the list of leaves with gaps (``None``: ``gap_capacity``, never the shorter:
    every such leaf has a gap cell)."""
    sides, before = _pair_sides(m1, m2, w1, w2, rule)
    compact = gap_capacity is not None and gap_capacity < capacity
    rows = min(gap_leaves or gap_capacity, gap_capacity) if compact else sum(
        s["valid"].shape[0] for s in sides)
    emit, vals = [s["self_emit"] for s in sides], [s["self_row"][2] for s in sides]

    def lay(with_gaps):
        p, g, after = _pair_cells(sides, rows, with_gaps)
        out = _pair_write((m1, m2), emit, vals, before, p, g, after, capacity,
                          gap_capacity if compact else capacity)
        return out + (g["leaves"] if with_gaps else jnp.int32(0),)

    # gaps (parts of a split leaf the finer map does not know) are rare; without any, their
    # closed-form cell counts and layout are skipped (under vmap both branches run)
    out, total, n_gap, new_gap_cells, n_gap_leaves = jax.lax.cond(
        sides[0]["any_gap"] | sides[1]["any_gap"], lambda: lay(True), lambda: lay(False))
    if do_prune:
        out = tree.prune_runs(out)
    overflow = (total > capacity) | ((n_gap > gap_capacity) | (n_gap_leaves > rows) if compact else False)
    rep = _pair_report(m1, m2, [s["stats"] for s in sides], total, out, new_gap_cells, overflow, capacity)
    return out, rep, (n_gap, n_gap_leaves)


@functools.partial(jax.jit, static_argnames=("gap_rows",))
def _pair_plan(m1: OccupancyMap, m2: OccupancyMap, w1, w2, rule, gap_rows: int):
    """The pair kernel's first phase, for a host that sizes the output from it: the merge,
    both sides, the ``gap_rows``-row list of leaves with gaps ``g`` and every leaf's cells
    prefix-summed (``p``); ``total`` cells and ``gap_cells`` (lower bounds when ``g``
    missed leaves: ``g["missed"] > 0``)."""
    sides, before = _pair_sides(m1, m2, w1, w2, rule)
    any_gap = sides[0]["any_gap"] | sides[1]["any_gap"]
    g_shape = jax.eval_shape(lambda: _pair_cells(sides, gap_rows, True)[1])
    p, g = jax.lax.cond(any_gap, lambda: _pair_cells(sides, gap_rows, True)[:2], lambda: (
        _pair_cells(sides, gap_rows, False)[0],
        jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), g_shape)))
    return dict(emit=[s["self_emit"] for s in sides], vals=[s["self_row"][2] for s in sides],
                before=before, p=p, g=g, any_gap=any_gap, stats=[s["stats"] for s in sides],
                total=(p[0][-1] + p[1][-1] + g["missed"]).astype(jnp.int32),
                gap_cells=(jnp.sum(g["nb"] + g["na"]) + g["missed"]).astype(jnp.int32))


@functools.partial(jax.jit, static_argnames=("capacity", "cell_rows", "do_prune"))
def _pair_emit(plan, m1: OccupancyMap, m2: OccupancyMap, capacity: int, cell_rows: int,
               do_prune: bool):
    """The pair kernel's second phase: ``_pair_plan``'s refinement laid out in ``capacity``
    rows (gap cells from a list of ``cell_rows``), pruned if ``do_prune``: ``(map,
    FuseReport)``."""
    def lay(with_gaps):
        return _pair_write((m1, m2), plan["emit"], plan["vals"], plan["before"], plan["p"],
                           plan["g"] if with_gaps else None, None, capacity, cell_rows)

    out, total, n_gap, new_gap_cells = jax.lax.cond(plan["any_gap"], lambda: lay(True),
                                                    lambda: lay(False))
    if do_prune:
        out = tree.prune_runs(out)
    overflow = (total > capacity) | (plan["g"]["missed"] > 0) | (n_gap > cell_rows)
    return out, _pair_report(m1, m2, plan["stats"], total, out, new_gap_cells, overflow, capacity)


def _fuse_pair_planned(m1: OccupancyMap, m2: OccupancyMap, w1, w2, rule, do_prune: bool,
                       gap_capacity: int | None, n_max: int):
    """The pair kernel on the host in two phases, the output sized from the first: its
    refinement's own bucket of rows, room for all its gap cells (the list of leaves with gaps
    starts at ``gap_capacity``, ``None``: ``default_gap_leaves`` of the smallest possible
    output, ``n_max = max(n1, n2)`` cells, and is re-planned larger when it is short).
    Returns ``(map, FuseReport)``."""
    n_in = m1.capacity + m2.capacity
    rows = gap_capacity or default_gap_leaves(bucket_capacity(n_max))
    while True:
        rows = min(rows or n_in, n_in)
        plan = _pair_plan(m1, m2, w1, w2, rule, gap_rows=rows)
        missed, total, gap_cells = (int(x) for x in jax.device_get(
            (plan["g"]["missed"], plan["total"], plan["gap_cells"])))
        if not missed:
            break
        rows = bucket_capacity(rows + missed)
    cap = bucket_capacity(total)
    cell_rows = max(default_gap_capacity(cap) or cap, bucket_capacity(gap_cells))
    return _pair_emit(plan, m1, m2, cap, min(cell_rows, cap), do_prune)


# Host default room for gap cells: capacity / 8, at least 512. Measured (gap cells / cells of
# the refinement): 0-0.1 % on the benchmark pairs (axis-aligned crops), 1-2 % for a robot map
# transformed into another's frame, 3-7.5 % when both were loaded from .bt files (maximum
# likelihood, pruned coarser); at capacity / 64 every such .bt merge ran the kernel twice. The
# list's cost did not show (3.6M-cell refinement: 290 / 299 ms at capacity / 64 / 8, +-3 %).
# The pair kernel's list of leaves with gaps: capacity / 16 (2.5-3 % of the refinement on the
# .bt robot pairs); its rows cost ~30 ns each, its cell list's ~40 ns (2 cores, robots medium).
_GAP_SHARE, _GAP_LEAF_SHARE, _GAP_MIN = 8, 16, 512


def default_gap_capacity(capacity: int) -> int | None:
    """The host default ``gap_capacity`` for an output of ``capacity`` rows (``None``: the
    per-slot layout, when the list would not be smaller)."""
    room = max(int(capacity) // _GAP_SHARE, _GAP_MIN)
    return room if room < capacity else None


def default_gap_leaves(capacity: int) -> int:
    """The host default rows of the pair kernel's list of leaves with gaps for an output of
    ``capacity`` rows: ``max(capacity / 16, 512)``."""
    return max(int(capacity) // _GAP_LEAF_SHARE, _GAP_MIN)


def _sized_gaps(kernel, cap: int, traced: bool, gap_capacity):
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


# ----------------------------------------------------------------------------- public


def _check_pair(maps: Sequence[OccupancyMap], names):
    for m, name in zip(maps, names):
        if not isinstance(m, OccupancyMap):
            raise ValueError(f"{name} must be an OccupancyMap, got {type(m).__name__}")
        if m.tree_depth != _D:
            raise ValueError(f"{name}.tree_depth must be {_D}, got {m.tree_depth}")
    r0 = maps[0].resolution
    for m, name in zip(maps[1:], names[1:]):
        if m.resolution != r0:
            raise ValueError(
                f"resolutions differ: {names[0]}.resolution = {r0:g} m, {name}.resolution = "
                f"{m.resolution:g} m; resample with transform_map to a common resolution first")


def _finish(run, guess: int, capacity, traced: bool, return_report: bool, what: str):
    """Run ``run(cap)``; plan the capacity on the host when not given (re-run on overflow)."""
    if capacity is not None:
        out, rep = run(int(capacity))
        if not traced and not return_report and bool(rep.overflow):
            raise ValueError(f"{what}: capacity {capacity} is too small for the "
                             f"{int(rep.refined_cells)} cells of the common refinement")
        return (out, rep) if return_report else out
    if traced:
        raise ValueError(f"{what}: pass a static capacity= when calling under jit/vmap")
    cap = bucket_capacity(guess)
    out, rep = run(cap)
    while int(rep.refined_cells) > cap:  # a lower bound when it overflowed: re-run larger
        cap = bucket_capacity(int(rep.refined_cells))
        out, rep = run(cap)
    return (out, rep) if return_report else out


def fuse(m1: OccupancyMap, m2: OccupancyMap, rule: str = "sum", *, weights=(1.0, 1.0),
         capacity: int | None = None, prune: bool = True, return_report: bool = False,
         gap_capacity: int | None = None):
    """Fuse ``m2`` (already in ``m1``'s frame) into ``m1`` (thesis Alg. 8, §5.2.3 cases 1-4).

    Args:
      m1, m2: maps of equal ``resolution`` (metres); ``m1``'s ``params`` (clamping) are kept.
      rule: ``"sum"`` (eq. 5.15), ``"max"`` or ``"weighted"`` (see the module docstring).
      weights: ``(w1, w2)`` for ``"weighted"`` (traced floats; ignored by other rules).
      capacity: static row count of the output. ``None`` (host only) plans it: the
        refinement has between ``max(n1, n2)`` and ``n1 + n2`` cells plus gap cells. When
        those bounds share a power-of-two bucket the kernel runs in it (re-run if gap cells
        overflow it); else its first phase counts the cells and the output gets their own
        bucket (up to half the rows, ~20 % faster; a pair whose count stays in the upper
        bucket pays ~1-4 ms for the count). Under ``jit``/``vmap`` pass it explicitly and
        check ``FuseReport.overflow``.
      prune: prune maximally (never into a depth-0 root leaf, as OctoMap). With ``False``
        the clamped common refinement is returned (sorted, disjoint, not pruned).
      return_report: also return a ``FuseReport``.
      gap_capacity: static room for *gap cells* (parts of a split leaf that the finer map
        does not know, thesis case 1 inside cases 3 / 4; rare in practice), and for the
        leaves that have them. ``None``: on the host ``max(capacity / 8, 512)`` (the leaves:
        half that), re-run with room for all when there are more; under ``jit``/``vmap``
        room for all (every leaf, ``capacity`` cells: never short, slower). A value that
        proves too small under ``jit`` sets ``overflow`` (``refined_cells`` is then a lower
        bound).

    Returns the fused ``OccupancyMap`` (capacity ``capacity``), or ``(map, report)``.
    Raises ``ValueError`` (host) for different resolutions, an unknown rule, or an overflow
    when no report is requested.
    """
    _check_pair([m1, m2], ["m1", "m2"])
    _check_rule(rule)
    if rule != "weighted":
        weights = (1.0, 1.0)
    w1, w2 = (jnp.asarray(w, jnp.float32) for w in weights)
    mode = jnp.asarray(_MODE[rule], jnp.int32)
    return _fuse2(m1, m2, w1, w2, mode, capacity, prune, return_report, gap_capacity, "fuse")


def _fuse2(m1, m2, w1, w2, mode, capacity, prune, return_report, gap_capacity, what):
    """The pair kernel for ``fuse`` / ``fuse_many`` of two checked maps. The refinement has
    between ``max(n1, n2)`` and ``n1 + n2`` cells (plus gap cells); on the host without a
    ``capacity``, when those bounds lie in different buckets, it is planned first and laid
    out in its own bucket (``_fuse_pair_planned``), else run in one program."""
    traced = is_traced(m1.count, m2.count)
    n1, n2 = (0, 0) if traced else (int(m1.count), int(m2.count))
    if capacity is None and not traced and bucket_capacity(max(n1, n2)) < bucket_capacity(n1 + n2):
        out, rep = _fuse_pair_planned(m1, m2, w1, w2, mode, bool(prune), gap_capacity, max(n1, n2))
        return (out, rep) if return_report else out

    def kernel(cap, gcap, gleaves):
        return _fuse_pair(m1, m2, w1, w2, mode, cap, bool(prune), gap_capacity=gcap, gap_leaves=gleaves)

    def run(cap):
        return _sized_gaps(kernel, cap, traced, gap_capacity)

    return _finish(run, n1 + n2, capacity, traced, return_report, what)


def fuse_many(maps: Sequence[OccupancyMap], rule: str = "sum", *, weights=None,
              capacity: int | None = None, prune: bool = True, return_report: bool = False):
    """Fuse ``m`` maps (all in the first map's frame) in one pass.

    All leaf boundaries are merged into one sorted list (a merge tree of the maps' sorted
    boundary lists, no sort), the elementary intervals between them form one common
    refinement, the nested leaves covering each interval are found level by level, and one
    value per cell is computed (two maps take the pair kernel of ``fuse``, the same
    refinement): for ``"sum"`` accumulated in map order with a clamp after each map, so the
    result is bit-identical to ``fuse(fuse(m0, m1), m2) ...``; ``"max"``: the maximum;
    ``"weighted"``: ``sum_k w_k L_k`` over the maps that know the voxel, clamped once.
    ``weights``: ``(m,)`` floats for ``"weighted"``. Other arguments as ``fuse``.

    On the host the boundary lists are sized to the maps' leaves and gaps (rounded to an
    eighth of an octave), the refinement is planned once (its exact cell count) and laid out
    in its own capacity bucket; under ``jit`` / ``vmap`` the lists have twice each map's
    capacity (always enough).

    Speed on 2 CPU cores (``benchmarks/bench_fuse.py``): 1.1-1.5x faster than the fold for
    m = 4 / 8 maps that each overlap their neighbours; when all m maps cover the same volume,
    the fold of ``fuse`` is faster (``fuse_many`` takes 1.2-1.4x its time at m = 4 / 8).
    """
    maps = list(maps)
    if not maps:
        raise ValueError("maps must hold at least one OccupancyMap")
    _check_pair(maps, [f"maps[{i}]" for i in range(len(maps))])
    _check_rule(rule)
    if weights is None or rule != "weighted":
        weights = [1.0] * len(maps)
    if len(weights) != len(maps):
        raise ValueError(f"weights has {len(weights)} entries for {len(maps)} maps")
    w = jnp.asarray(np.asarray(weights, np.float32))
    traced = is_traced(*[m.count for m in maps])

    mode = jnp.asarray(_MODE[rule], jnp.int32)
    if len(maps) == 2:  # the pair kernel is the one-pass refinement of two maps
        return _fuse2(maps[0], maps[1], w[0], w[1], mode, capacity, prune, return_report, None,
                      "fuse_many")
    # boundary lists sized to the maps' contents (host), else twice the capacities
    sizes = tuple(2 * mk.capacity for mk in maps) if traced else tuple(
        min(_list_size(int(n)), 2 * mk.capacity)
        for n, mk in zip(np.asarray(_boundary_counts(tuple(maps))), maps))
    plan = _many_plan(tuple(maps), sizes)  # the refinement once, laid out at its size

    def kernel(cap, gcap, _):
        out, rep, n_gap = _many_emit(plan, tuple(maps), w, mode, cap, bool(prune), gap_capacity=gcap)
        return out, rep, (n_gap, 0)

    guess = 0 if traced else int(plan["total"])  # exact: no re-run

    def run(cap):
        return _sized_gaps(kernel, cap, traced, None)

    return _finish(run, guess, capacity, traced, return_report, "fuse_many")


# ----------------------------------------------------------------------------- m maps


def _explicit_ends(mk: OccupancyMap):
    """``(valid, end hi, end lo, explicit)`` per row: ``explicit``, a valid leaf whose end is
    not the next leaf's start (a gap, or the last leaf)."""
    valid = mk.valid_mask()
    h, l = mk.code[:, 0], mk.code[:, 1]
    eh, el = _end(h, l, mk.depth)
    joined = _shift_up(valid, False) & (eh == _shift_up(h, 0)) & (el == _shift_up(l, 0))
    return valid, eh, el, valid & ~joined


@jax.jit
def _boundary_counts(maps):
    """``(m,)`` rows of each map's boundary list: leaves plus explicit ends."""
    return jnp.stack([mk.count + jnp.sum(_explicit_ends(mk)[3]) for mk in maps]).astype(jnp.int32)


def _boundaries(mk: OccupancyMap, row0: int, size: int):
    """Map ``mk``'s sorted boundary list, ``size`` rows ``(hi, key, payload)``: each leaf's
    start, and its end only when the next leaf does not start there (an *explicit* end; the
    others are implied by the next start). Key ``lo * 64 + tag``: at one position ends (tag 0)
    sort before starts, starts coarser first (tag ``2 + 2 depth + implied``, ``implied``: the
    previous leaf ends here). Payload: the leaf's global row ``row0 + i`` for a start, -1 for
    an end, ``_NONE`` for padding (hi ``_SENT``)."""
    valid, eh, el, explicit = _explicit_ends(mk)
    i = jnp.arange(mk.capacity, dtype=jnp.int32)
    h, l = mk.code[:, 0], mk.code[:, 1]
    implied = _shift_down(valid & ~explicit, False)
    n_exp = cumsum(explicit.astype(jnp.int32))
    at_start = jnp.where(valid, i + n_exp - explicit.astype(jnp.int32), size)
    at_end = jnp.where(explicit, i + n_exp, size)
    cols = []
    for pad, start, end in ((_SENT, h, eh),
                            (0, l * _TAGS + 2 + 2 * mk.depth + implied.astype(jnp.int32), el * _TAGS),
                            (_NONE, i + row0, jnp.full_like(i, -1))):
        col = jnp.full((size,), pad, jnp.int32)
        cols.append(col.at[at_start].set(start, mode="drop").at[at_end].set(end, mode="drop"))
    return tuple(cols)


def _list_size(n: int) -> int:
    """Host: static rows for a boundary list of ``n`` entries: ``n`` rounded up to an eighth of
    its power-of-two bucket (8 sizes per octave, so few compilations)."""
    step = max(bucket_capacity(n) // 8, 64)
    return -(-max(int(n), 1) // step) * step


def _fuse_many(maps, w, mode, capacity: int, do_prune: bool, gap_capacity: int | None = None,
               list_sizes: tuple[int, ...] | None = None):
    """The m-map kernel: ``(map, FuseReport, gap cells)``, the refinement (``_many_plan``)
    laid out (``_many_emit``). ``list_sizes``: static rows of each map's boundary list
    (``None``: twice the map's capacity, always enough; the host passes ``_list_size`` of the
    leaves plus explicit ends)."""
    plan = _many_plan(maps, list_sizes or tuple(2 * mk.capacity for mk in maps))
    return _many_emit(plan, maps, w, mode, capacity, do_prune, gap_capacity)


def _map_of(maps, row):
    """The map of global leaf row ``row`` (maps' rows concatenated)."""
    first_row = np.cumsum([mk.capacity for mk in maps])
    return sum((row >= int(f)).astype(jnp.int32) for f in first_row[:-1])


@functools.partial(jax.jit, static_argnames=("list_sizes",))
def _many_plan(maps, list_sizes: tuple[int, ...]):
    """Phase 1 of the m-map kernel, everything the output size depends on: the merged
    boundary list, per row its nesting ``level``, whether it starts a ``known`` interval and
    that interval's cell count ``n_cells``; ``total`` cells, and the report's case counts.
    ``list_sizes``: static rows of each map's boundary list."""
    m = len(maps)
    first_row = np.cumsum([0] + [mk.capacity for mk in maps])
    # 1. every map's boundaries merged into one sorted list (a merge tree, log2(m) levels),
    #    each level into memory: fused, every consumer of the final list gathered through all
    #    levels, both branches of each (shared m = 8: plan 150 -> 115 ms)
    lists = [_boundaries(mk, int(first_row[k]), list_sizes[k]) for k, mk in enumerate(maps)]
    while len(lists) > 1:
        nxt = [materialize(maps[0].count >= 0, lambda i=i: morton.merge_sorted(lists[i], lists[i + 1]))
               for i in range(0, len(lists) - 1, 2)]
        if len(lists) % 2:
            nxt.append(lists[-1])
        lists = nxt
    bh, bkey, bidx = lists[0]
    bl = jnp.right_shift(bkey, _TAG_BITS)
    n_b = bh.shape[0]
    q = jnp.arange(n_b, dtype=jnp.int32)
    nh, nl = _shift_up(bh, _SENT + 1), _shift_up(bl, 0)
    is_start = bidx >= 0
    implied = is_start & ((bkey & 1) == 1)
    # 2. nesting: the leaves covering [b_q, b_{q+1}) are nested (aligned cells); level[q] of
    #    them are open after row q (ends, explicit or implied by a start, before starts at a
    #    position: the implied ends of a position's later starts are taken off the earlier
    #    ones). (Which leaf is open at each level: ``_many_emit``.)
    last_row = (bh != nh) | (bl != nl)  # last row of its position
    group_end = cummin(jnp.where(last_row, q, n_b - 1), reverse=True)
    n_implied = cumsum(implied.astype(jnp.int32))
    opens = jnp.where(is_start, 1 - implied.astype(jnp.int32), jnp.where(bidx == -1, -1, 0))
    level = cumsum(opens) - (n_implied[group_end] - n_implied)
    known = _less(bh, bl, nh, nl) & (bh < _SENT) & (level > 0)
    # a leaf is exactly one interval iff it ends where its start position's interval ends
    gn = jnp.minimum(group_end + 1, n_b - 1)
    sd = jnp.right_shift(bkey & (_TAGS - 1), 1) - 1
    seh, sel = _end(bh, bl, sd)
    exact = is_start & (seh == bh[gn]) & (sel == bl[gn]) & (bh < _SENT)
    exact_k = jax.ops.segment_sum(exact.astype(jnp.int32), jnp.where(exact, _map_of(maps, bidx), m),
                                  num_segments=m + 1)[:m]
    leaf_key = jnp.right_shift(bkey, 1)  # position and depth
    same_leaf = (_shift_down(leaf_key, -1) == leaf_key) & (_shift_down(bh, -1) == bh)
    dup = exact & _shift_down(exact, False) & same_leaf  # the previous row is the same leaf
    same_depth = jnp.sum(dup & ~_shift_down(dup, False))  # positions with >= 2 equal leaves

    n_cells = materialize(maps[0].count >= 0, lambda: jnp.where(known, _gap_plan(bh, bl, nh, nl), 0))
    return dict(bh=bh, bl=bl, nh=nh, nl=nl, bidx=bidx, is_start=is_start, level=level, known=known,
                n_cells=n_cells, total=jnp.sum(n_cells).astype(jnp.int32),
                cells_both=jnp.sum(jnp.where(level >= 2, n_cells, 0)).astype(jnp.int32),
                split=jnp.stack([mk.count for mk in maps]).astype(jnp.int32) - exact_k,
                same_depth=same_depth.astype(jnp.int32))


@functools.partial(jax.jit, static_argnames=("capacity", "do_prune", "gap_capacity"))
def _many_emit(plan, maps, w, mode, capacity: int, do_prune: bool, gap_capacity: int | None = None):
    """Phase 2 of the m-map kernel: one value per known interval (maps in order), the
    intervals decomposed into ``capacity`` rows of aligned cells, pruned if ``do_prune``:
    ``(map, FuseReport, gap cells)``. With ``gap_capacity`` an interval that is one aligned
    cell (most) is written as it is and only the others are decomposed, from a compact list
    (``_emit``)."""
    m0, m = maps[0], len(maps)
    bidx, level, known, is_start = plan["bidx"], plan["level"], plan["known"], plan["is_start"]
    n_b = bidx.shape[0]
    q = jnp.arange(n_b, dtype=jnp.int32)
    # the known intervals, compacted: each is one or more cells of the output, so at most
    # ``capacity`` of them fit (more is an overflow); the per-map work runs on them only (the
    # boundary list has a row per leaf start and explicit end of every map, several per
    # interval where maps overlap)
    n_known = jnp.sum(known.astype(jnp.int32))
    if capacity < n_b:
        r = jnp.arange(capacity, dtype=jnp.int32)
        n_before = cumsum(known.astype(jnp.int32))
        at = jnp.full((capacity,), n_b - 1, jnp.int32).at[
            jnp.where(known, n_before - 1, capacity)].set(q, mode="drop")
        pick = lambda x: x[at]  # noqa: E731
        on_list = r < n_known
        shows = n_before - known.astype(jnp.int32)  # the list row of the first known row >= q
    else:  # no fewer rows than the list itself: every row stays
        r, pick, on_list, shows = q, lambda x: x, known, q  # noqa: E731
    level_k = jnp.where(on_list, pick(level), 0)
    # the leaf at nesting level L on list row i is the last start that opened level L at or
    # before it (a later one would lie inside it): every start put once in level L's row of
    # a (m, list) table at the list row where it first shows, then one cumulative max per
    # level present (1-2 for maps that overlap pairwise; at most m, not one per map) over
    # the list, not over the whole boundary list
    opened = jnp.full((m, r.shape[0]), -1, jnp.int32).at[
        jnp.where(is_start & (level >= 1), level - 1, m), shows].max(q, mode="drop")

    def open_level(lv, rows):
        """``rows[k]``: map k's leaf row on every known interval (-1 where it has none)."""
        row = bidx[jnp.maximum(cummax(opened[lv - 1]), 0)]
        return rows.at[jnp.where(level_k >= lv, _map_of(maps, row), m), r].set(row, mode="drop")

    rows = jax.lax.fori_loop(1, jnp.max(level) + 1, open_level,
                             jnp.full((m, r.shape[0]), -1, jnp.int32))
    lo_c, hi_c = m0.params.clamp_min_log_odds, m0.params.clamp_max_log_odds
    leaf_v = jnp.concatenate([mk.log_odds for mk in maps])
    counts = jnp.stack([mk.count for mk in maps]).astype(jnp.int32)
    # 3. one value per interval, maps in order (sum: clamped after each map, as the fold of
    #    fuse; the fold does not clamp map 0's values before adding map 1)
    def value(k):
        r = rows[k]
        return r >= 0, leaf_v[jnp.maximum(r, 0)]

    cov0, v = value(0)
    acc = jnp.where(cov0, _single(mode, v, w[0]), 0.0)

    def add_map(k, carry):
        acc, seen = carry
        c, v = value(k)
        summed = jnp.clip(jnp.where(seen, acc + v, v), lo_c, hi_c)
        other = jnp.where(seen, _combine(mode, acc, v, 1.0, w[k]), _single(mode, v, w[k]))
        new = jnp.where(mode == 0, summed, other)
        acc = jnp.where(c, new, jnp.where(mode == 0, jnp.clip(acc, lo_c, hi_c), acc))
        return acc, seen | c

    acc, _ = jax.lax.fori_loop(1, m, add_map, (acc, cov0))
    # 4. decompose the known intervals into aligned cells, laid out in order
    bh, bl, nh, nl = (pick(plan[k]) for k in ("bh", "bl", "nh", "nl"))
    n_cells = jnp.where(on_list, pick(plan["n_cells"]), 0)
    ends = cumsum(n_cells)
    total = plan["total"]  # all intervals' cells (those past a short list too)
    value, first = jnp.clip(acc, lo_c, hi_c), ends - n_cells
    compact = gap_capacity is not None and gap_capacity < capacity
    if compact:
        one = n_cells == 1  # the interval [b, n) is one aligned cell: depth from its size
        dl = nl - bl
        dh = nh - bh - (dl < 0).astype(jnp.int32)
        size_bit = morton.top_bit(dh, jnp.where(dl < 0, dl + (1 << morton.WORD_BITS), dl))
        selfs = [(jnp.where(one, first, capacity), jnp.stack([bh, bl], -1), _D - size_bit // 3, value)]
        gaps = [(first, jnp.where(one, 0, n_cells), bh, bl, nh, nl, value)]
    else:
        selfs, gaps = [], [(first, n_cells, bh, bl, nh, nl, value)]
    n_gap = jnp.sum(gaps[0][1]).astype(jnp.int32)
    out = _emit(capacity, total, selfs, gaps, m0.params, m0.resolution, m0.tree_depth,
                gap_capacity if compact else None)
    if do_prune:
        out = tree.prune_runs(out)
    report = FuseReport(
        leaves_in=counts,
        refined_cells=total,
        leaves_out=out.count,
        same_depth=plan["same_depth"],
        split=plan["split"],
        cells_both=plan["cells_both"],
        cells_new=jnp.sum(jnp.where(~cov0, n_cells, 0)).astype(jnp.int32),
        overflow=(total > capacity) | ((n_gap > gap_capacity) if compact else False),
        capacity=capacity,
    )
    return out, report, n_gap
