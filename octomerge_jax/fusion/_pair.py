"""The pair kernel: the common refinement of two maps (thesis Alg. 8, §5.2.3 cases 1-4),
reached with local expansion only.

Every leaf's cells (the gap before it, its own unless split, the gap after it if it is the
last leaf inside the other map's coarser leaf; ``_sides``) are counted and prefix-summed in
merged order: every leaf scatters its own cell to its slot, and each gap cell finds its leaf
by a cumulative max over a short list of the leaves with gaps and computes its cell in
closed form (``_gaps``): the refinement comes out sorted. When no leaf has a gap, their
counts and layout are skipped (``lax.cond``). Values are combined per rule, clamped (eq.
2.10), and pruned maximally (``tree.prune_runs``).

Two ways to run it: one program at a capacity fixed in advance (``pair_kernel``), or, on
the host, a first phase that counts the cells (``plan_pair``) and a second that lays them
out in their own bucket (``emit_pair``).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from .. import tree
from .._ops import bucket_capacity, cond_with_shapes, cumsum, is_traced, padding_rows, zeros_of
from ..kernel_store import stored_jit
from ..map import OccupancyMap
from ._gaps import gap_cell_once
from ._layout import Cells, cell_owners, excl_at, put_selfs
from ._report import FuseReport
from ._sides import GapList, Pair, SideStats, gap_entries, pair_sides, to_leaves
from ._sizing import default_gap_capacity, default_gap_leaves, refinement_cells, sized_gaps, sized_output


class PairPlan(NamedTuple):
    """``plan_pair``'s output: the refinement counted, ready to lay out."""

    emit: tuple  # 2 x (Ck,) bool, leaf k emits its own cell
    vals: tuple  # 2 x (Ck,) float32, its value
    before: tuple  # 2 x (Ck,) int32, the other side's leaves before it (``Pair.before``)
    p: tuple  # 2 x (Ck,) int32, cells up to and including each leaf's, prefix-summed per side
    g: GapList  # the leaves with gaps (zeros when there are none)
    any_gap: jax.Array  # () bool
    stats: tuple  # 2 x SideStats
    total: jax.Array  # () int32 cells (a lower bound when ``g.missed > 0``)
    gap_cells: jax.Array  # () int32 gap cells (a lower bound when ``g.missed > 0``)


def _pair_cells(pair: Pair, rows: int, with_gaps: bool):
    """Every leaf's cells in the refinement (the gap before it, its own, the gap after it),
    prefix-summed per side: ``(p, g, after)``. ``with_gaps``: the leaves with gaps are listed
    in ``rows`` rows (``g``, ``gap_entries``) and their cell counts scattered back,
    ``after[k]`` the cells after each leaf; else ``g`` is ``None``, ``after`` zeros."""
    emit = [s.self_emit.astype(jnp.int32) for s in pair.sides]
    if not with_gaps:
        return tuple(cumsum(e) for e in emit), None, (0, 0)
    g = gap_entries(pair, rows)
    cells, after = [], []
    for k, e in enumerate(emit):
        packed = to_leaves(g, k, e.shape[0], g.n_before | jnp.left_shift(g.n_after, 16))
        after.append(jnp.right_shift(packed, 16))
        cells.append((packed & 0xFFFF) + e + after[-1])
    return tuple(cumsum(c) for c in cells), g, tuple(after)


def _pair_write(maps, emit, vals, before, p, g: GapList | None, after, capacity: int, cell_rows: int):
    """The refinement laid out in ``capacity`` rows (unpruned): the leaves' own cells at their
    slots and, with a gap list ``g``, the gap cells (``_pair_gap_cells``, a list of
    ``cell_rows``). Merged order: m1 leaf i comes after the m2 leaves with code < its code;
    m2 leaf j after the m1 leaves with code <= its code (``before``; ties: m1 first, one of a
    tied pair emits nothing or the pair is equal and only m1 emits). ``after``: the cells
    after each leaf (``None``: from ``g``). Returns ``(map, total cells, gap cells needed,
    gap cells of side 0)``; the total is a lower bound when ``g`` missed leaves."""
    excl = [excl_at(p[1 - k], before[k]) for k in range(2)]  # the other side's cells before
    total = p[0][-1] + p[1][-1]
    code, depth, val = padding_rows(capacity)
    n_gap = new = jnp.int32(0)
    if g is None:
        after = (0, 0)
    else:
        side, at = g.side, g.at
        if after is None:
            after = tuple(to_leaves(g, k, e.shape[0], g.n_after) for k, e in enumerate(emit))
        pick = lambda x: jnp.where(side == 1, x[1][at[1]], x[0][at[0]])  # noqa: E731
        emits = pick(emit).astype(jnp.int32)
        first = pick(p) - (g.n_before + emits + g.n_after) + pick(excl)
        code, depth, val, n_gap = _pair_gap_cells(g, first, emits, code, depth, val, capacity, cell_rows)
        total = total + g.missed
        new = jnp.sum(jnp.where(side == 0, g.n_before + g.n_after, 0)).astype(jnp.int32)
    selfs = [Cells(jnp.where(emit[k], p[k] - 1 - after[k] + excl[k], capacity), m.code, m.depth, vals[k])
             for k, m in enumerate(maps)]
    out = put_selfs(code, depth, val, selfs, total, capacity, maps[0])
    return out, total.astype(jnp.int32), n_gap, new


def _pair_gap_cells(g: GapList, first, emits, code, depth, val, capacity: int, rows: int):
    """Write the gap cells of the leaves in ``g`` at their slots: the gap before a listed leaf
    from its first slot ``first``, the gap after it after its own cell (``emits``: 1 if it
    has one). Each of ``rows`` gap cells finds its leaf by a cumulative max over the leaves'
    first cells and computes its cell in closed form. Returns ``(code, depth, val, gap cells
    needed)``."""
    nb, na = g.n_before, g.n_after
    e, t, n_cells = cell_owners(nb + na, rows)  # the leaf of each gap cell
    q = jnp.arange(rows, dtype=jnp.int32)
    nb_e = nb[e]
    bef = t < nb_e
    tt = jnp.where(bef, t, t - nb_e)
    gap = g.gaps
    ch, cl, cd = gap_cell_once(n_cells >= 0, lambda: tuple(
        jnp.where(bef, gap.before[k][e], gap.after[k][e]) for k in range(4)), tt)
    slot = first[e] + jnp.where(bef, t, nb_e + emits[e] + tt)
    dst = jnp.where(q < n_cells, slot, capacity)
    code = code.at[dst].set(jnp.stack([ch, cl], -1), mode="drop")
    depth = depth.at[dst].set(cd, mode="drop")
    val = val.at[dst].set(gap.value[e], mode="drop")
    return code, depth, val, (n_cells + g.missed).astype(jnp.int32)


def _pair_report(m1, m2, stats: tuple[SideStats, SideStats], total, out, new_gap_cells, overflow,
                 capacity: int) -> FuseReport:
    """The pair kernel's ``FuseReport`` from both sides' ``stats`` and the layout's counts."""
    st1, st2 = stats
    return FuseReport(
        leaves_in=jnp.stack([m1.count, m2.count]).astype(jnp.int32),
        refined_cells=total,
        leaves_out=out.count,
        same_depth=st1.equal.astype(jnp.int32),
        split=jnp.stack([st1.split, st2.split]).astype(jnp.int32),
        cells_both=(st1.both + st2.both).astype(jnp.int32),
        cells_new=(st2.new_self + new_gap_cells).astype(jnp.int32),
        overflow=overflow,
        capacity=capacity,
    )


@functools.partial(jax.jit, static_argnames=("capacity", "do_prune", "gap_capacity", "gap_leaves"))
def pair_kernel(m1: OccupancyMap, m2: OccupancyMap, w1, w2, mode, capacity: int, do_prune: bool,
                gap_capacity: int | None = None, gap_leaves: int | None = None):
    """The pair kernel, one program: ``(map, FuseReport, (gap cells, leaves with gaps))``.
    ``gap_capacity``: rows of the list of gap cells (``None``: room for all); ``gap_leaves``:
    rows of the list of leaves with gaps (``None``: ``gap_capacity``, never the shorter:
    every such leaf has a gap cell)."""
    pair = pair_sides(m1, m2, w1, w2, mode)
    sides = pair.sides
    compact = gap_capacity is not None and gap_capacity < capacity
    rows = min(gap_leaves or gap_capacity, gap_capacity) if compact else sum(
        s.valid.shape[0] for s in sides)
    emit, vals = [s.self_emit for s in sides], [s.self_val for s in sides]

    def lay(with_gaps):
        p, g, after = _pair_cells(pair, rows, with_gaps)
        out = _pair_write((m1, m2), emit, vals, pair.before, p, g, after, capacity,
                          gap_capacity if compact else capacity)
        return out + (g.leaves if with_gaps else jnp.int32(0),)

    # without any gap, their closed-form cell counts and layout are skipped (under vmap both
    # branches run)
    out, total, n_gap, new_gap_cells, n_gap_leaves = jax.lax.cond(
        sides[0].any_gap | sides[1].any_gap, lambda: lay(True), lambda: lay(False))
    if do_prune:
        out = tree.prune_runs(out)
    overflow = (total > capacity) | ((n_gap > gap_capacity) | (n_gap_leaves > rows) if compact else False)
    rep = _pair_report(m1, m2, tuple(s.stats for s in sides), total, out, new_gap_cells, overflow, capacity)
    return out, rep, (n_gap, n_gap_leaves)


@stored_jit(static_argnames=("gap_rows",))
def plan_pair(m1: OccupancyMap, m2: OccupancyMap, w1, w2, mode, gap_rows: int) -> PairPlan:
    """The pair kernel's first phase, for a host that sizes the output from it: the merge,
    both sides, the ``gap_rows``-row list of leaves with gaps and every leaf's cells
    prefix-summed."""
    pair = pair_sides(m1, m2, w1, w2, mode)
    sides = pair.sides
    any_gap = sides[0].any_gap | sides[1].any_gap
    p, g = cond_with_shapes(any_gap, lambda: _pair_cells(pair, gap_rows, True)[:2],
                            lambda shapes: (_pair_cells(pair, gap_rows, False)[0], zeros_of(shapes[1])))
    return PairPlan(emit=tuple(s.self_emit for s in sides), vals=tuple(s.self_val for s in sides),
                    before=pair.before, p=p, g=g, any_gap=any_gap, stats=tuple(s.stats for s in sides),
                    total=(p[0][-1] + p[1][-1] + g.missed).astype(jnp.int32),
                    gap_cells=(jnp.sum(g.n_before + g.n_after) + g.missed).astype(jnp.int32))


@stored_jit(static_argnames=("capacity", "cell_rows", "do_prune"))
def emit_pair(plan: PairPlan, m1: OccupancyMap, m2: OccupancyMap, capacity: int, cell_rows: int,
              do_prune: bool):
    """The pair kernel's second phase: ``plan_pair``'s refinement laid out in ``capacity``
    rows (gap cells from a list of ``cell_rows``), pruned if ``do_prune``: ``(map,
    FuseReport)``."""
    def lay(with_gaps):
        return _pair_write((m1, m2), plan.emit, plan.vals, plan.before, plan.p,
                           plan.g if with_gaps else None, None, capacity, cell_rows)

    out, total, n_gap, new_gap_cells = jax.lax.cond(plan.any_gap, lambda: lay(True), lambda: lay(False))
    if do_prune:
        out = tree.prune_runs(out)
    overflow = (total > capacity) | (plan.g.missed > 0) | (n_gap > cell_rows)
    return out, _pair_report(m1, m2, plan.stats, total, out, new_gap_cells, overflow, capacity)


def fuse_pair_planned(m1: OccupancyMap, m2: OccupancyMap, w1, w2, mode, do_prune: bool,
                      gap_capacity: int | None, n_max: int):
    """The pair kernel on the host in two phases, the output sized from the first: its
    refinement's own bucket of rows, room for all its gap cells (the list of leaves with gaps
    starts at ``gap_capacity``, ``None``: ``default_gap_leaves`` of the smallest possible
    output, ``n_max = max(n1, n2)`` cells, and is re-planned larger when it is short).
    Returns ``(map, FuseReport)``."""
    n_in = m1.capacity + m2.capacity
    rows = _first_gap_rows(gap_capacity, n_max, n_in)
    while True:
        plan = plan_pair(m1, m2, w1, w2, mode, gap_rows=rows)
        missed, total, gap_cells = (int(x) for x in jax.device_get((plan.g.missed, plan.total, plan.gap_cells)))
        if not missed:
            break
        rows = min(bucket_capacity(rows + missed), n_in)
    return emit_pair(plan, m1, m2, *_emit_rows(total, gap_cells), do_prune)


def _first_gap_rows(gap_capacity: int | None, n_max: int, n_in: int) -> int:
    """``plan_pair``'s first ``gap_rows``: ``gap_capacity``, else ``default_gap_leaves`` of the
    smallest possible output (``n_max = max(n1, n2)`` cells), at most the inputs' ``n_in`` rows."""
    return min(gap_capacity or default_gap_leaves(bucket_capacity(n_max)), n_in)


def _emit_rows(total: int, gap_cells: int) -> tuple[int, int]:
    """``emit_pair``'s ``(capacity, cell_rows)`` for a refinement of ``total`` cells of which
    ``gap_cells`` are gap cells: the refinement's own bucket, and room for all its gap cells."""
    cap = bucket_capacity(total)
    return cap, min(max(default_gap_capacity(cap) or cap, bucket_capacity(gap_cells)), cap)


def plan_pair_shapes(m1: OccupancyMap, m2: OccupancyMap, gap_capacity: int | None = None) -> PairPlan:
    """The shapes of the ``plan_pair`` result ``fuse_pair_planned`` computes first for ``m1`` and
    ``m2`` (a ``PairPlan`` of ``jax.ShapeDtypeStruct``), by the trace its program compiles from."""
    rows = _first_gap_rows(gap_capacity, max(int(m1.count), int(m2.count)), m1.capacity + m2.capacity)
    weight, mode = jax.ShapeDtypeStruct((), jnp.float32), jax.ShapeDtypeStruct((), jnp.int32)
    return plan_pair.eval_shape(m1, m2, weight, weight, mode, gap_rows=rows)


def precompile_emit_pair(m1: OccupancyMap, m2: OccupancyMap, do_prune: bool, plan: PairPlan) -> bool:
    """Make ready, without running anything, the second-phase program (``emit_pair``) that
    ``fuse_pair_planned`` runs for ``m1`` and ``m2`` (checked maps of one resolution) after a
    first phase of shapes ``plan`` (``plan_pair_shapes``): its sizes from the refinement counted on
    the host (``refinement_cells``). Meant for a thread beside one that fuses the pair, so the
    two phases compile side by side. Returns ``False`` (nothing done) without an open kernel
    store (``kernel_store.StoredJit.precompile``)."""
    return emit_pair.precompile(plan, m1, m2, *_emit_rows(*refinement_cells(m1, m2)), bool(do_prune))


def fuse_pair(m1, m2, w1, w2, mode, capacity: int | None, prune: bool, gap_capacity: int | None,
              what: str):
    """The pair kernel for ``fuse`` / ``fuse_many`` of two checked maps: ``(map,
    FuseReport)``. On the host without a ``capacity`` it is planned first and laid out in
    its refinement's own bucket with room for all its gap cells (``fuse_pair_planned``: the
    refinement has between ``max(n1, n2)`` and ``n1 + n2`` cells, and its gap cells range
    from none to a seventh of it on maps with large coarse leaves, so no size guessed in
    advance fits both); with a ``capacity``, or under ``jit``/``vmap``, it runs in one
    program (``pair_kernel``)."""
    traced = is_traced(m1.count, m2.count)
    n1, n2 = (0, 0) if traced else (int(m1.count), int(m2.count))
    if capacity is None and not traced:
        return fuse_pair_planned(m1, m2, w1, w2, mode, bool(prune), gap_capacity, max(n1, n2))

    def kernel(cap, gcap, gleaves):
        return pair_kernel(m1, m2, w1, w2, mode, cap, bool(prune), gap_capacity=gcap, gap_leaves=gleaves)

    def run(cap):
        return sized_gaps(kernel, cap, traced, gap_capacity)

    return sized_output(run, n1 + n2, capacity, traced, what)
