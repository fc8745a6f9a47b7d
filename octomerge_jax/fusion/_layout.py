"""Writing the common refinement into the output rows: the leaves' own cells scattered to
their slots, gap cells computed in closed form (``_gaps``) at theirs, either on every slot
of the output or from a compact list of gap cells."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import morton
from .._ops import cummax, cumsum, float_bits, materialize, padding_rows
from ..map import OccupancyMap
from ._gaps import cell_code, gap_cell_info, gap_cell_once

_D = morton.TREE_DEPTH


class Cells(NamedTuple):
    """Cells written as they are (a map's own leaves), ``n`` rows."""

    slot: jax.Array  # (n,) int32 output row; past the capacity: dropped
    code: jax.Array  # (n, 2) int32 words
    depth: jax.Array  # (n,) int32
    value: jax.Array  # (n,) float32 log-odds


class Intervals(NamedTuple):
    """Intervals ``[s, e)`` whose ``count`` aligned cells go to rows ``slot, slot + 1, ...``
    (``n`` intervals, each field ``(n,)``)."""

    slot: jax.Array  # int32 row of the first cell
    count: jax.Array  # int32 cells (0: nothing written)
    s_hi: jax.Array  # int32 start words
    s_lo: jax.Array
    e_hi: jax.Array  # int32 end words (may be 2^48)
    e_lo: jax.Array
    value: jax.Array  # float32 log-odds of every cell


def excl_at(incl, idx):
    """``sum(count[:idx])`` from the inclusive prefix sum ``incl`` (0 for ``idx <= 0``)."""
    return jnp.where(idx > 0, incl[jnp.clip(idx - 1, 0, incl.shape[0] - 1)], 0)


def cell_owners(n, rows: int):
    """Cells laid out owner after owner (owner ``k`` has ``n[k]`` of them, in order), in a
    list of ``rows``: ``(owner, index within the owner, cells in all)`` per row, by a
    cumulative max over the owners' first rows (rows past the cells repeat the last owner)."""
    first = cumsum(n) - n  # the owner's first row
    mark = jnp.zeros((rows,), jnp.int32).at[jnp.where(n > 0, first, rows)].set(
        jnp.arange(n.shape[0], dtype=jnp.int32) + 1, mode="drop")
    owner = jnp.maximum(cummax(mark) - 1, 0)
    return owner, jnp.arange(rows, dtype=jnp.int32) - first[owner], first[-1] + n[-1]


def put_selfs(code, depth, val, selfs: list[Cells], total, cap: int, like: OccupancyMap):
    """The output map: ``selfs`` written over the slots they own (whatever the gap fill put
    there; their code and depth are the input arrays, no stacked copy), ``min(total, cap)``
    valid rows, ``like``'s params, resolution and tree depth."""
    for c in selfs:
        code = code.at[c.slot].set(c.code, mode="drop")
        depth = depth.at[c.slot].set(c.depth, mode="drop")
        val = val.at[c.slot].set(c.value, mode="drop")
    return OccupancyMap(code, depth, val, jnp.minimum(total, cap).astype(jnp.int32),
                        like.params, like.resolution, like.tree_depth)


def emit(capacity: int, total, selfs: list[Cells], gaps: list[Intervals], like: OccupancyMap,
         gap_capacity: int | None = None):
    """Lay out the common refinement (``capacity`` rows, Morton order) as an unpruned map
    with ``like``'s params.

    ``selfs`` are written as they are, ``gaps`` cut into their cells. Slots past
    ``capacity`` are dropped (``total > capacity`` is the overflow). Every slot of a gap finds
    its gap by a cumulative max over gap start slots and computes its cell in closed form.
    With ``gap_capacity`` (static, below ``capacity``) that is done on a compact list of at
    most ``gap_capacity`` gap cells (more is an overflow the caller reports), not on every
    slot.
    """
    if gaps and gap_capacity is not None and gap_capacity < capacity:
        code, depth, val = _compact_gap_cells(capacity, gap_capacity, gaps)
    elif gaps:
        code, depth, val = _slot_gap_cells(capacity, total, gaps)
    else:
        code, depth, val = padding_rows(capacity)
    return put_selfs(code, depth, val, selfs, total, capacity, like)


def _slot_gap_cells(cap: int, total, gaps: list[Intervals]):
    """Gap cells on every slot: ``(code (cap, 2), depth, value)``, each slot below ``total``
    holding the cell of the gap that covers it (the leaves' own cells go on top)."""
    gap_rows = jnp.zeros((cap, 6), jnp.int32)  # s_hi, s_lo, e_hi, e_lo, value, start slot + 1
    for g in gaps:
        slot = jnp.where(g.count > 0, g.slot, cap)
        gap_rows = gap_rows.at[slot].set(
            jnp.stack([g.s_hi, g.s_lo, g.e_hi, g.e_lo, float_bits(g.value), slot + 1], -1), mode="drop")
    q = jnp.arange(cap, dtype=jnp.int32)
    start = cummax(gap_rows[:, 5]) - 1
    g = gap_rows[jnp.maximum(start, 0)]
    g0, g1, g2, g3 = g[:, 0], g[:, 1], g[:, 2], g[:, 3]
    info = materialize(total >= 0, lambda: gap_cell_info(g0, g1, g2, g3, q - start))
    ch, cl, cd = cell_code(g0, g1, g2, g3, info)
    ok = q < total
    code = jnp.stack([jnp.where(ok, ch, morton.SENTINEL_HI), jnp.where(ok, cl, 0)], -1)
    depth = jnp.where(ok, cd, _D)
    val = jnp.where(ok, jax.lax.bitcast_convert_type(g[:, 4], jnp.float32), 0.0)
    return code, depth, val


def _compact_gap_cells(capacity: int, gap_capacity: int, gaps: list[Intervals]):
    """Gap cells from a compact list: ``(code (capacity, 2), depth, value)`` holding the first
    ``gap_capacity`` gap cells at their slots and padding elsewhere (the leaves' own cells go
    on top, ``put_selfs``). Only nonempty gaps are gathered (the ``r``-th one by a binary
    search in the prefix count of nonempty gaps, concatenated over the gap lists), then each
    gap cell finds its gap by a cumulative max over a ``gap_capacity``-row list."""
    cap, gcap = capacity, gap_capacity
    lens = [g.count.shape[0] for g in gaps]
    offs = np.cumsum([0] + lens)
    nonempty = cumsum(jnp.concatenate([(g.count > 0).astype(jnp.int32) for g in gaps]))
    r = jnp.arange(gcap, dtype=jnp.int32)
    gi = jnp.searchsorted(nonempty, r, side="right", method="scan").astype(jnp.int32)
    which = sum((gi >= int(o)).astype(jnp.int32) for o in offs[1:-1])
    fields = []
    for f in range(len(Intervals._fields)):  # each field of the r-th nonempty gap
        x = None
        for j, g in enumerate(gaps):
            xj = g[f][jnp.clip(gi - int(offs[j]), 0, lens[j] - 1)]
            x = xj if x is None else jnp.where(which == j, xj, x)
        fields.append(x)
    slot, n, sh, sl, eh, el, v = fields
    n = jnp.where(r < nonempty[-1], n, 0)
    g, t, n_cells = cell_owners(n, gcap)  # the gap of each gap cell
    ch, cl, cd = gap_cell_once(n_cells >= 0, lambda: (sh[g], sl[g], eh[g], el[g]), t)
    dst = jnp.where(r < n_cells, slot[g] + t, cap)
    code, depth, val = padding_rows(cap)
    return (code.at[dst].set(jnp.stack([ch, cl], -1), mode="drop"),
            depth.at[dst].set(cd, mode="drop"), val.at[dst].set(v[g], mode="drop"))
