"""The final maximal prune of ``transform_map``'s output.

The kernel prunes inside each brick, so its leaves finer than a brick are maximal already;
only whole-brick leaves (depth 13) can still merge with their siblings. Those few are merged
on the host (``_prune_whole_bricks``) and the kernel's output is compacted in place on the
device (``_apply_brick_merges``). Where the refinement (``_cells.py``) made uniform coarse
cells, those and the whole-brick leaves are pruned together on the host (``_prune_cells``)
and merged into the kernel's finer leaves by a merge path (``merge_with_cells``).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from .. import morton
from .._ops import bucket_capacity, count_true, cumsum
from ..budget import check_allocation
from ..map import OccupancyMap, from_words
from ._bricks import BRICK_DEPTH

__all__ = ["merge_whole_bricks", "merge_with_cells"]

_D = morton.TREE_DEPTH
_COMPACT_CHUNK = 1 << 16  # rows per step of the in-place compaction
HOST_MERGE_MAX = 1 << 16  # outputs up to this many leaves join the coarse cells on the host


def _prune_whole_bricks(codes, values):
    """Maximal prune of whole-brick leaves ``codes (n,) uint64`` (sorted, all depth 13) with
    log-odds ``values (n,)``: eight siblings of equal log-odds (exact float equality, as
    ``tree.prune``) merge into their parent, level by level. A merged node keeps its first
    child's code and value. Returns ``(drop (k,), head (r,), head_depth (r,))``: indices of
    the children that disappear, and of the first children that now stand for a coarser node,
    with its depth."""
    n = codes.size
    depth = np.full(n, BRICK_DEPTH, np.int32)
    dropped = np.zeros(n, bool)
    row = np.arange(n)  # the first original row under each active node
    c, v = codes, values
    for d in range(BRICK_DEPTH, 0, -1):
        if c.size < 8:
            break
        shift, parent, start, gid, first, merge = _full_uniform_siblings(c, v, d)
        if not merge.any():
            break
        merged = merge[gid]
        dropped[row[merged & ~start]] = True
        keep = first[merge]
        depth[row[keep]] = d - 1
        c, v, row = parent[keep] << shift, v[keep], row[keep]
    head = np.flatnonzero((depth != BRICK_DEPTH) & ~dropped)
    return np.flatnonzero(dropped), head, depth[head]


@functools.partial(jax.jit, donate_argnums=(0, 1, 2), static_argnames=("step",))
def _apply_brick_merges(code, depth, log_odds, count, drop, head, head_depth, *,
                        step: int = _COMPACT_CHUNK):
    """In place (the buffers are donated): drop rows ``drop`` (sorted ascending, padded with
    the capacity) of the brick-pruned output ``code (n, 2), depth (n,), log_odds (n,)``
    holding ``count`` rows, and set the depth of rows ``head`` to ``head_depth`` (padding: out
    of range). Returns ``(code, depth, log_odds, new_count)``, order kept.

    Only the rows after the first dropped one move, each by the number of drops before it:
    a loop over chunks of rows reads a chunk, compacts it and writes it back at its new start,
    which is never after its old start, so no unread row is overwritten. ``step``: rows per
    loop step (static; capped to the largest power of two dividing the capacity)."""
    cap = code.shape[0]
    step = min(step, cap & -cap)  # capacities are q 2^k
    depth = depth.at[head].set(head_depth, mode="drop")
    n_drop = count_true(drop < cap)
    fills = (jnp.array([morton.SENTINEL_HI, 0], jnp.int32), jnp.int32(_D), jnp.float32(0))

    def body(k, bufs):
        start = k * step
        local = jnp.where(drop >= start, drop - start, step)  # no negative (wrapping) index
        keep = jnp.ones(step, bool).at[local].set(False, mode="drop")
        pos = jnp.where(keep, cumsum(keep.astype(jnp.int32)) - 1, step)
        dst = start - jnp.searchsorted(drop, start).astype(jnp.int32)
        out = []
        for buf, fill in zip(bufs, fills):
            rows = jax.lax.dynamic_slice_in_dim(buf, start, step)
            packed = jnp.full_like(rows, fill).at[pos].set(rows, mode="drop")
            out.append(jax.lax.dynamic_update_slice_in_dim(buf, packed, dst, axis=0))
        return tuple(out)

    first = jnp.where(n_drop > 0, drop[0] // step, 0)
    last = jnp.where(n_drop > 0, (count + step - 1) // step, 0)
    bufs = jax.lax.fori_loop(first, last, body, (code, depth, log_odds))
    new_count = count - n_drop
    stale = jnp.where(jnp.arange(drop.shape[0]) < n_drop,
                      new_count + jnp.arange(drop.shape[0], dtype=jnp.int32), cap)
    bufs = [buf.at[stale].set(fill, mode="drop") for buf, fill in zip(bufs, fills)]
    return (*bufs, new_count)


def _padded(x, dtype, fill):
    """``x`` padded with ``fill`` to a power-of-two length (few compiled shapes)."""
    out = np.full(bucket_capacity(x.size, minimum=64), fill, dtype)
    out[:x.size] = x
    return out


def merge_whole_bricks(out: OccupancyMap, total: int) -> OccupancyMap:
    """The kernel's brick-pruned output ``out`` (``total`` rows) pruned maximally, in place
    (its buffers are donated)."""
    rows13 = np.flatnonzero(np.asarray(out.depth)[:total] == BRICK_DEPTH)
    codes = morton.join_codes(np.asarray(out.code)[rows13])
    drop, head, head_depth = _prune_whole_bricks(codes, np.asarray(out.log_odds)[rows13])
    oob = out.capacity  # padding index: dropped by the scatters
    code, depth, log_odds, count = _apply_brick_merges(
        out.code, out.depth, out.log_odds, out.count, _padded(rows13[drop], np.int32, oob),
        _padded(rows13[head], np.int32, oob), _padded(head_depth, np.int32, _D))
    return OccupancyMap(code, depth, log_odds, count, out.params, out.resolution, out.tree_depth)


def _prune_cells(codes, depths, values):
    """Maximal prune of disjoint leaves of depth <= 13 (``codes (n,) uint64`` sorted,
    ``depths (n,)``, ``values (n,) float32``): eight siblings of equal log-odds (exact float
    equality, as ``tree.prune``) merge into their parent, level by level. Returns the pruned
    ``(codes, depths, values)``, sorted."""
    levels = {int(d): (codes[depths == d], values[depths == d]) for d in np.unique(depths)}
    for d in range(BRICK_DEPTH, 0, -1):
        if d not in levels or levels[d][0].size < 8:
            continue
        c, v = levels[d]
        shift, parent, start, gid, first, merge = _full_uniform_siblings(c, v, d)
        if not merge.any():
            continue
        gone = merge[gid]
        levels[d] = (c[~gone], v[~gone])
        pc, pv = parent[first[merge]] << shift, v[first[merge]]
        if d - 1 in levels:
            pc, pv = np.concatenate([levels[d - 1][0], pc]), np.concatenate([levels[d - 1][1], pv])
            order = np.argsort(pc, kind="stable")
            pc, pv = pc[order], pv[order]
        levels[d - 1] = (pc, pv)
    out_c = np.concatenate([c for c, _ in levels.values()])
    out_d = np.concatenate([np.full(c.size, d, np.int32) for d, (c, _) in levels.items()])
    out_v = np.concatenate([v for _, v in levels.values()])
    order = np.argsort(out_c, kind="stable")
    return out_c[order], out_d[order], out_v[order]


@functools.partial(jax.jit, static_argnames=("capacity",))
def _merge_leaves(code, depth, log_odds, c_code, c_depth, c_log_odds, *, capacity: int):
    """Merge two Morton-sorted leaf lists (padding ``(SENTINEL_HI, 0)`` last; disjoint) into
    ``capacity`` rows: ``(code (capacity, 2), depth, log_odds)`` (merge path, no sort)."""
    merged = morton.merge_sorted((code[:, 0], code[:, 1], depth, log_odds),
                                 (c_code[:, 0], c_code[:, 1], c_depth, c_log_odds))
    n = merged[0].shape[0]
    if capacity <= n:
        merged = tuple(x[:capacity] for x in merged)
    else:
        fills = (morton.SENTINEL_HI, 0, _D, 0)
        merged = tuple(jnp.concatenate([x, jnp.full((capacity - n,), f, x.dtype)])
                       for x, f in zip(merged, fills))
    return jnp.stack(merged[:2], -1), merged[2], merged[3]


def merge_with_cells(out: OccupancyMap | None, total: int, codes, depths, values,
                     like: OccupancyMap) -> OccupancyMap:
    """The kernel's brick-pruned output ``out`` (``total`` rows; ``None``: no kernel bricks)
    joined with the uniform coarse cells ``codes (c,) uint64, depths (c,), values (c,)``
    (Morton-sorted, disjoint from the kernel's bricks) and pruned maximally. ``like``: the
    source map (parameters, resolution). ``out``'s buffers are donated."""
    if out is not None and codes.size == 0:
        return merge_whole_bricks(out, total)
    if out is not None:  # whole-brick kernel leaves join the cells on the host
        rows13 = np.flatnonzero(np.asarray(out.depth)[:total] == BRICK_DEPTH)
        codes = np.concatenate([codes, morton.join_codes(np.asarray(out.code)[rows13])])
        depths = np.concatenate([depths, np.full(rows13.size, BRICK_DEPTH, np.int32)])
        values = np.concatenate([values, np.asarray(out.log_odds)[rows13]])
        order = np.argsort(codes, kind="stable")
        codes, depths, values = codes[order], depths[order], values[order]
    codes, depths, values = _prune_cells(codes, depths.astype(np.int32), values)
    n_kernel = 0 if out is None else total - rows13.size
    n = n_kernel + codes.size
    check_allocation(3 * bucket_capacity(n) * 16,
                     f"transform_map: an output of {n} leaves at {like.resolution:g} m")
    words = morton.split_codes(codes)
    if out is None or n_kernel == 0:
        return from_words(words, depths, values, like.resolution, like.params)
    if n <= HOST_MERGE_MAX:  # small: merge on the host (no compilation for each shape)
        keep = np.ones(total, bool)
        keep[rows13] = False
        words = np.concatenate([np.asarray(out.code)[:total][keep], words])
        depths = np.concatenate([np.asarray(out.depth)[:total][keep], depths])
        values = np.concatenate([np.asarray(out.log_odds)[:total][keep], values])
        order = np.argsort(morton.join_codes(words), kind="stable")
        return from_words(words[order], depths[order], values[order], like.resolution,
                          like.params)
    oob = out.capacity
    none = np.zeros(0, np.int32)
    code, depth, log_odds, _ = _apply_brick_merges(
        out.code, out.depth, out.log_odds, out.count, _padded(rows13, np.int32, oob),
        _padded(none, np.int32, oob), _padded(none, np.int32, _D))
    cap = bucket_capacity(codes.size, minimum=64)
    c_code = np.zeros((cap, 2), np.int32)
    c_code[:, 0] = morton.SENTINEL_HI
    c_code[:codes.size] = words
    c_depth = np.full(cap, _D, np.int32)
    c_depth[:codes.size] = depths
    c_lo = np.zeros(cap, np.float32)
    c_lo[:codes.size] = values
    code, depth, log_odds = _merge_leaves(code, depth, log_odds, c_code, c_depth, c_lo,
                                          capacity=bucket_capacity(n))
    return OccupancyMap(code, depth, log_odds, jnp.int32(n), like.params, like.resolution,
                        like.tree_depth)


def _full_uniform_siblings(c, v, d: int):
    """Groups of siblings among sorted leaves ``c (n,) uint64`` of depth ``d`` with values
    ``v (n,)``: ``(shift, parent (n,), start (n,) bool, gid (n,), first (g,), merge (g,) bool)``,
    ``merge`` marking the groups of all eight children with one value (exact equality)."""
    shift = np.uint64(3 * (_D - d + 1))
    parent = c >> shift
    start = np.ones(c.size, bool)
    start[1:] = parent[1:] != parent[:-1]
    gid = np.cumsum(start) - 1
    first = np.flatnonzero(start)
    size = np.diff(np.append(first, c.size))
    uniform = np.bincount(gid, weights=v != v[first][gid], minlength=first.size) == 0
    return shift, parent, start, gid, first, (size == 8) & uniform
