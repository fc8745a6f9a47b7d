"""Log-odds fusion of occupancy maps across octree depths (thesis §5.2.3, Alg. 8, §6.5).

``fuse(m1, m2)`` integrates a map already in M1's frame (the output of ``transform_map``)
into M1. The result is, exactly, "expand both maps to depth 16, combine the log-odds where
both know a voxel, keep the one value where only one does, clamp to M1's
``[clamp_min, clamp_max]`` (eq. 2.10), prune maximally" - reached with **local expansion
only**, as the thesis asks: a leaf is split only where the other map holds finer leaves inside
it, and only into the few cells needed.

How, on flat Morton intervals (a leaf at depth ``d`` covers ``[code, code + 8^(16-d))``):

1. One merge of the two sorted leaf lists (ranks by ``searchsorted`` of each list in the
   other; nothing is re-sorted) tells every leaf which leaf of the other map starts at or
   before it: hence whether it is covered by an equal or coarser leaf (thesis case 2 / 3),
   strictly contains finer leaves (case 3 for M1, case 4 for M2: it is *split*), or lies
   in unknown space (case 1).
2. A split leaf emits no cell itself. Each finer leaf inside it emits itself (with both
   values combined, eqs. 5.17 / 5.19) plus the *gap* before it (and after it, if it is the
   last one) inside the split leaf: the part of the coarse leaf that the finer map does not
   know, which keeps the coarse value alone (eq. 5.16 / 5.18 then case 1, eq. 5.14). A gap
   ``[s, e)`` is cut into the minimal set of aligned octree cells (at most 7 per level and
   side), computed in closed form from the octal digits of ``s - 1`` and ``e``.
3. Cell counts per leaf, one exclusive prefix sum in merged order, and every output slot
   finds its owner with a scatter + cumulative max: the common refinement comes out
   already sorted. Values are combined per rule, clamped, and pruned maximally in one pass
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

``fuse_many(maps)`` fuses m maps in one pass: all leaf boundaries merged into one sorted
list (a merge tree of sorted lists, no sort), elementary intervals, one common refinement,
per-map coverage by cumulative maxima, one combined value per cell. For ``"sum"`` it is
bit-identical to folding ``fuse`` left to right (values are accumulated in map order with a
clamp after each map, as the fold does).

Everything is jitted with static capacities; a refinement larger than the capacity is
reported in ``FuseReport.overflow`` (and raised on the host when no report is requested),
never silently truncated.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from . import morton, tree
from .map import OccupancyMap, bucket_capacity

__all__ = ["RULES", "FuseReport", "fuse", "fuse_many"]

RULES = ("sum", "max", "weighted")

_D = morton.TREE_DEPTH
_MASK = (1 << morton.WORD_BITS) - 1
_SENT = morton.SENTINEL_HI


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
    - ``overflow``: bool, the refinement did not fit ``capacity`` (result truncated).
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
        out["pruned"] = int(np.asarray(self.pruned))
        return out


# ----------------------------------------------------------------------------- code arithmetic
# A code is (hi, lo) int32 words of 24 bits = 8 octal digits each; digit k (0 = finest level)
# lives in lo for k < 8, in hi for 8 <= k < 16, and digit 16 (only for the end 2^48 of the
# whole volume) is bit 24 of hi. Level indices k may be traced (loops over levels are
# ``fori_loop``s, which keeps compile times short).


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


def _end_words(code, depth):
    """Exclusive end ``code + 8^(16-depth)`` of leaves: ``(hi, lo)``; may equal 2^48."""
    end = morton.end_words(code, depth)
    return end[..., 0], end[..., 1]


def _less(ah, al, bh, bl):
    return (ah < bh) | ((ah == bh) & (al < bl))


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
    p = jnp.where(zero, _D, top_bit // 3)
    p = jnp.where(nonempty, p, 0)
    base = jnp.where(zero, 0, _digit(mh, ml, p) + 1)
    return nonempty, p, base


def _left_count(sh, sl, k, p):
    """Cells at level ``k`` ascending from ``s`` (0 unless ``k < p``)."""
    n = (8 - _digit(sh, sl, k) - _low_nonzero(sh, sl, k).astype(jnp.int32)) & 7
    return jnp.where(k < p, n, 0)


def _gap_plan(sh, sl, eh, el):
    """Number of cells of the canonical decomposition of Morton intervals ``[s, e)`` into
    maximal aligned octree cells (0 for empty intervals). Ascending from ``s`` there are
    ``(8 - d_k(s) - [s mod 8^k != 0]) mod 8`` cells at each level ``k < p``, then
    ``d_p(e) - base`` at level ``p``, then ``d_k(e)`` descending to ``e``: at most 7 per
    level and side."""
    nonempty, p, base = _gap_top(sh, sl, eh, el)

    def body(k, total):
        return total + _left_count(sh, sl, k, p) + jnp.where(k < p, _digit(eh, el, k), 0)

    total = jax.lax.fori_loop(0, _D, body, _digit(eh, el, p) - base)
    return jnp.where(nonempty, total, 0)


def _gap_cell(sh, sl, eh, el, t):
    """The ``t``-th cell (Morton order) of the decomposition of ``[s, e)``:
    ``(hi, lo, depth)``. ``t`` must be below the interval's cell count."""
    _, p, base = _gap_top(sh, sl, eh, el)
    zeros = jnp.zeros_like(sh)

    def pick(state, sel, h, l, k):
        done, oh, ol, ok, cum = state
        sel = sel & ~done
        return (done | sel, jnp.where(sel, h, oh), jnp.where(sel, l, ol), jnp.where(sel, k, ok), cum)

    def up(k, state):  # ascending from s: digit k = d_k(s) + [low digits != 0] + i (no carry)
        cum = state[-1]
        n = _left_count(sh, sl, k, p)
        i = t - cum
        h, l = _trunc(sh, sl, k + 1)
        val = _digit(sh, sl, k) + _low_nonzero(sh, sl, k).astype(jnp.int32) + i
        h, l = _put_digit(h, l, k, jnp.clip(val, 0, 7))
        state = pick(state, i < n, h, l, k)
        return state[:-1] + (cum + n,)

    state = jax.lax.fori_loop(0, _D, up, (jnp.zeros(sh.shape, bool), zeros, zeros, zeros, jnp.zeros_like(t)))
    # middle, level p: digits above p from e, digit p = base + i (p = 16 only for [0, 2^48))
    cum = state[-1]
    i = t - cum
    n_mid = _digit(eh, el, p) - base
    h, l = _trunc(eh, el, jnp.minimum(p + 1, _D))
    h, l = _put_digit(h, l, jnp.minimum(p, _D - 1), jnp.clip(base + i, 0, 7))
    h = jnp.where(p >= _D, 0, h)
    l = jnp.where(p >= _D, 0, l)
    state = pick(state, i < n_mid, h, l, p)
    state = state[:-1] + (cum + n_mid,)

    def down(j, state):  # descending to e: digit k = i, digits above k from e
        k = _D - 1 - j
        cum = state[-1]
        n = jnp.where(k < p, _digit(eh, el, k), 0)
        i = t - cum
        h, l = _trunc(eh, el, k + 1)
        h, l = _put_digit(h, l, k, jnp.clip(i, 0, 7))
        state = pick(state, i < n, h, l, k)
        return state[:-1] + (cum + n,)

    _, oh, ol, ok, _ = jax.lax.fori_loop(0, _D, down, state)
    return oh, ol, _D - ok


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


def _is_traced(*xs) -> bool:
    return any(isinstance(x, jax.core.Tracer) for x in xs)


# ----------------------------------------------------------------------------- merge ranks


def _merge_ranks(a, b):
    """For two sorted code lists ``a (Ca, 2)``, ``b (Cb, 2)``: ``(#b <= a_i, #a < b_j)``.

    Both inputs are sorted, so this is the merge of the two lists (no re-sort). It is a
    vectorised binary search of each list in the other (``morton.searchsorted_words``).
    """
    return (morton.searchsorted_words(b, a, side="right"),
            morton.searchsorted_words(a, b, side="left"))


# ----------------------------------------------------------------------------- pair kernel


def _side(first: bool, A: OccupancyMap, B: OccupancyMap, le_b, rule, w_a, w_b):
    """Per-leaf plan of map A against map B (``first``: A is M1, equal pairs emit from A).

    ``le_b[i]`` = number of B leaves with code <= A's code i.
    """
    ca, cb = A.capacity, B.capacity
    na, nb = A.count, B.count
    ia = jnp.arange(ca, dtype=jnp.int32)
    valid = ia < na
    sa_h, sa_l = A.code[:, 0], A.code[:, 1]
    ea_h, ea_l = _end_words(A.code, A.depth)
    eb_h, eb_l = _end_words(B.code, B.depth)
    j = le_b - 1
    jc = jnp.clip(j, 0, cb - 1)
    jn = jnp.clip(j + 1, 0, cb - 1)
    has_j = (j >= 0) & (j < nb)
    cov = valid & has_j & _less(sa_h, sa_l, eb_h[jc], eb_l[jc])
    dbj = B.depth[jc]
    equal = cov & (dbj == A.depth)
    coarser_b = cov & (dbj < A.depth)  # B's leaf strictly contains A's (A finer)
    finer_at_start = cov & (dbj > A.depth)
    next_inside = (j + 1 < nb) & _less(B.code[jn, 0], B.code[jn, 1], ea_h, ea_l)
    split = valid & (finer_at_start | (~cov & next_inside))
    self_emit = valid & ~split & ~(equal if not first else jnp.zeros_like(equal))

    va, vb = A.log_odds, B.log_odds[jc]
    both = _combine(rule, va, vb, w_a, w_b) if first else _combine(rule, vb, va, w_b, w_a)
    self_val = jnp.where(cov, both, _single(rule, va, w_a))
    gap_val = _single(rule, vb, w_b)

    # gaps inside B's coarser leaf (cells known only to B): before A's leaf, and after it
    # if it is the last A leaf inside that B leaf.
    prev = jnp.clip(ia - 1, 0, ca - 1)
    pe_h, pe_l = ea_h[prev], ea_l[prev]
    pb_h, pb_l = B.code[jc, 0], B.code[jc, 1]
    use_prev = (ia > 0) & _less(pb_h, pb_l, pe_h, pe_l)
    gb_s_h = jnp.where(use_prev, pe_h, pb_h)
    gb_s_l = jnp.where(use_prev, pe_l, pb_l)
    nxt = jnp.clip(ia + 1, 0, ca - 1)
    last = (ia + 1 >= na) | ~_less(A.code[nxt, 0], A.code[nxt, 1], eb_h[jc], eb_l[jc])
    ga_e_h = jnp.where(last, eb_h[jc], ea_h)
    ga_e_l = jnp.where(last, eb_l[jc], ea_l)
    # empty gaps where A is not strictly inside a B leaf: [s, s)
    gb_s_h = jnp.where(coarser_b, gb_s_h, sa_h)
    gb_s_l = jnp.where(coarser_b, gb_s_l, sa_l)
    ga_e_h = jnp.where(coarser_b, ga_e_h, ea_h)
    ga_e_l = jnp.where(coarser_b, ga_e_l, ea_l)
    n_before = _gap_plan(gb_s_h, gb_s_l, sa_h, sa_l)
    n_after = _gap_plan(ea_h, ea_l, ga_e_h, ga_e_l)
    count = jnp.where(valid, n_before + self_emit.astype(jnp.int32) + n_after, 0)
    return dict(
        count=count, n_before=n_before, self_emit=self_emit,
        gb=(gb_s_h, gb_s_l, sa_h, sa_l), ga=(ea_h, ea_l, ga_e_h, ga_e_l),
        self_val=self_val, gap_val=gap_val,
        stats=dict(equal=jnp.sum(equal & first), split=jnp.sum(split),
                   both=jnp.sum(self_emit & cov),
                   new_self=jnp.sum(self_emit & ~cov),
                   gaps=jnp.sum(jnp.where(valid, n_before + n_after, 0))),
    )


def _assemble(sides, orders, capacity: int, params, resolution, tree_depth):
    """Lay the per-leaf cells of several leaf tables out in merged order and build the map.

    ``sides``: per-table plans (``_side``); ``orders[t][i]``: number of cells owned by
    other tables' leaves that precede leaf ``i`` of table ``t`` (already summed).
    """
    offsets, owners, tabs = [], [], []
    base_id = 0
    for s, before in zip(sides, orders):
        excl = jnp.cumsum(s["count"]) - s["count"]
        offsets.append(excl + before)
        owners.append(base_id + jnp.arange(s["count"].shape[0], dtype=jnp.int32))
        base_id += s["count"].shape[0]
    total = sum(jnp.sum(s["count"]) for s in sides).astype(jnp.int32)
    slot = jnp.arange(capacity, dtype=jnp.int32)
    mark = jnp.full((capacity,), -1, jnp.int32)
    owner_at = jnp.zeros((capacity,), jnp.int32)
    for s, off, own in zip(sides, offsets, owners):
        pos = jnp.where(s["count"] > 0, off, capacity)
        mark = mark.at[pos].set(pos, mode="drop")
        owner_at = owner_at.at[pos].set(own, mode="drop")
    first = jax.lax.cummax(mark)
    owner = owner_at[jnp.clip(first, 0, capacity - 1)]

    def cat(f):
        return jnp.concatenate([f(s) for s in sides])

    off_all = jnp.concatenate(offsets)[owner]
    nb_all = cat(lambda s: s["n_before"])[owner]
    self_all = cat(lambda s: s["self_emit"])[owner]
    local = slot - off_all
    in_before = local < nb_all
    is_self = self_all & (local == nb_all)
    gb = [cat(lambda s, i=i: s["gb"][i])[owner] for i in range(4)]
    ga = [cat(lambda s, i=i: s["ga"][i])[owner] for i in range(4)]
    g = [jnp.where(in_before, b, a) for b, a in zip(gb, ga)]
    t = jnp.where(in_before, local, local - nb_all - self_all.astype(jnp.int32))
    gh, gl, gd = _gap_cell(g[0], g[1], g[2], g[3], jnp.maximum(t, 0))
    # self cell = the leaf itself: its code is the gap-before end, its depth from the gap-after
    # start (end of leaf) is not needed: recover it from the tables.
    depth_all = cat(lambda s: s["depth"])[owner]
    hi = jnp.where(is_self, gb[2], gh)
    lo = jnp.where(is_self, gb[3], gl)
    depth = jnp.where(is_self, depth_all, gd)
    val = jnp.where(is_self, cat(lambda s: s["self_val"])[owner], cat(lambda s: s["gap_val"])[owner])
    ok = slot < total
    code = jnp.stack([jnp.where(ok, hi, _SENT), jnp.where(ok, lo, 0)], axis=-1)
    lo_p, hi_p = params.clamp_min_log_odds, params.clamp_max_log_odds
    val = jnp.where(ok, jnp.clip(val, lo_p, hi_p), 0.0).astype(jnp.float32)
    m = OccupancyMap(code, jnp.where(ok, depth, _D).astype(jnp.int32), val,
                     jnp.minimum(total, capacity).astype(jnp.int32), params, resolution, tree_depth)
    return m, total


@functools.partial(jax.jit, static_argnames=("capacity", "do_prune"))
def _fuse_pair(m1: OccupancyMap, m2: OccupancyMap, w1, w2, rule, capacity: int, do_prune: bool):
    le2, lt1 = _merge_ranks(m1.code, m2.code)  # #m2 <= m1_i, #m1 < m2_j
    # m2_j's lookup needs #m1 <= m2_j: add the equal-start m1 leaf.
    k = jnp.clip(lt1, 0, m1.capacity - 1)
    eq = (lt1 < m1.count) & morton.words_equal(m1.code[k], m2.code)
    le1 = lt1 + eq.astype(jnp.int32)
    s1 = _side(True, m1, m2, le2, rule, w1, w2)
    s2 = _side(False, m2, m1, le1, rule, w2, w1)
    s1["depth"], s2["depth"] = m1.depth, m2.depth
    # merged order: m1 leaf i is preceded by the m2 leaves with code < its code; m2 leaf j
    # by the m1 leaves with code <= its code (ties: m1 first; one of a tied pair emits nothing
    # or the pair is equal and only m1 emits).
    ex1 = jnp.cumsum(s1["count"]) - s1["count"]
    ex2 = jnp.cumsum(s2["count"]) - s2["count"]
    eq2 = (le2 > 0) & morton.words_equal(m2.code[jnp.clip(le2 - 1, 0, m2.capacity - 1)], m1.code)
    lt2 = le2 - eq2.astype(jnp.int32)
    before1 = _excl_at(ex2, s2["count"], lt2)
    before2 = _excl_at(ex1, s1["count"], le1)
    out, total = _assemble([s1, s2], [before1, before2], capacity, m1.params,
                           m1.resolution, m1.tree_depth)
    if do_prune:
        out = tree._prune_runs(out)
    st1, st2 = s1["stats"], s2["stats"]
    report = FuseReport(
        leaves_in=jnp.stack([m1.count, m2.count]).astype(jnp.int32),
        refined_cells=total,
        leaves_out=out.count,
        same_depth=st1["equal"].astype(jnp.int32),
        split=jnp.stack([st1["split"], st2["split"]]).astype(jnp.int32),
        cells_both=(st1["both"] + st2["both"]).astype(jnp.int32),
        cells_new=(st2["new_self"] + st1["gaps"]).astype(jnp.int32),
        overflow=total > capacity,
        capacity=capacity,
    )
    return out, report


def _excl_at(excl, count, idx):
    """Sum of ``count[:idx]`` given its exclusive prefix sum ``excl`` (idx may equal len)."""
    n = count.shape[0]
    i = jnp.clip(idx, 0, n - 1)
    full = excl[n - 1] + count[n - 1]
    return jnp.where(idx >= n, full, excl[i])


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
    """Run ``run(cap)``; plan the capacity on the host when not given (one retry on overflow)."""
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
    need = int(rep.refined_cells)
    if need > cap:
        cap = bucket_capacity(need)
        out, rep = run(cap)
    return (out, rep) if return_report else out


def fuse(m1: OccupancyMap, m2: OccupancyMap, rule: str = "sum", *, weights=(1.0, 1.0),
         capacity: int | None = None, prune: bool = True, return_report: bool = False):
    """Fuse ``m2`` (already in ``m1``'s frame) into ``m1`` (thesis Alg. 8, §5.2.3 cases 1-4).

    Args:
      m1, m2: maps of equal ``resolution`` (metres); ``m1``'s ``params`` (clamping) are kept.
      rule: ``"sum"`` (eq. 5.15), ``"max"`` or ``"weighted"`` (see the module docstring).
      weights: ``(w1, w2)`` for ``"weighted"`` (traced floats; ignored by other rules).
      capacity: static row count of the output. ``None`` (host only) plans it: the
        refinement is at most ``n1 + n2`` cells plus gap cells; one re-run if it is larger.
        Under ``jit``/``vmap`` pass it explicitly and check ``FuseReport.overflow``.
      prune: prune maximally (never into a depth-0 root leaf, as OctoMap). With ``False``
        the clamped common refinement is returned (sorted, disjoint, not pruned).
      return_report: also return a ``FuseReport``.

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
    traced = _is_traced(m1.count, m2.count)

    def run(cap):
        return _fuse_pair(m1, m2, w1, w2, mode, cap, bool(prune))

    guess = 0 if traced else int(m1.count) + int(m2.count)
    return _finish(run, guess, capacity, traced, return_report, "fuse")


def fuse_many(maps: Sequence[OccupancyMap], rule: str = "sum", *, weights=None,
              capacity: int | None = None, prune: bool = True, return_report: bool = False):
    """Fuse ``m`` maps (all in the first map's frame) in one pass.

    All leaf boundaries are merged into one sorted list, the elementary intervals between
    them form one common refinement, each map's value on it is found by a cumulative max,
    and one value per cell is computed: for ``"sum"`` accumulated in map order with a clamp
    after each map, so the result is bit-identical to ``fuse(fuse(m0, m1), m2) ...``;
    ``"max"``: the maximum; ``"weighted"``: ``sum_k w_k L_k`` over the maps that know the
    voxel, clamped once. ``weights``: ``(m,)`` floats for ``"weighted"``.
    Other arguments as ``fuse``.
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
    traced = _is_traced(*[m.count for m in maps])

    def run(cap):
        return _fuse_many(tuple(maps), w, jnp.asarray(_MODE[rule], jnp.int32), cap, bool(prune))

    guess = 0 if traced else 2 * sum(int(m.count) for m in maps)
    return _finish(run, guess, capacity, traced, return_report, "fuse_many")


# ----------------------------------------------------------------------------- m maps


def _merge_lists(a, b):
    """Stable merge of two sorted record lists ``(hi, lo, *payload)`` (tuples of ``(n,)``
    arrays, duplicates allowed, padding sorted last); ties keep ``a`` first. Both inputs are
    sorted, so each record's output position is its own index plus its rank in the other list
    (``_merge_ranks``): no sort."""
    ca, cb = a[0].shape[0], b[0].shape[0]
    wa = jnp.stack([a[0], a[1]], axis=-1)
    wb = jnp.stack([b[0], b[1]], axis=-1)
    pos_a = jnp.arange(ca, dtype=jnp.int32) + morton.searchsorted_words(wb, wa, side="left")
    pos_b = jnp.arange(cb, dtype=jnp.int32) + morton.searchsorted_words(wa, wb, side="right")
    return tuple(jnp.zeros((ca + cb,), xa.dtype).at[pos_a].set(xa).at[pos_b].set(xb)
                 for xa, xb in zip(a, b))


@functools.partial(jax.jit, static_argnames=("capacity", "do_prune"))
def _fuse_many(maps, w, mode, capacity: int, do_prune: bool):
    m0 = maps[0]
    # 1. every map's starts and ends (each sorted) merged into one sorted boundary list;
    #    payload: map id, leaf index (-1 for an end).
    lists = []
    for k, m in enumerate(maps):
        valid = m.valid_mask()
        eh, el = _end_words(m.code, m.depth)
        eh = jnp.where(valid, eh, _SENT)
        el = jnp.where(valid, el, 0)
        idx = jnp.arange(m.capacity, dtype=jnp.int32)
        kk = jnp.full((m.capacity,), k, jnp.int32)
        lists.append((m.code[:, 0], m.code[:, 1], kk, jnp.where(valid, idx, -1)))
        lists.append((eh, el, kk, jnp.full((m.capacity,), -1, jnp.int32)))
    while len(lists) > 1:  # merge tree: log2(2m) levels
        nxt = [_merge_lists(lists[i], lists[i + 1]) for i in range(0, len(lists) - 1, 2)]
        if len(lists) % 2:
            nxt.append(lists[-1])
        lists = nxt
    bh, bl, bmap, bidx = lists[0]
    n_b = bh.shape[0]
    q = jnp.arange(n_b, dtype=jnp.int32)
    nh = jnp.concatenate([bh[1:], jnp.full((1,), _SENT + 1, jnp.int32)])
    nl = jnp.concatenate([bl[1:], jnp.zeros((1,), jnp.int32)])
    nonempty = _less(bh, bl, nh, nl) & (bh < _SENT)
    # 2. per map, the leaf covering each elementary interval [b_q, b_{q+1}): the last start
    #    of that map at or before q, if its end lies past b_q.
    cov, vals, exact = [], [], []
    for k, m in enumerate(maps):
        is_start = (bmap == k) & (bidx >= 0)
        last = jax.lax.cummax(jnp.where(is_start, q, -1))
        leaf = jnp.clip(bidx[jnp.clip(last, 0, n_b - 1)], 0, m.capacity - 1)
        eh, el = _end_words(m.code[leaf], m.depth[leaf])
        c = nonempty & (last >= 0) & _less(bh, bl, eh, el)
        cov.append(c)
        vals.append(m.log_odds[leaf])
        exact.append(c & morton.words_equal(m.code[leaf], jnp.stack([bh, bl], -1))
                     & (eh == nh) & (el == nl))
    # 3. one value per interval (sum: map order, clamped after each map, as the fold of fuse)
    p = m0.params
    lo_c, hi_c = p.clamp_min_log_odds, p.clamp_max_log_odds
    known = cov[0]
    acc = jnp.where(known, _single(mode, vals[0], w[0]), 0.0)
    for k in range(1, len(maps)):
        v = vals[k]
        summed = jnp.clip(jnp.where(known, acc + v, v), lo_c, hi_c)  # fold of fuse: clamp per map
        other = jnp.where(known, _combine(mode, acc, v, 1.0, w[k]), _single(mode, v, w[k]))
        new = jnp.where(mode == 0, summed, other)
        acc = jnp.where(cov[k], new, jnp.where(mode == 0, jnp.clip(acc, lo_c, hi_c), acc))
        known = known | cov[k]
    n_known = sum(c.astype(jnp.int32) for c in cov)
    # 4. decompose the known intervals into aligned cells, laid out in order
    n_cells = jnp.where(known, _gap_plan(bh, bl, nh, nl), 0)
    table = dict(count=n_cells, n_before=n_cells, self_emit=jnp.zeros_like(known),
                 gb=(bh, bl, nh, nl), ga=(bh, bl, nh, nl), self_val=acc, gap_val=acc,
                 depth=jnp.full((n_b,), _D, jnp.int32))
    out, total = _assemble([table], [jnp.zeros((n_b,), jnp.int32)], capacity, p,
                           m0.resolution, m0.tree_depth)
    if do_prune:
        out = tree._prune_runs(out)
    n_exact = sum(e.astype(jnp.int32) for e in exact)
    report = FuseReport(
        leaves_in=jnp.stack([m.count for m in maps]).astype(jnp.int32),
        refined_cells=total,
        leaves_out=out.count,
        same_depth=jnp.sum(n_exact >= 2).astype(jnp.int32),
        split=jnp.stack([m.count - jnp.sum(e) for m, e in zip(maps, exact)]).astype(jnp.int32),
        cells_both=jnp.sum(jnp.where(n_known >= 2, n_cells, 0)).astype(jnp.int32),
        cells_new=jnp.sum(jnp.where(~cov[0], n_cells, 0)).astype(jnp.int32),
        overflow=total > capacity,
        capacity=capacity,
    )
    return out, report
