"""Tree operations on flat leaf arrays: lookup, prune, expand, clamp, max-likelihood,
node counts, and OctoMap-style voxel updates with *local* expansion.

Every operation is a sort, a ``searchsorted``, a segment reduction or a scatter over the
Morton-sorted leaves (``map.py``): no pointers, no recursion, jittable and vmappable. Host
functions plan a static output capacity when the result size depends on the data, then call
a jitted kernel (so maps of one capacity bucket share one compilation).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from . import morton
from ._ops import all_of, bucket_capacity, cummax, cummin, cumsum, materialize, padding_rows, shift_down, shift_up
from ._sort import lexsort_rows
from .budget import check_allocation
from .kernel_store import stored_jit
from .map import OccupancyMap, OccupancyParams, from_leaves, from_words

__all__ = [
    "lookup",
    "lookup_words",
    "lookup_keys",
    "containing_leaf",
    "prune",
    "prune_runs",
    "expand",
    "clamp",
    "to_max_likelihood",
    "num_nodes",
    "from_voxels",
    "update_points",
    "apply_voxel_updates",
    "occupied_mask",
    "equal",
    "coarsen",
]

_D = morton.TREE_DEPTH


# ----------------------------------------------------------------------------- lookup


def lookup_words(m: OccupancyMap, words):
    """Leaf containing each finest code. ``words (..., 2)`` -> ``(row (...,) int32, known (...,) bool)``.

    ``row`` indexes ``m``'s arrays; where ``known`` is False it is clipped garbage. A leaf at
    any depth matches (a pruned leaf covers its whole cube), as OctoMap's ``search``.
    """
    return containing_leaf(m, words, morton.searchsorted_words(m.code, words, side="right") - 1)


def containing_leaf(m: OccupancyMap, words, i):
    """``lookup_words``'s answer from its search: ``i (...,)`` int32 is, for each finest code
    ``words (..., 2)``, the last row of ``m`` whose code is at or before it (``-1``: none).
    Returns ``(row (...,) int32, known (...,) bool)``: the row holds the code's leaf when its
    cube contains the code (and the row is a valid one)."""
    row = jnp.clip(i, 0, m.capacity - 1)
    inside = morton.words_equal(morton.truncate_words(words, m.depth[row]), m.code[row])
    return row, (i >= 0) & (i < m.count) & inside


def lookup_keys(m: OccupancyMap, keys):
    """``lookup_words`` of finest voxel ``keys (..., 3)`` int32 (OctoMap keys, any value):
    ``(row (...,) int32, known (...,) bool)``; a key outside the key range is not known."""
    limit = 2 * morton.KEY_OFFSET
    in_range = jnp.all((keys >= 0) & (keys < limit), axis=-1)
    row, known = lookup_words(m, morton.keys_to_words(jnp.clip(keys, 0, limit - 1)))
    return row, known & in_range


@jax.jit
def _lookup_points(m: OccupancyMap, points):
    keys, in_range = morton.points_to_keys(points, m.resolution)
    row, known = lookup_words(m, morton.keys_to_words(keys))
    known = known & in_range
    return jnp.where(known, m.log_odds[row], jnp.float32(0)), known


def lookup(m: OccupancyMap, points):
    """Log-odds at metric ``points (..., 3)`` [m]: ``(log_odds (...,) float32, known (...,) bool)``.

    Unknown points (no leaf, or outside the key range) give log-odds 0 and ``known=False``.
    Keys are computed in the points' precision on device (float32 by default); for keys
    exactly as OctoMap's double arithmetic, use ``morton.coords_to_keys`` on the host.
    """
    return _lookup_points(m, jnp.asarray(points))


# ----------------------------------------------------------------------------- prune


def _compact(m: OccupancyMap, keep, depth=None, log_odds=None) -> OccupancyMap:
    """Keep the rows where ``keep`` (order preserved), padding the rest."""
    depth = m.depth if depth is None else depth
    log_odds = m.log_odds if log_odds is None else log_odds
    cap = m.capacity
    rank = cumsum(keep.astype(jnp.int32))
    pos = jnp.where(keep, rank - 1, cap)
    # each array scattered into a buffer pre-filled with its padding value: no stacked
    # copy, no second pass to pad (less memory written)
    pad_code, pad_depth, pad_value = padding_rows(cap)
    code = pad_code.at[pos].set(m.code, mode="drop")
    depth = pad_depth.at[pos].set(depth.astype(jnp.int32), mode="drop")
    log_odds = pad_value.at[pos].set(log_odds.astype(jnp.float32), mode="drop")
    return OccupancyMap(code, depth, log_odds, rank[-1], m.params, m.resolution, m.tree_depth)


def prune_runs(m: OccupancyMap) -> OccupancyMap:
    """Maximal prune in one pass.

    A node (depth >= 1: the root is never created, as OctoMap's ``prune`` never prunes it)
    is a leaf of the maximally pruned tree exactly when its whole volume is known with one
    value. On sorted leaves: its Morton interval lies inside one *run* of leaves that are
    contiguous (each starts where the previous ends) with equal log-odds (exact float
    equality, as OctoMap's ``isNodeCollapsible``). So each leaf's final depth is that of its
    shallowest ancestor inside its run ``[rs, re)``, in closed form: the level-``k`` ancestor
    ``a`` of code ``c`` has ``a >= rs`` iff ``3k <= topbit(c ^ rs)`` or ``8^k | rs``, and
    ``a + 8^k <= re`` iff ``3k <= topbit(c ^ re)``. The first leaf of every final node keeps
    it, and one compaction drops the rest.
    """
    cap = m.capacity
    valid = m.valid_mask()
    i = jnp.arange(cap, dtype=jnp.int32)
    ch, cl = m.code[:, 0], m.code[:, 1]
    end = morton.end_words(m.code, m.depth)
    eh, el = end[:, 0], end[:, 1]
    joins_prev = (valid & (shift_down(eh, 1, -1) == ch) & (shift_down(el, 1, -1) == cl)
                  & (shift_down(m.log_odds, 1, jnp.nan) == m.log_odds))
    head = cummax(jnp.where(joins_prev, -1, i))
    joins_next = shift_up(joins_prev, 1, False)
    tail = cummin(jnp.where(joins_next, cap, i), reverse=True)
    gate = m.count >= 0
    rsh, rsl, reh, rel = ch[head], cl[head], eh[tail], el[tail]  # gathered inside the depth pass
    # trailing zero bits of rs (48 for rs = 0), then whole octal digits
    ctz = lambda w: jax.lax.population_count(~w & (w - 1))  # noqa: E731 (32 for w = 0)
    tz = jnp.where(rsl != 0, ctz(rsl), 24 + jnp.minimum(ctz(rsh), 24))
    div3 = lambda x: jax.lax.div(jnp.maximum(x, 0), 3)  # noqa: E731 (non-negative: no floor fix-up)
    k_start = jnp.maximum(div3(morton.top_bit(ch ^ rsh, cl ^ rsl)), div3(tz))
    k_end = div3(morton.top_bit(ch ^ reh, cl ^ rel))
    k = jnp.minimum(jnp.minimum(k_start, k_end), _D - 1)
    depth = materialize(gate, lambda: jnp.minimum(m.depth, _D - k))
    keep = valid & morton.words_equal(morton.truncate_words(m.code, depth), m.code)
    return _compact(m, keep, depth=depth)


_prune = jax.jit(prune_runs)


def prune(m: OccupancyMap) -> OccupancyMap:
    """Prune maximally: every 8 sibling leaves of equal log-odds (exact float equality, as
    OctoMap's ``isNodeCollapsible``) become their parent, repeated bottom-up. Same capacity."""
    return _prune(m)


def equal(a: OccupancyMap, b: OccupancyMap) -> bool:
    """Host check: same resolution and identical valid leaves (codes, depths, log-odds)."""
    if a.resolution != b.resolution or a.num_leaves != b.num_leaves:
        return False
    n = a.num_leaves
    return all(np.array_equal(np.asarray(x)[:n], np.asarray(y)[:n])
               for x, y in ((a.code, b.code), (a.depth, b.depth), (a.log_odds, b.log_odds)))


# ----------------------------------------------------------------------------- expand


@functools.partial(jax.jit, static_argnames=("depth", "capacity"))
def _expand(m: OccupancyMap, depth: int, capacity: int) -> OccupancyMap:
    valid = m.valid_mask()
    target = jnp.maximum(m.depth, depth)
    n_children = jnp.where(valid, jnp.left_shift(1, 3 * (target - m.depth)), 0)
    ends = cumsum(n_children.astype(jnp.int32))
    o = jnp.arange(capacity, dtype=jnp.int32)
    src = jnp.clip(jnp.searchsorted(ends, o, side="right"), 0, m.capacity - 1).astype(jnp.int32)
    k = o - (ends[src] - n_children[src])
    shift = 3 * (_D - target[src])
    code = morton.or_offset_words(m.code[src], k, shift)
    count = ends[-1].astype(jnp.int32)
    ok = o < count
    code = jnp.where(ok[:, None], code, jnp.array([morton.SENTINEL_HI, 0], jnp.int32))
    return OccupancyMap(code, jnp.where(ok, target[src], _D), jnp.where(ok, m.log_odds[src], 0.0),
                        count, m.params, m.resolution, m.tree_depth)


def expand(m: OccupancyMap, depth: int = _D, capacity: int | None = None) -> OccupancyMap:
    """Split every leaf shallower than ``depth`` into its ``8^(depth - d)`` descendants at
    ``depth`` (values copied), like OctoMap's ``expand()`` for ``depth=16``.

    The output capacity is planned on the host (``bucket_capacity`` of the exact count).
    """
    if not 0 <= int(depth) <= _D:
        raise ValueError(f"depth must lie in 0..16, got {depth}")
    d = np.asarray(m.depth)[: m.num_leaves].astype(np.int64)
    needed = int(np.sum(np.left_shift(1, 3 * np.maximum(int(depth) - d, 0)).astype(np.int64)))
    if needed > (1 << 31) - 1:
        raise ValueError(f"expand to depth {depth} would create {needed} leaves (more than 2^31)")
    cap = bucket_capacity(needed) if capacity is None else int(capacity)
    if cap < needed:
        raise ValueError(f"capacity {cap} is smaller than the {needed} expanded leaves")
    check_allocation(cap * 32, f"expand: {needed} leaves at depth {depth} from a map of "
                     f"{m.num_leaves} leaves at {m.resolution:g} m")
    return _expand(m, int(depth), cap)


# ----------------------------------------------------------------------------- values


@jax.jit
def clamp(m: OccupancyMap) -> OccupancyMap:
    """Clip log-odds to ``[clamp_min, clamp_max]`` (padding untouched)."""
    p = m.params
    lo = jnp.where(m.valid_mask(), jnp.clip(m.log_odds, p.clamp_min_log_odds, p.clamp_max_log_odds), 0.0)
    return dataclass_replace(m, log_odds=lo.astype(jnp.float32))


@jax.jit
def to_max_likelihood(m: OccupancyMap) -> OccupancyMap:
    """Every leaf becomes clamp max if occupied (``>= threshold``) else clamp min (OctoMap
    ``toMaxLikelihood``). Not pruned: call ``prune`` (the ``.bt`` writer does both)."""
    p = m.params
    occ = m.log_odds >= p.occupancy_threshold_log_odds
    lo = jnp.where(occ, p.clamp_max_log_odds, p.clamp_min_log_odds)
    return dataclass_replace(m, log_odds=jnp.where(m.valid_mask(), lo, 0.0).astype(jnp.float32))


def occupied_mask(m: OccupancyMap):
    """``(C,)`` bool, valid leaves with ``log_odds >= occupancy threshold``."""
    return m.is_occupied()


def dataclass_replace(m: OccupancyMap, **changes) -> OccupancyMap:
    return dataclasses.replace(m, **changes)


# ----------------------------------------------------------------------------- node count


def num_nodes(m: OccupancyMap) -> int:
    """Number of nodes OctoMap's ``size()`` reports for the same tree: the leaves plus every
    distinct inner node (all ancestors of the leaves, root included). 0 for an empty map.
    Host-side, one pass over the sorted leaves (the count the file writers put in headers)."""
    n = m.num_leaves
    if n == 0:
        return 0
    codes = morton.join_codes(np.asarray(m.code)[:n])
    return int(morton.group_sizes(codes, np.asarray(m.depth)[:n]).sum())


# ----------------------------------------------------------------------------- voxel updates
#
# OctoMap updates one finest voxel by x -> clip(x + delta, lo, hi) (``updateNodeLogOdds``,
# float32); a new voxel starts at 0, and ``updateNode`` returns early when the node found is
# already at the clamp in the update's direction. Repeated updates of one voxel are applied
# in order, one round per repetition, so results are bit-identical to OctoMap's sequence.


def _fold_updates(seg_start, valid, deltas, base, known, lo, hi):
    """Apply each voxel's ordered deltas (rows grouped by voxel, ``seg_start`` marks the first
    row of a group) to its start value ``base``; the result is valid at each group's first row."""
    n = deltas.shape[0]
    idx = jnp.arange(n, dtype=jnp.int32)
    seg_id = cumsum(seg_start.astype(jnp.int32)) - 1
    mult = jax.ops.segment_sum(valid.astype(jnp.int32), seg_id, num_segments=n)[seg_id]

    def body(k, v):
        d = deltas[jnp.clip(idx + k, 0, n - 1)]
        at_clamp = ((d >= 0) & (v >= hi)) | ((d <= 0) & (v <= lo))
        exists = known | (k > 0)
        apply = (k < mult) & ~(exists & at_clamp)
        return jnp.where(apply, jnp.clip(v + d, lo, hi), v)

    return jax.lax.fori_loop(0, jnp.max(mult), body, base)


# _KTH_ABSENT[mask, k] = index of the k-th child (0..7) whose bit is not set in ``mask``.
_KTH_ABSENT = np.zeros((256, 8), np.int32)
for _mask in range(256):
    _absent = [c for c in range(8) if not (_mask >> c) & 1]
    _KTH_ABSENT[_mask, : len(_absent)] = _absent


def _plan_updates(m: OccupancyMap, words, valid):
    """Sort (unless already sorted, as ``insert`` gives them) and look up the updated voxels.
    Returns a dict of arrays used by ``_plan_splits`` and ``_apply_updates``."""
    n = words.shape[0]
    code = jnp.where(valid[:, None], words, jnp.array([morton.SENTINEL_HI, 0], jnp.int32))
    order = jnp.arange(n, dtype=jnp.int32)
    presorted = all_of(~morton.words_less(code[1:], code[:-1]))

    def sort_rows():
        o = lexsort_rows(((code[:, 0], morton.WORD_BITS + 1), (code[:, 1], morton.WORD_BITS)))
        return o, code[o]

    # the identity is the stable sort of sorted rows (no gather on insert's presorted path)
    order, code = jax.lax.cond(presorted, lambda: (order, code), sort_rows)
    valid_sorted = code[:, 0] < morton.SENTINEL_HI
    prev = shift_down(code, 1, -1)
    seg_start = ~morton.words_equal(code, prev)
    row, known = lookup_words(m, code)
    known = known & valid_sorted
    leaf_depth = jnp.where(known, m.depth[row], _D)
    split = known & (leaf_depth < _D)  # inside a coarse leaf: local expansion
    unique = seg_start & valid_sorted
    touched = jnp.zeros(m.capacity, jnp.int32).at[jnp.where(known & unique, row, m.capacity)].max(1, mode="drop")
    return dict(code=code, order=order, seg_start=seg_start, valid=valid_sorted, row=row, known=known,
                leaf_depth=leaf_depth, split=split, unique=unique, touched=touched.astype(bool),
                num_split=jnp.sum(split), num_unique=jnp.sum(unique), num_touched=jnp.sum(touched))


_plan_updates_jit = jax.jit(_plan_updates)


@stored_jit(static_argnames=("split_capacity",))
def _plan_splits(p, split_capacity: int):
    """The sibling 'filler' leaves that local expansion of coarse leaves creates, planned on
    the voxels inside coarse leaves only (compacted to ``split_capacity`` rows; every voxel
    sharing a path node with one of them is one of them, so runs are unchanged).

    Entry ``(j, l)`` stands for the level-``(l-1)`` ancestor of split voxel ``j`` when ``j``
    is the first voxel under it, strictly below its coarse leaf; ``mask`` has a bit per child
    (level ``l``) holding an updated voxel, and ``8 - popcount(mask)`` fillers are created.
    """
    n = split_capacity
    split = p["split"]
    pos = jnp.where(split, cumsum(split.astype(jnp.int32)) - 1, n)
    sidx = jnp.zeros((n,), jnp.int32).at[pos].set(jnp.arange(split.shape[0], dtype=jnp.int32), mode="drop")
    ok = jnp.arange(n) < jnp.sum(split)
    code = jnp.where(ok[:, None], p["code"][sidx], jnp.array([morton.SENTINEL_HI, 0], jnp.int32))
    leaf_depth = jnp.where(ok, p["leaf_depth"][sidx], _D)
    levels = jnp.arange(1, _D + 1, dtype=jnp.int32)  # child level l = 1..16

    def per_level(l):
        anc_parent = morton.truncate_words(code, l - 1)
        anc_child = morton.truncate_words(code, l)
        fp = ~morton.words_equal(anc_parent, shift_down(anc_parent, 1, -1))
        fc = ~morton.words_equal(anc_child, shift_down(anc_child, 1, -1))
        run = cumsum(fp.astype(jnp.int32)) - 1
        bits = jnp.where(fc, jnp.left_shift(1, morton.child_index_words(code, l)), 0)
        return fp, jax.ops.segment_sum(bits, run, num_segments=n)[run]

    first_parent, masks = jax.vmap(per_level, out_axes=1)(levels)  # (n, 16) each
    masks = masks.astype(jnp.int32)
    active = first_parent & ok[:, None] & (levels[None, :] > leaf_depth[:, None])
    popcount = jnp.sum((masks[..., None] >> jnp.arange(8)) & 1, axis=-1)
    n_fill = jnp.where(active, 8 - popcount, 0).reshape(-1)
    return dict(sidx=sidx, masks=masks.reshape(-1), n_fill=n_fill, num_fill=jnp.sum(n_fill))


@stored_jit(static_argnames=("fill_capacity", "capacity"))
def _apply_updates(m: OccupancyMap, p, s, deltas, fill_capacity: int, capacity: int):
    n = deltas.shape[0]
    code = p["code"]
    base = jnp.where(p["known"], m.log_odds[p["row"]], jnp.float32(0))
    new_value = _fold_updates(p["seg_start"], p["valid"], deltas[p["order"]], base, p["known"],
                              m.params.clamp_min_log_odds, m.params.clamp_max_log_odds)
    new_value = new_value.astype(jnp.float32)
    voxel_keep = p["seg_start"] & p["valid"]

    # Fillers: the absent children of each path node, valued as the coarse leaf they split.
    ends = cumsum(s["n_fill"].astype(jnp.int32))
    o = jnp.arange(fill_capacity, dtype=jnp.int32)
    e = jnp.clip(jnp.searchsorted(ends, o, side="right"), 0, s["n_fill"].shape[0] - 1).astype(jnp.int32)
    k = o - (ends[e] - s["n_fill"][e])
    j, lvl = s["sidx"][e // _D], e % _D + 1  # j: the split voxel's row in the sorted updates
    child = jnp.asarray(_KTH_ABSENT)[s["masks"][e], jnp.clip(k, 0, 7)]
    fill_code = morton.or_offset_words(morton.truncate_words(code[j], lvl - 1), child, 3 * (_D - lvl))
    fill_ok = o < ends[-1]
    fill_value = m.log_odds[p["row"][j]]

    # Old leaves (sorted), updated voxels (sorted by the plan; repeated rows keep their code so
    # the list stays sorted) and fillers (few: sorted here) are merged, not re-sorted; then
    # the dropped rows (touched old leaves, repeats, padding) are compacted away.
    keep_old = m.valid_mask() & ~p["touched"]
    bits = lambda v: jax.lax.bitcast_convert_type(v.astype(jnp.float32), jnp.int32)  # noqa: E731
    sent = jnp.int32(morton.SENTINEL_HI)
    old = (m.code[:, 0], m.code[:, 1], m.depth, bits(m.log_odds), keep_old.astype(jnp.int32))
    voxels = (code[:, 0], code[:, 1], jnp.full((n,), _D, jnp.int32), bits(new_value),
              voxel_keep.astype(jnp.int32))
    fillers = jax.lax.sort((jnp.where(fill_ok, fill_code[:, 0], sent), jnp.where(fill_ok, fill_code[:, 1], 0),
                            lvl, bits(fill_value), fill_ok.astype(jnp.int32)), num_keys=2)
    hi, lo, depth, value, keep = morton.merge_sorted(old, morton.merge_sorted(voxels, fillers))
    keep = keep != 0
    rank = cumsum(keep.astype(jnp.int32))
    pos = jnp.where(keep, rank - 1, capacity)
    put = lambda x, fill: jnp.full((capacity,), fill, jnp.int32).at[pos].set(x, mode="drop")  # noqa: E731
    out = OccupancyMap(
        jnp.stack([put(hi, morton.SENTINEL_HI), put(lo, 0)], axis=-1),
        put(depth, _D),
        jax.lax.bitcast_convert_type(put(value, 0), jnp.float32),
        rank[-1], m.params, m.resolution, m.tree_depth,
    )
    return _prune(out)


def _apply(m: OccupancyMap, words, deltas, valid, sizes=None) -> OccupancyMap:
    grow = sizes.grow if sizes is not None else lambda _name, n, minimum: bucket_capacity(n, minimum)
    words = jnp.asarray(words, jnp.int32).reshape(-1, 2)
    n = words.shape[0]
    if n == 0:
        return m
    plan = _plan_updates_jit(m, words, valid)
    num_split, num_unique, num_touched = (int(x) for x in jax.device_get(
        (plan["num_split"], plan["num_unique"], plan["num_touched"])))
    # only the arrays it reads: ``touched`` has the map's capacity, which is no key of this program
    inputs = {k: plan[k] for k in ("split", "code", "leaf_depth")}
    splits = _plan_splits(inputs, grow("split_rows", _split_rows(num_split, n), 1))
    num_fill = int(splits["num_fill"])
    needed = m.num_leaves - num_touched + num_fill + num_unique
    cap = bucket_capacity(max(needed, m.capacity))
    if sizes is not None and cap > m.capacity:  # a run of updates grows with headroom: fewer capacities
        cap = grow("leaves", 2 * needed, 1)
    check_allocation(3 * cap * 16, f"voxel updates: {needed} leaves after {num_unique} updated "
                     f"voxels on a map of {m.num_leaves} leaves at {m.resolution:g} m")
    if cap > m.capacity:  # grown first: the update compiles once per output capacity
        plan = {**plan, "touched": jnp.pad(plan["touched"], (0, cap - m.capacity))}
        m = m.with_capacity(cap)
    return _apply_updates(m, plan, splits, deltas, grow("fill_rows", num_fill, 1024), cap)


def _split_rows(num_split: int, n: int) -> int:
    """Rows of ``_plan_splits`` for ``num_split`` voxels inside coarse leaves among ``n``
    updates: ``4096 * 16^k``, at most ``n``'s bucket. Steps of 16 rather than 2, from more
    rows than the first scans need: a run of scans meets a few sizes, so the updates compile
    a few programs (the rows cost little)."""
    rows = 4096
    while rows < num_split:
        rows *= 16
    return min(rows, bucket_capacity(n))


def _pad_rows(x, n_cap, fill):
    x = np.asarray(x)
    out = np.full((n_cap,) + x.shape[1:], fill, dtype=x.dtype)
    out[: x.shape[0]] = x
    return out


def apply_voxel_updates(m: OccupancyMap, words, deltas, valid=None, *, sizes=None) -> OccupancyMap:
    """Add log-odds ``deltas (n,)`` to the finest voxels ``words (n, 2)`` with OctoMap's
    per-update clamping (``updateNodeLogOdds``), in row order for repeated voxels.

    Unknown voxels start at 0; a voxel inside a coarse (pruned) leaf splits that leaf
    locally (thesis §5.2.3 case 3: siblings along the path inherit the leaf's value) and the
    result is pruned maximally. Capacity grows to the next bucket when needed.

    ``sizes``: optional ``insert.CapacityPlan`` (anything with its ``grow(name, n, minimum)``)
    keeping high-water marks of the update's work sizes (``split_rows``, ``fill_rows``)
    across calls, so a run of updates compiles each size once; a map that must grow then
    grows to twice the leaves it needs (``leaves``), and the caller trims it at the end.
    """
    deltas = jnp.asarray(deltas, jnp.float32).reshape(-1)
    n = deltas.shape[0]
    valid = jnp.ones((n,), bool) if valid is None else jnp.asarray(valid, bool).reshape(-1)
    return _apply(m, words, deltas, valid, sizes)


def update_points(m: OccupancyMap, points, occupied) -> OccupancyMap:
    """OctoMap ``updateNode(point, occupied)`` for one point ``(3,)`` or many ``(n, 3)`` in
    order: a hit adds ``hit_log_odds``, a miss ``miss_log_odds``, clamped after every update,
    then pruned. ``occupied`` is a bool or ``(n,)`` bools. Raises ``ValueError`` for points
    outside the key range."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    occ = np.broadcast_to(np.asarray(occupied, dtype=bool).reshape(-1), (pts.shape[0],))
    keys = morton.coords_to_keys(pts, m.resolution, name="points")
    n_cap = bucket_capacity(pts.shape[0], 64)
    words = _pad_rows(morton.split_codes(morton.keys_to_codes(keys)), n_cap, 0)
    p = m.params
    deltas = jnp.where(jnp.asarray(_pad_rows(occ, n_cap, False)), p.hit_log_odds, p.miss_log_odds)
    valid = _pad_rows(np.ones(pts.shape[0], bool), n_cap, False)
    return apply_voxel_updates(m, words, deltas, valid)


def from_voxels(centers, log_odds, resolution: float, depth: int = _D,
                params: OccupancyParams | None = None, prune_result: bool = True) -> OccupancyMap:
    """Build a map from voxel centres ``(n, 3)`` [m] and ``log_odds (n,)``: each point sets the
    depth-``depth`` node containing it; duplicates are summed, then clamped and (by default)
    pruned maximally."""
    params = OccupancyParams() if params is None else params
    pts = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    values = np.broadcast_to(np.asarray(log_odds, np.float32).reshape(-1), (pts.shape[0],))
    if not 0 <= int(depth) <= _D:
        raise ValueError(f"depth must lie in 0..16, got {depth}")
    if not np.all(np.isfinite(values)):
        raise ValueError("log_odds must be finite")
    keys = morton.coords_to_keys(pts, resolution, name="centers")
    shift = np.uint64(3 * (_D - int(depth)))
    codes = (morton.keys_to_codes(keys) >> shift) << shift
    uniq, inverse = np.unique(codes, return_inverse=True)
    sums = np.bincount(inverse.reshape(-1), weights=values.astype(np.float64), minlength=uniq.size)
    lo = float(np.asarray(params.clamp_min_log_odds))
    hi = float(np.asarray(params.clamp_max_log_odds))
    sums = np.clip(sums.astype(np.float32), np.float32(lo), np.float32(hi))
    m = from_words(morton.split_codes(uniq), np.full(uniq.size, int(depth), np.int32), sums,
                   resolution, params, bucket_capacity(uniq.size))
    if not prune_result:
        return m
    pruned = prune(m)
    return pruned.trimmed()


# ----------------------------------------------------------------------------- coarsening


def coarsen(m: OccupancyMap, k: int, capacity: int | None = None, *,
            resolution: float | None = None) -> OccupancyMap:
    """Map ``m`` coarsened by ``2^k`` per axis and relabelled as a map of resolution
    ``res * 2^k``: a leaf finer than ``2^k`` voxels goes to the coarse cell containing it
    (cells take the maximum log-odds of their known children, OctoMap's inner-node rule); a
    coarser leaf keeps its extent (depth ``d -> d + k``). Centres keep their metric positions
    (cell ``i`` of the coarse map covers exactly ``2^k`` voxels ``i * 2^k ...``). With
    ``resolution`` given, the result is labelled with it instead (the dense alignment stores
    every level at the finest resolution and scales the sample points). ``capacity``: of the
    result (default ``bucket_capacity`` of its leaves). Host function.

    Raises ``ValueError`` for ``k`` outside 0..15 or a depth-0 (root) leaf with ``k > 0``.
    """
    k = int(k)
    if not 0 <= k < _D:
        raise ValueError(f"k (coarsening level) must lie in 0..15, got {k}")
    if k == 0:
        return m if capacity is None else m.with_capacity(capacity)
    lv = m.leaves()
    if lv.depths.size and lv.depths.min() < 1:
        raise ValueError("coarsen: a depth-0 (root) leaf cannot be relabelled; expand it first")
    keys = lv.keys.astype(np.int64) - morton.KEY_OFFSET
    new_keys = (keys >> k) + morton.KEY_OFFSET  # floor division: exact for coarse leaves
    new_depth = np.minimum(lv.depths + k, _D)
    codes = morton.keys_to_codes(new_keys.astype(np.uint64))
    span = np.uint64(1) << (np.uint64(3) * (_D - new_depth).astype(np.uint64))
    codes = codes & ~(span - np.uint64(1))
    # ``leaves()`` come in Morton order and stay in it (the relabelling keeps each axis's order and
    # the levels' precedence); equal codes are depth-16 cells of leaves finer than 2^k: no sort
    first = np.ones(codes.shape, bool)
    first[1:] = codes[1:] != codes[:-1]
    lo = lv.log_odds.astype(np.float32)
    val = np.maximum.reduceat(lo, np.flatnonzero(first)) if codes.size else lo
    res = m.resolution * 2.0 ** k if resolution is None else resolution
    return from_leaves(codes[first], new_depth[first], val, res, m.params, capacity=capacity)
