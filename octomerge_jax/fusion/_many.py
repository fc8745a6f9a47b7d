"""The m-map kernel of ``fuse_many``: one common refinement of all maps in one pass.

The maps' leaf boundaries (every start, and the ends no next leaf starts at) are merged into
one sorted list (a merge tree, no sort), whose consecutive entries bound elementary
intervals. The leaves covering an interval are nested, so a running count of open leaves
gives its nesting level, and one cumulative max per level present (not per map) finds its
leaves, kept for the known intervals only. The exact cell count is planned (``plan_many``)
before the layout (``emit_many``). For ``"sum"`` values are accumulated in map order with a
clamp after each map, as a fold of ``fuse`` does, so the two are bit-identical.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import morton, tree
from .._ops import cummax, cummin, cumsum, is_traced, materialize, shift_down, shift_up
from ..map import OccupancyMap
from ._gaps import gap_cell_count
from ._layout import Cells, Intervals, emit
from ._report import FuseReport
from ._rules import combine, single
from ._sizing import list_size, sized_gaps, sized_output

_D = morton.TREE_DEPTH
_SENT = morton.SENTINEL_HI
_NONE = np.iinfo(np.int32).min  # payload of padding boundaries
_TAG_BITS, _TAGS = 6, 64  # boundary keys: lo * 64 + tag


class ManyPlan(NamedTuple):
    """``plan_many``'s output: the merged boundary list (``n_b`` rows, the lists' sizes
    summed) and the refinement's counts."""

    bh: jax.Array  # (n_b,) int32 boundary code, hi word (padding: SENTINEL_HI)
    bl: jax.Array  # (n_b,) int32 lo word
    nh: jax.Array  # (n_b,) int32 the next boundary's hi word (the interval's end)
    nl: jax.Array  # (n_b,) int32 its lo word
    bidx: jax.Array  # (n_b,) int32 payload: global leaf row of a start, -1 an end, _NONE padding
    is_start: jax.Array  # (n_b,) bool
    level: jax.Array  # (n_b,) int32 leaves open on the interval after the row
    known: jax.Array  # (n_b,) bool the row starts a nonempty interval some map knows
    n_cells: jax.Array  # (n_b,) int32 aligned cells of that interval (0 unless known)
    total: jax.Array  # () int32 cells of the refinement
    cells_both: jax.Array  # () int32 cells known to >= 2 maps
    split: jax.Array  # (m,) int32 leaves of each map split by finer leaves of others
    same_depth: jax.Array  # () int32 positions with >= 2 equal leaves


def _explicit_ends(mk: OccupancyMap):
    """``(valid, end hi, end lo, explicit)`` per row: ``explicit``, a valid leaf whose end is
    not the next leaf's start (a gap, or the last leaf)."""
    valid = mk.valid_mask()
    h, l = mk.code[:, 0], mk.code[:, 1]
    eh, el = morton.code_end(h, l, mk.depth)
    joined = shift_up(valid, 1, False) & (eh == shift_up(h, 1, 0)) & (el == shift_up(l, 1, 0))
    return valid, eh, el, valid & ~joined


@jax.jit
def boundary_counts(maps):
    """``(m,)`` rows of each map's boundary list: leaves plus explicit ends."""
    counts = []
    for mk in maps:
        _, _, _, explicit = _explicit_ends(mk)
        counts.append(mk.count + jnp.sum(explicit))
    return jnp.stack(counts).astype(jnp.int32)


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
    implied = shift_down(valid & ~explicit, 1, False)
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


def _map_of(maps, row):
    """The map of global leaf row ``row`` (maps' rows concatenated)."""
    first_row = np.cumsum([mk.capacity for mk in maps])
    return sum((row >= int(f)).astype(jnp.int32) for f in first_row[:-1])


@functools.partial(jax.jit, static_argnames=("list_sizes",))
def plan_many(maps, list_sizes: tuple[int, ...]) -> ManyPlan:
    """Phase 1 of the m-map kernel, everything the output size depends on: the merged
    boundary list, per row its nesting ``level``, whether it starts a ``known`` interval and
    that interval's cell count; the total, and the report's case counts. ``list_sizes``:
    static rows of each map's boundary list (twice a map's capacity is always enough)."""
    m = len(maps)
    first_row = np.cumsum([0] + [mk.capacity for mk in maps])
    # 1. every map's boundaries merged into one sorted list (a merge tree, log2(m) levels),
    #    each level into memory (else every consumer of the final list gathers through all
    #    levels, both branches of each)
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
    nh, nl = shift_up(bh, 1, _SENT + 1), shift_up(bl, 1, 0)
    is_start = bidx >= 0
    implied = is_start & ((bkey & 1) == 1)
    # 2. nesting: the leaves covering [b_q, b_{q+1}) are nested (aligned cells); level[q] of
    #    them are open after row q (ends, explicit or implied by a start, before starts at a
    #    position: the implied ends of a position's later starts are taken off the earlier
    #    ones). (Which leaf is open at each level: ``_open_leaves``.)
    last_row = (bh != nh) | (bl != nl)  # last row of its position
    group_end = cummin(jnp.where(last_row, q, n_b - 1), reverse=True)
    n_implied = cumsum(implied.astype(jnp.int32))
    opens = jnp.where(is_start, 1 - implied.astype(jnp.int32), jnp.where(bidx == -1, -1, 0))
    level = cumsum(opens) - (n_implied[group_end] - n_implied)
    known = morton.code_less(bh, bl, nh, nl) & (bh < _SENT) & (level > 0)
    # a leaf is exactly one interval iff it ends where its start position's interval ends
    gn = jnp.minimum(group_end + 1, n_b - 1)
    sd = jnp.right_shift(bkey & (_TAGS - 1), 1) - 1
    seh, sel = morton.code_end(bh, bl, sd)
    exact = is_start & (seh == bh[gn]) & (sel == bl[gn]) & (bh < _SENT)
    exact_k = jax.ops.segment_sum(exact.astype(jnp.int32), jnp.where(exact, _map_of(maps, bidx), m),
                                  num_segments=m + 1)[:m]
    leaf_key = jnp.right_shift(bkey, 1)  # position and depth
    same_leaf = (shift_down(leaf_key, 1, -1) == leaf_key) & (shift_down(bh, 1, -1) == bh)
    dup = exact & shift_down(exact, 1, False) & same_leaf  # the previous row is the same leaf
    same_depth = jnp.sum(dup & ~shift_down(dup, 1, False))  # positions with >= 2 equal leaves

    n_cells = materialize(maps[0].count >= 0, lambda: jnp.where(known, gap_cell_count(bh, bl, nh, nl), 0))
    return ManyPlan(bh=bh, bl=bl, nh=nh, nl=nl, bidx=bidx, is_start=is_start, level=level, known=known,
                    n_cells=n_cells, total=jnp.sum(n_cells).astype(jnp.int32),
                    cells_both=jnp.sum(jnp.where(level >= 2, n_cells, 0)).astype(jnp.int32),
                    split=jnp.stack([mk.count for mk in maps]).astype(jnp.int32) - exact_k,
                    same_depth=same_depth.astype(jnp.int32))


def _known_list(plan: ManyPlan, capacity: int):
    """The known intervals, compacted: each is one or more cells of the output, so at most
    ``capacity`` of them fit (more is an overflow); the per-map work runs on them only (the
    boundary list has a row per leaf start and explicit end of every map, several per
    interval where maps overlap). Returns ``(r, at, on_list, shows)``: the list's row
    numbers, the boundary row of each (``None``: no fewer rows than the boundary list, every
    row stays), whether a known interval is on the row, and per boundary row the list row of
    the first known row at or after it."""
    known = plan.known
    n_b = known.shape[0]
    q = jnp.arange(n_b, dtype=jnp.int32)
    if capacity >= n_b:
        return q, None, known, q
    n_known = jnp.sum(known.astype(jnp.int32))
    r = jnp.arange(capacity, dtype=jnp.int32)
    n_before = cumsum(known.astype(jnp.int32))
    at = jnp.full((capacity,), n_b - 1, jnp.int32).at[
        jnp.where(known, n_before - 1, capacity)].set(q, mode="drop")
    return r, at, r < n_known, n_before - known.astype(jnp.int32)


def _open_leaves(plan: ManyPlan, maps, r, level_k, shows):
    """``(m, list)`` int32: map k's leaf row (global) on every listed interval, -1 where it has
    none. The leaf at nesting level L on list row i is the last start that opened level L at
    or before it (a later one would lie inside it): every start put once in level L's row of
    a ``(m, list)`` table at the list row where it first shows, then one cumulative max per
    level present (at most m, not one per map) over the list, not over the boundary list."""
    m = len(maps)
    bidx, level = plan.bidx, plan.level
    q = jnp.arange(bidx.shape[0], dtype=jnp.int32)
    opened = jnp.full((m, r.shape[0]), -1, jnp.int32).at[
        jnp.where(plan.is_start & (level >= 1), level - 1, m), shows].max(q, mode="drop")

    def open_level(lv, rows):
        row = bidx[jnp.maximum(cummax(opened[lv - 1]), 0)]
        return rows.at[jnp.where(level_k >= lv, _map_of(maps, row), m), r].set(row, mode="drop")

    return jax.lax.fori_loop(1, jnp.max(level) + 1, open_level, jnp.full((m, r.shape[0]), -1, jnp.int32))


def _interval_values(rows, maps, w, mode):
    """One value per listed interval, maps in order (sum: clamped after each map, as the fold
    of ``fuse``, which does not clamp map 0's values before adding map 1): ``(value before
    the final clamp, map 0 knows the interval)``, ``(list,)`` each."""
    m0 = maps[0]
    lo_c, hi_c = m0.params.clamp_min_log_odds, m0.params.clamp_max_log_odds
    leaf_v = jnp.concatenate([mk.log_odds for mk in maps])

    def value(k):
        r = rows[k]
        return r >= 0, leaf_v[jnp.maximum(r, 0)]

    cov0, v = value(0)
    acc = jnp.where(cov0, single(mode, v, w[0]), 0.0)

    def add_map(k, carry):
        acc, seen = carry
        c, v = value(k)
        summed = jnp.clip(jnp.where(seen, acc + v, v), lo_c, hi_c)
        other = jnp.where(seen, combine(mode, acc, v, 1.0, w[k]), single(mode, v, w[k]))
        new = jnp.where(mode == 0, summed, other)
        acc = jnp.where(c, new, jnp.where(mode == 0, jnp.clip(acc, lo_c, hi_c), acc))
        return acc, seen | c

    acc, _ = jax.lax.fori_loop(1, len(maps), add_map, (acc, cov0))
    return acc, cov0


@functools.partial(jax.jit, static_argnames=("capacity", "do_prune", "gap_capacity"))
def emit_many(plan: ManyPlan, maps, w, mode, capacity: int, do_prune: bool,
              gap_capacity: int | None = None):
    """Phase 2 of the m-map kernel: one value per known interval (maps in order), the
    intervals decomposed into ``capacity`` rows of aligned cells, pruned if ``do_prune``:
    ``(map, FuseReport, gap cells)``. With ``gap_capacity`` an interval that is one aligned
    cell (most) is written as it is and only the others are decomposed, from a compact list
    (``_layout.emit``)."""
    m0 = maps[0]
    lo_c, hi_c = m0.params.clamp_min_log_odds, m0.params.clamp_max_log_odds
    r, at, on_list, shows = _known_list(plan, capacity)
    pick = (lambda x: x) if at is None else (lambda x: x[at])  # noqa: E731
    level_k = jnp.where(on_list, pick(plan.level), 0)
    rows = _open_leaves(plan, maps, r, level_k, shows)
    acc, cov0 = _interval_values(rows, maps, w, mode)
    # decompose the known intervals into aligned cells, laid out in order
    bh, bl, nh, nl = pick(plan.bh), pick(plan.bl), pick(plan.nh), pick(plan.nl)
    n_cells = jnp.where(on_list, pick(plan.n_cells), 0)
    ends = cumsum(n_cells)
    total = plan.total  # all intervals' cells (those past a short list too)
    value, first = jnp.clip(acc, lo_c, hi_c), ends - n_cells
    compact = gap_capacity is not None and gap_capacity < capacity
    if compact:
        one = n_cells == 1  # the interval [b, n) is one aligned cell: depth from its size
        dl = nl - bl
        dh = nh - bh - (dl < 0).astype(jnp.int32)
        size_bit = morton.top_bit(dh, jnp.where(dl < 0, dl + (1 << morton.WORD_BITS), dl))
        selfs = [Cells(jnp.where(one, first, capacity), jnp.stack([bh, bl], -1), _D - size_bit // 3, value)]
        gaps = [Intervals(first, jnp.where(one, 0, n_cells), bh, bl, nh, nl, value)]
    else:
        selfs, gaps = [], [Intervals(first, n_cells, bh, bl, nh, nl, value)]
    n_gap = jnp.sum(gaps[0].count).astype(jnp.int32)
    out = emit(capacity, total, selfs, gaps, m0, gap_capacity if compact else None)
    if do_prune:
        out = tree.prune_runs(out)
    report = FuseReport(
        leaves_in=jnp.stack([mk.count for mk in maps]).astype(jnp.int32),
        refined_cells=total,
        leaves_out=out.count,
        same_depth=plan.same_depth,
        split=plan.split,
        cells_both=plan.cells_both,
        cells_new=jnp.sum(jnp.where(~cov0, n_cells, 0)).astype(jnp.int32),
        overflow=(total > capacity) | ((n_gap > gap_capacity) if compact else False),
        capacity=capacity,
    )
    return out, report, n_gap


def fuse_maps(maps: tuple, w, mode, capacity: int | None, prune: bool):
    """The m-map kernel for ``fuse_many`` of checked maps: ``(map, FuseReport)``. On the host
    the boundary lists are sized to the maps' leaves and explicit ends (``list_size``), the
    refinement is planned once (its exact cell count) and laid out in its own bucket unless
    ``capacity`` is given; under ``jit``/``vmap`` the lists have twice each map's capacity
    (always enough)."""
    traced = is_traced(*[mk.count for mk in maps])
    sizes = tuple(2 * mk.capacity for mk in maps) if traced else tuple(
        min(list_size(int(n)), 2 * mk.capacity) for n, mk in zip(np.asarray(boundary_counts(maps)), maps))
    plan = plan_many(maps, sizes)

    def kernel(cap, gcap, _):
        out, rep, n_gap = emit_many(plan, maps, w, mode, cap, bool(prune), gap_capacity=gcap)
        return out, rep, (n_gap, 0)

    def run(cap):
        return sized_gaps(kernel, cap, traced, None)

    guess = 0 if traced else int(plan.total)  # exact: no re-run
    return sized_output(run, guess, capacity, traced, "fuse_many")
