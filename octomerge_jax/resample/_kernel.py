"""The jitted kernel of ``transform_map``: destination bricks in fixed-size chunks, each voxel
mapped back (eq. 5.13) and blended from its 8 source neighbours (eqs. 3.6-3.13), each brick
pruned inside itself (levels 16 -> 13) and its leaves appended to growable output buffers.

Every per-voxel quantity is a ``(B, 512)`` array per axis or per corner (no trailing axis of
3 or 8), so XLA's CPU loops vectorise, and the 8 neighbour reads are 8 flat gathers from the
source's brick table (``_bricks.SourceView``).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import morton
from .._ops import count_true, cumsum, quarter_octave_capacity, to_device
from ..budget import check_allocation
from ..kernel_store import stored_jit
from ..map import OccupancyMap
from ._bricks import BRICK_EDGE, BRICK_VOXELS, LOCAL_OFFSETS, KernelInputs, Plan
from ._interp import KEY_MAX, blend

__all__ = ["OutputLeaves", "run_kernel", "transform_kernel"]

_D = morton.TREE_DEPTH
_SNAP = 1e-5  # offsets closer than this (in voxels) to a lattice point are snapped


class OutputLeaves(NamedTuple):
    """The kernel's output buffers: brick-pruned leaves, then padding rows."""

    code: jax.Array  # (capacity, 2) int32 Morton code words; padding (SENTINEL_HI, 0)
    depth: jax.Array  # (capacity,) int32 leaf depth 13..16; padding 16
    log_odds: jax.Array  # (capacity,) float32 clamped log-odds; padding 0


class _LoopState(NamedTuple):
    """Carry of ``transform_kernel``'s loop over chunks."""

    bufs: OutputLeaves  # output so far
    offset: jax.Array  # () int32 rows of ``bufs`` in use
    chunk: jax.Array  # () int32 next chunk to compute
    misses: jax.Array  # () int32 neighbour keys outside their window so far (0 unless a bug)
    full: jax.Array  # () bool: chunk ``chunk`` did not fit in ``bufs``


def _spread3bits(v):
    """Bits (b2 b1 b0) -> (b2 0 0 b1 0 0 b0): one axis of a local Morton index."""
    return (v & 1) | ((v & 2) << 2) | ((v & 4) << 4)


def _neighbour_keys(inp: KernelInputs, bkeys, wb, bvalid):
    """Offsets ``f`` (3 x (B, 512) f32) and, per axis ``i`` and bit ``b``, the neighbour key
    ``k0 + b`` packed in one int32: window brick ``q 3^i`` (bits 16+), out-of-window flag
    (bit 13) and local Morton bits (bits 0-8), so a corner sums three of them. Also the
    number of in-range neighbour keys of valid bricks outside their window."""
    # eq. 5.13 in key units, relative to K_s: per brick corner plus per local offset
    # (elementwise, not a matmul, so the rounding does not depend on the chunk size)
    A, c = inp.A, inp.c
    d0 = (bkeys * BRICK_EDGE - inp.K_d).astype(jnp.float32)  # (B, 3)
    dl = jnp.asarray(LOCAL_OFFSETS, jnp.float32)  # (512, 3)
    f, packed, misses = [], [], jnp.int32(0)
    for i in range(3):
        u0 = d0[:, 0] * A[i, 0] + d0[:, 1] * A[i, 1] + d0[:, 2] * A[i, 2] + c[i]
        du = dl[:, 0] * A[i, 0] + dl[:, 1] * A[i, 1] + dl[:, 2] * A[i, 2]
        u = u0[:, None] + du[None, :]
        base = jnp.floor(u)
        fi = u - base
        # Snap offsets within float32 noise of a lattice point (exact whole-voxel moves).
        up = fi > 1.0 - _SNAP
        base = jnp.where(up, base + 1.0, base)
        f.append(jnp.where(up | (fi < _SNAP), jnp.float32(0), fi))
        key0 = base.astype(jnp.int32) + inp.K_s[i]
        for k in (key0, key0 + 1):
            q = jnp.right_shift(k, 3) - wb[:, i, None]
            in_range = (k >= 0) & (k < KEY_MAX)
            outside = (q < 0) | (q > 2)
            bad = ~in_range | outside
            misses += count_true(outside & in_range & bvalid[:, None])
            packed.append((jnp.clip(q, 0, 2) * 3 ** i << 16) | (bad.astype(jnp.int32) << 13)
                          | (_spread3bits(k & 7) << i))
    return f, packed, misses


def _resample_chunk(inp: KernelInputs, bkeys, wb, wrows, bvalid):
    """Resample one chunk of destination bricks ``bkeys (B, 3)`` with source windows from
    ``wb (B, 3)`` (brick keys) and window table offsets ``wrows (B * 27,)`` (row * 512):
    per voxel ``(log_odds (B, 512) clamped, known (B, 512))`` in local Morton order, and the
    number of in-range neighbour keys of valid bricks outside their window (0 unless the
    host's window planning is wrong; checked by ``run_kernel``)."""
    nb = bkeys.shape[0]
    table = inp.table
    nan_off = table.shape[0] - BRICK_VOXELS  # the table's last row is NaN (unknown)

    def nothing():
        return ([jnp.zeros((nb, BRICK_VOXELS), jnp.float32)] * 3,
                [jnp.full((nb, BRICK_VOXELS), 1 << 13, jnp.int32)] * 6, jnp.int32(0))

    # A conditional's results are materialised: without it XLA's CPU fusion would recompute
    # all the index arithmetic inside each of the 8 gathers and at every use in the blend.
    f, packed, misses = jax.lax.cond(
        bvalid[0], lambda: _neighbour_keys(inp, bkeys, wb, bvalid), nothing)
    brick0 = (jnp.arange(nb, dtype=jnp.int32) * 27)[:, None]
    vals = []
    for corner in range(8):
        s = packed[corner & 1] + packed[2 + ((corner >> 1) & 1)] + packed[4 + (corner >> 2)]
        row = wrows.at[brick0 + jnp.right_shift(s, 16)].get(mode="promise_in_bounds")
        idx = jnp.where((s & (3 << 13)) != 0, nan_off, row + (s & (BRICK_VOXELS - 1)))
        vals.append(table.at[idx].get(mode="promise_in_bounds"))  # in bounds by construction
    known8 = [~jnp.isnan(v) for v in vals]
    _, lo, center_known, exact = blend(vals, known8, tuple(f), inp.mode)
    lo = jnp.where(jnp.isnan(exact), lo, exact)
    params = inp.m.params
    lo = jnp.clip(lo, params.clamp_min_log_odds, params.clamp_max_log_odds)
    known = center_known & bvalid[:, None]
    return jnp.where(known, lo, jnp.float32(0)), known, misses


def _brick_prune(lo, known):
    """Prune inside each brick (levels 16 -> 13). ``(B, 512)`` -> per voxel
    ``(emit (B, 512) bool, depth (B, 512) int32)``: a voxel emits the leaf it starts.

    A voxel's local Morton index is ``64 a + 8 b + c``: groups of 8 (same ``a, b``) are
    uniform when all known and equal, groups of 64 when their 8 groups are uniform with
    equal values, the brick likewise; each uniform level above a voxel lowers its depth."""
    nb = lo.shape[0]
    l4, k4 = lo.reshape(nb, 8, 8, 8), known.reshape(nb, 8, 8, 8)
    u8 = jnp.all(k4, axis=-1) & jnp.all(l4 == l4[..., :1], axis=-1)  # (B, 8, 8)
    v8 = l4[..., 0]
    u64 = jnp.all(u8, axis=-1) & jnp.all(v8 == v8[..., :1], axis=-1)  # (B, 8)
    u512 = jnp.all(u64, axis=-1) & jnp.all(v8[..., 0] == v8[:, :1, 0], axis=-1)  # (B,)
    u8, u64, u512 = u8[..., None], u64[..., None, None], u512[:, None, None, None]
    depth = _D - u8.astype(jnp.int32) - u64.astype(jnp.int32) - u512.astype(jnp.int32)
    i = jnp.arange(8, dtype=jnp.int32)
    emit = (k4 & ((i == 0) | ~u8) & ((i[:, None] == 0) | ~u64)
            & ((i[:, None, None] == 0) | ~u512))
    depth = jnp.broadcast_to(depth, l4.shape)
    return emit.reshape(nb, BRICK_VOXELS), depth.reshape(nb, BRICK_VOXELS)


def _padding_rows(n: int, hi, depth):
    """``n`` padding rows of the kernel's output: ``(code (n, 2), depth (n,), log_odds (n,))``.
    The fill values are traced arguments, so XLA does not constant-fold (and embed) large
    buffers at compile time."""
    return OutputLeaves(jnp.zeros((n, 2), jnp.int32).at[:, 0].set(hi),
                        jnp.full((n,), depth, jnp.int32), jnp.zeros((n,), jnp.float32))


@functools.partial(jax.jit, static_argnames=("capacity",))
def _empty_output(hi, depth, *, capacity: int):
    """Empty kernel output buffers of ``capacity`` rows (``hi = SENTINEL_HI``, ``depth = 16``)."""
    return _padding_rows(capacity, hi, depth)


@functools.partial(jax.jit, static_argnames=("capacity",))
def _grow_output(bufs, hi, depth, *, capacity: int):
    """The kernel's output buffers extended with padding rows to ``capacity``."""
    pad = _padding_rows(capacity - bufs.code.shape[0], hi, depth)
    return OutputLeaves(*(jnp.concatenate([b, p]) for b, p in zip(bufs, pad)))


def _chunk_leaves(inp: KernelInputs, i, chunk: int):
    """Chunk ``i`` of the destination bricks: ``(log_odds, emit, depth)`` per voxel
    ``(chunk, 512)`` (``_brick_prune``) and its window misses."""
    def compute(i):
        bk = jax.lax.dynamic_slice_in_dim(inp.bkeys, i * chunk, chunk)
        w = jax.lax.dynamic_slice_in_dim(inp.wb, i * chunk, chunk)
        wr = jax.lax.dynamic_slice_in_dim(inp.wrows, i * chunk * 27, chunk * 27)
        bvalid = i * chunk + jnp.arange(chunk) < inp.n_bricks
        lo, known, misses = _resample_chunk(inp, bk, w, wr, bvalid)
        emit, depth = _brick_prune(lo, known)
        return lo, emit, depth, misses

    def skip(i):
        return (jnp.zeros((chunk, BRICK_VOXELS), jnp.float32),
                jnp.zeros((chunk, BRICK_VOXELS), bool),
                jnp.full((chunk, BRICK_VOXELS), _D, jnp.int32), jnp.int32(0))

    # The loop visits valid chunks only; the cond (never false there) stays because a
    # conditional's results are materialised: inlined, XLA fuses the blend into the
    # append's fusions and recomputes it.
    return jax.lax.cond(i * chunk < inp.n_bricks, compute, skip, i)


@stored_jit(static_argnames=("chunk",), donate_argnums=(1,))
def transform_kernel(inp: KernelInputs, bufs, offset, start, *, chunk):
    """Loop over chunks of destination bricks from chunk ``start``; append each chunk's
    brick-pruned leaves to ``bufs`` (``OutputLeaves``, donated) from row ``offset``.

    Stops at the first chunk whose leaves do not fit (nothing of it is committed; its
    partial writes lie past ``offset`` and are overwritten when the caller resumes with
    larger buffers). Returns ``(bufs, offset, next chunk, window misses)``: all chunks are
    done when ``next chunk * chunk >= n_bricks``; ``misses > 0`` is a planning bug (see
    ``_resample_chunk``).
    """
    n_chunks = inp.bkeys.shape[0] // chunk
    cap = bufs.code.shape[0]

    def step(state: _LoopState) -> _LoopState:
        (out_code, out_depth, out_lo), offset, i = state.bufs, state.offset, state.chunk
        lo, emit, depth, miss = _chunk_leaves(inp, i, chunk)
        bk = jax.lax.dynamic_slice_in_dim(inp.bkeys, i * chunk, chunk)
        bwords = morton.keys_to_words(bk * BRICK_EDGE)  # (B, 2); local index fills low 9 bits
        local = jnp.arange(BRICK_VOXELS, dtype=jnp.int32)[None, :]
        vcode = jnp.stack([jnp.broadcast_to(bwords[:, None, 0], (chunk, BRICK_VOXELS)),
                           bwords[:, None, 1] | local], -1)
        emit = emit.reshape(-1)
        n_emit = count_true(emit)
        # Append the emitted leaves in order: one scatter per array (past capacity: dropped).
        pos = jnp.where(emit, offset + cumsum(emit.astype(jnp.int32)) - 1, cap)
        out_code = out_code.at[pos].set(vcode.reshape(-1, 2), mode="drop")
        out_depth = out_depth.at[pos].set(depth.reshape(-1), mode="drop")
        out_lo = out_lo.at[pos].set(lo.reshape(-1), mode="drop")
        fits = offset + n_emit <= cap
        return _LoopState(OutputLeaves(out_code, out_depth, out_lo),
                          jnp.where(fits, offset + n_emit, offset), jnp.where(fits, i + 1, i),
                          state.misses + jnp.where(fits, miss, 0), ~fits)

    # A loop of dynamic length over the chunks holding valid bricks: padding chunks cost
    # nothing.
    n_valid = jnp.minimum((inp.n_bricks + chunk - 1) // chunk, n_chunks)
    end = jax.lax.while_loop(
        lambda state: (state.chunk < n_valid) & ~state.full, step,
        _LoopState(bufs, jnp.int32(offset), jnp.int32(start), jnp.int32(0), jnp.bool_(False)))
    return end.bufs, end.offset, end.chunk, end.misses


def run_kernel(plan: Plan) -> tuple[OccupancyMap, int]:
    """Run the kernel over all destination bricks: ``(map of brick-pruned leaves, count)``.

    When the output buffers fill up, they grow (to the leaves per chunk so far, extrapolated)
    and the kernel resumes at the chunk that did not fit: no chunk is computed twice except
    that one. Raises ``RuntimeError`` if a neighbour fell outside its planned window (a bug).
    """
    n_chunks = -(-plan.n_dest_bricks // plan.chunk)
    fills = (np.int32(morton.SENTINEL_HI), np.int32(_D))
    bufs = _empty_output(*fills, capacity=plan.out_capacity)
    offset, start, misses = 0, 0, 0
    while True:
        bufs, offset, start, miss = transform_kernel(plan.inputs, bufs, offset, start,
                                                     chunk=plan.chunk)
        offset, start, misses = int(offset), int(start), misses + int(miss)
        if start >= n_chunks:
            break
        estimate = offset / max(start, 1) * n_chunks * 1.05 + plan.chunk * BRICK_VOXELS
        grown = quarter_octave_capacity(max(estimate, 1.25 * bufs.code.shape[0]), minimum=64)
        check_allocation((grown + bufs.code.shape[0]) * 16,
                         f"transform_map: output buffers of {grown} leaves at "
                         f"{plan.inputs.m.resolution:g} m")
        bufs = _grow_output(bufs, *fills, capacity=grown)
    if misses:
        raise RuntimeError(f"transform_map: {misses} interpolation neighbours fell outside "
                           "their planned source window (a bug; please report the transform)")
    m = plan.inputs.m
    return OccupancyMap(*bufs, to_device(offset, np.int32), m.params, m.resolution, m.tree_depth), offset
