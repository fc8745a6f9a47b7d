"""The final maximal prune of ``transform_map``'s output.

The kernel prunes inside each brick, so its leaves finer than a brick are maximal already;
only whole-brick leaves (depth 13) can still merge with their siblings. Those few are merged
on the host (``_prune_whole_bricks``) and the kernel's output is compacted in place on the
device (``_apply_brick_merges``).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from .. import morton
from .._ops import bucket_capacity
from ..map import OccupancyMap
from ._bricks import BRICK_DEPTH

__all__ = ["merge_whole_bricks"]

_D = morton.TREE_DEPTH
_COMPACT_CHUNK = 1 << 16  # rows per step of the in-place compaction


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
        shift = np.uint64(3 * (_D - d + 1))
        parent = c >> shift
        start = np.ones(c.size, bool)
        start[1:] = parent[1:] != parent[:-1]
        gid = np.cumsum(start) - 1
        first = np.flatnonzero(start)
        size = np.diff(np.append(first, c.size))
        uniform = np.bincount(gid, weights=v != v[first][gid], minlength=first.size) == 0
        merge = (size == 8) & uniform
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
    n_drop = jnp.sum(drop < cap, dtype=jnp.int32)
    fills = (jnp.array([morton.SENTINEL_HI, 0], jnp.int32), jnp.int32(_D), jnp.float32(0))

    def body(k, bufs):
        start = k * step
        local = jnp.where(drop >= start, drop - start, step)  # no negative (wrapping) index
        keep = jnp.ones(step, bool).at[local].set(False, mode="drop")
        pos = jnp.where(keep, jnp.cumsum(keep) - 1, step)
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
