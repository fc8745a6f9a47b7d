"""Host plan of ``transform_map``: which destination bricks the transformed source can reach,
the brick-indexed view of the source, and each destination brick's source window.

A *brick* is a depth-13 node: 8^3 finest voxels, key ``finest key >> 3`` per axis; voxels
inside a brick are in local Morton order (index ``0..511``). Coordinates here are in *key
units*: voxel centres at integer ``u = x / res + 32768 - 0.5``. The plan ends in ``Plan``, the
device inputs of the jitted kernel (``_kernel.py``).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import morton
from .._ops import bucket_capacity, column_extent, quarter_octave_capacity, to_device
from ..budget import check_allocation
from ..map import OccupancyMap
from ..se3 import check_rigid_transform
from ._cells import BRICK_DEPTH, KeyTransform, Refinement, key_transform, refine
from ._interp import CORNERS, KEY_MAX, mode_index

__all__ = [
    "BRICK_DEPTH",
    "BRICK_EDGE",
    "BRICK_VOXELS",
    "LOCAL_OFFSETS",
    "KernelInputs",
    "Plan",
    "make_plan",
    "transformed_bounds",
]

BRICK_EDGE = 8  # voxels per brick edge
BRICK_VOXELS = 512  # voxels per brick
_D = morton.TREE_DEPTH
_WINDOW_MARGIN = 0.05  # voxels; covers float32 rounding of the kernel's inverse map


def _compact9(v):
    return (v & 1) | ((v >> 2) & 2) | ((v >> 4) & 4)


# (512, 3) int32 voxel offsets inside a brick, in local Morton order
LOCAL_OFFSETS = np.stack([_compact9(np.arange(BRICK_VOXELS) >> a) for a in range(3)],
                         axis=-1).astype(np.int32)


class SourceView(NamedTuple):
    """The brick-indexed view of the source map (``_source_view``)."""

    table: np.ndarray  # (rows * 512,) float32 log-odds, one brick per row, NaN = unknown
    bricks: np.ndarray  # (n, 3) int64 key of every brick holding leaves finer than a brick
    brick_rows: np.ndarray  # (n,) int32 table row of each such brick (0..n-1)
    coarse_start: np.ndarray  # (c,) uint64 first finest code of each leaf of depth <= 13
    coarse_end: np.ndarray  # (c,) uint64 one past its last finest code
    coarse_rows: np.ndarray  # (c,) int32 its table row (one constant row per value)
    nan_row: int  # the first all-NaN row of ``table``
    n_dense: int  # rows 0..n_dense-1 hold bricks with leaves finer than a brick


class KernelInputs(NamedTuple):
    """Device inputs of the transform kernel; keys relative to the anchors ``K_d``, ``K_s``
    keep float32 precision (``u_rel = A (k - K_d) + c``, a source key offset from ``K_s``)."""

    m: OccupancyMap  # the source map (clamp bounds)
    table: jax.Array  # (rows * 512,) float32 ``SourceView.table``; its last row is NaN
    A: jax.Array  # (3, 3) float32 R^T: destination -> source key offsets
    c: jax.Array  # (3,) float32 source key of K_d minus K_s (|c| <= 0.5) [voxels]
    K_d: jax.Array  # (3,) int32 destination anchor key
    K_s: jax.Array  # (3,) int32 source anchor key
    bkeys: jax.Array  # (b_cap, 3) int32 destination brick keys, Morton order, then padding
    wb: jax.Array  # (b_cap, 3) int32 first source brick of each window (3x3x3 bricks)
    wrows: jax.Array  # (b_cap * 27,) int32 table offset (row * 512) of window brick x + 3 y + 9 z
    n_bricks: jax.Array  # () int32 valid rows of bkeys
    mode: jax.Array  # () int32 blend rule (``_interp.mode_index``)


class Plan(NamedTuple):
    """Host planning result of ``transform_map``."""

    inputs: KernelInputs  # device arrays of the kernel
    chunk: int  # destination bricks per loop step (static)
    out_capacity: int  # rows of the kernel's first output buffers
    n_dest_bricks: int  # destination bricks with a non-empty source window
    n_dense_bricks: int  # source bricks stored as dense table rows
    cells: Refinement  # uniform destination cells (not in the kernel) and the refinement


@jax.jit
def _key_bounds(m: OccupancyMap):
    """Per-axis min key and max key + 1 ``(3,) int32`` over the leaves' cubes (on device:
    no host copy of the leaves)."""
    valid = m.valid_mask()
    keys = morton.words_to_keys(m.code)
    end = keys + jnp.left_shift(1, _D - m.depth)[:, None]
    return column_extent(keys, valid)[0], column_extent(end, valid)[1]  # keys below 2^16


def transformed_bounds(m: OccupancyMap, T_dst_src) -> tuple[np.ndarray, np.ndarray]:
    """Alg. 4: axis-aligned bounds ``(p_min, p_max)`` [m, float64 (3,)] in frame ``dst`` of
    the source map's leaf extent (OctoMap ``getMetricMin/Max``) after ``T_dst_src``.

    The 8 corners of the source bounding box are transformed and their extremes taken.
    Raises ``ValueError`` for an empty map or an invalid transform.
    """
    T = check_rigid_transform(T_dst_src)
    if m.num_leaves == 0:
        raise ValueError("transformed_bounds: the map has no leaves")
    kmin, kmax = (np.asarray(k, np.float64) for k in _key_bounds(m))
    bmin = (kmin - morton.KEY_OFFSET) * m.resolution
    bmax = (kmax - morton.KEY_OFFSET) * m.resolution
    corners = np.array([[bmax[0] if c & 1 else bmin[0], bmax[1] if c & 2 else bmin[1],
                         bmax[2] if c & 4 else bmin[2]] for c in range(8)])
    moved = corners @ T[:3, :3].T + T[:3, 3]
    return moved.min(axis=0), moved.max(axis=0)


def _aligned_full(shape, fill, dtype, align: int = 64) -> np.ndarray:
    """``np.full`` whose data start on an ``align``-byte boundary (zero-copy to XLA:CPU)."""
    dtype = np.dtype(dtype)
    n = int(np.prod(shape))
    raw = np.empty(n * dtype.itemsize + align, np.uint8)
    start = -raw.ctypes.data % align
    out = raw[start:start + n * dtype.itemsize].view(dtype).reshape(shape)
    out.fill(fill)
    return out


def _shared_on_device_of(x: np.ndarray, like: jax.Array) -> jax.Array:
    """Host array -> an array on the device of ``like``. On a CPU device an aligned array is
    shared, not copied; elsewhere a plain transfer."""
    devices = like.devices() if isinstance(like, jax.Array) else set()
    device = next(iter(devices)) if len(devices) == 1 else None
    if device is not None and device.platform == "cpu" and x.ctypes.data % 64 == 0:
        shared = jnp.from_dlpack(x)
        return shared if shared.devices() == devices else jax.device_put(shared, device)
    return jax.device_put(x, device)


def _source_view(m: OccupancyMap) -> SourceView:
    """The brick-indexed view of the source (see ``SourceView``).

    ``table`` holds, in local Morton order, one dense row per brick that contains leaves finer
    than a brick, then one constant row per distinct value of the leaves that cover whole
    bricks (depth <= 13), then NaN rows. Coarse leaves are not expanded into their bricks: a
    window brick finds its leaf by binary search (``_dest_windows``). Memory: 2 KiB per dense
    brick plus 20 bytes per coarse leaf. Works on the int32 code words (hi, lo: 24 bits each;
    a brick is ``hi, lo >> 9``).
    """
    n = m.num_leaves
    words = np.asarray(m.code)[:n]
    depth = np.asarray(m.depth)[:n]
    lo = np.asarray(m.log_odds)[:n]
    fine = depth > BRICK_DEPTH
    hi_w, lo_w, d, v = words[fine, 0], words[fine, 1], depth[fine], lo[fine]
    # leaves are Morton-sorted, so a brick's leaves are contiguous
    first = np.ones(hi_w.shape, bool)
    np.not_equal(lo_w[1:] >> 9, lo_w[:-1] >> 9, out=first[1:])
    first[1:] |= hi_w[1:] != hi_w[:-1]
    n_db = int(np.count_nonzero(first))
    uniq, inv = np.unique(lo[~fine], return_inverse=True)
    rows = quarter_octave_capacity(n_db + uniq.size + 1, minimum=64)
    check_allocation(rows * BRICK_VOXELS * 4 + n * 24,
                     f"transform_map: the source table of {n_db} dense bricks "
                     f"(a map of {n} leaves at {m.resolution:g} m)")
    table = _aligned_full((rows, BRICK_VOXELS), np.nan, np.float32)
    itype = np.int32 if rows * BRICK_VOXELS < 2 ** 31 else np.int64
    flat = np.cumsum(first, dtype=itype)  # slot + 1, then the voxel index in the table
    flat -= 1
    flat *= BRICK_VOXELS
    flat += lo_w & (BRICK_VOXELS - 1)
    for depth_l in (14, 15, 16):
        sel = d == depth_l
        if sel.any():
            span = 8 ** (_D - depth_l)
            table.reshape(-1, span)[flat[sel] // span] = v[sel, None]
    table[n_db:n_db + uniq.size] = uniq[:, None]
    keys = morton.codes_to_keys(morton.join_codes(np.stack([hi_w[first], lo_w[first]], -1))
                                ).astype(np.int64) >> 3
    cstart = morton.join_codes(words[~fine])
    cend = cstart + (np.uint64(1) << (np.uint64(3) * (_D - depth[~fine]).astype(np.uint64)))
    crow = (n_db + inv.reshape(-1)).astype(np.int32)
    return SourceView(table.reshape(-1), keys, np.arange(n_db, dtype=np.int32), cstart, cend,
                      crow, n_db + uniq.size, n_db)


def _brick_grid(view: SourceView, q_lo, q_hi):
    """A dense grid of table rows over the bricks ``q_lo..q_hi`` (inclusive ``(3,)`` keys) when
    it is small (4 B per brick, at most ``max(2^22, 8 x dense bricks)``): dense bricks and the
    coarse leaves of at most 8^3 bricks painted in. Returns ``(grid (z, y, x) int32, lo,
    painted (c,) bool)`` or ``None``; ``painted`` marks the coarse leaves wholly in the grid."""
    ext = q_hi - q_lo + 1
    if np.any(ext <= 0) or np.prod(ext) > max(1 << 22, 8 * view.bricks.shape[0]):
        return None
    grid = np.full(tuple(ext[::-1]), view.nan_row, np.int32)
    r = view.bricks - q_lo
    ins = np.all((r >= 0) & (r < ext), axis=1)
    grid[r[ins, 2], r[ins, 1], r[ins, 0]] = view.brick_rows[ins]
    painted = np.zeros(view.coarse_start.size, bool)
    if view.coarse_start.size:
        width = np.cbrt((view.coarse_end - view.coarse_start).astype(np.float64) / 512)
        width = np.rint(width).astype(np.int64)  # bricks per edge
        base = morton.codes_to_keys(view.coarse_start).astype(np.int64) >> 3
        inside = np.all((base >= q_lo) & (base + width[:, None] - 1 <= q_hi), axis=1)
        for w in np.unique(width[inside & (width <= 8)]):
            sel = np.flatnonzero(inside & (width == w))
            painted[sel] = True
            g = np.stack(np.meshgrid(*[np.arange(w)] * 3, indexing="ij"), -1).reshape(-1, 3)
            k = (base[sel, None, :] + g[None] - q_lo).reshape(-1, 3)
            grid[k[:, 2], k[:, 1], k[:, 0]] = np.repeat(view.coarse_rows[sel], g.shape[0])
    return grid, q_lo, painted


def _window_rows(q, view: SourceView, grid) -> np.ndarray:
    """Table rows of source bricks with keys ``q (..., 3)`` int64 (any, in range or not):
    a dense row, the constant row of the coarse leaf covering the brick, or ``view.nan_row``.
    ``grid``: ``_brick_grid``'s result or ``None``."""
    shape = q.shape[:-1]
    q = q.reshape(-1, 3)
    rows = np.full(q.shape[0], view.nan_row, np.int32)
    ok = np.all((q >= 0) & (q < KEY_MAX // BRICK_EDGE), axis=1)
    rest = np.ones(view.coarse_start.size, bool)
    if grid is not None:
        g, lo, painted = grid
        r = q - lo
        inside = np.all((r >= 0) & (r < g.shape[::-1]), axis=1)
        r = np.where(inside[:, None], r, 0)
        rows = np.where(inside, g[r[:, 2], r[:, 1], r[:, 0]], rows)
        rest = ~painted
    elif view.bricks.shape[0]:  # sparse dense bricks: binary search by Morton code
        bcode = morton.keys_to_codes(view.bricks.astype(np.uint64))
        order = np.argsort(bcode)
        qc = morton.keys_to_codes(np.where(ok[:, None], q, 0).astype(np.uint64))
        i = np.minimum(np.searchsorted(bcode[order], qc), bcode.size - 1)
        hit = ok & (bcode[order][i] == qc)
        rows = np.where(hit, view.brick_rows[order][i], rows)
    if rest.any():  # the other coarse leaves: the one whose range holds the brick
        cs, ce, cr = view.coarse_start[rest], view.coarse_end[rest], view.coarse_rows[rest]
        need = ok & (rows == view.nan_row)
        code = morton.keys_to_codes((q[need] << 3).astype(np.uint64))
        j = np.searchsorted(cs, code, side="right") - 1
        hit = (j >= 0) & (ce[np.maximum(j, 0)] > code)
        rows[need] = np.where(hit, cr[np.maximum(j, 0)], view.nan_row)
    return rows.reshape(shape)


def _dest_windows(dest, T_key: KeyTransform, view: SourceView):
    """Each destination brick's source window, 3x3x3 source bricks from ``wb``.

    ``dest (n, 3)``: destination brick keys. Returns ``(wb (n, 3) int64, rows (n, 27) int32)``,
    window brick ``x + 3 y + 9 z`` -> table row (``view.nan_row`` where no leaf covers it).
    Every neighbour key ``k0 + {0, 1}`` of every voxel lies in the window: the inverse image
    of a brick's centres spans <= 7 sqrt(3) < 12.2 voxels per axis, so with the margin the
    neighbours span <= 15 keys from at most 7 into the first brick.
    """
    R, t_key = T_key
    n = dest.shape[0]
    if n == 0:
        return np.zeros((n, 3), np.int64), np.full((n, 27), view.nan_row, np.int32)
    umin = np.full((n, 3), np.inf)
    for corner in CORNERS:  # the extremes of an affine map over a cube are at its corners
        k = (dest * BRICK_EDGE + 7 * corner).astype(np.float64)
        umin = np.minimum(umin, (k - t_key) @ R)  # R^T (k - t_key), row-wise
    wb = np.floor_divide(np.floor(umin - _WINDOW_MARGIN).astype(np.int64), BRICK_EDGE)
    g = CORNERS_27  # window brick x + 3 y + 9 z
    rows = np.empty((n, 27), np.int32)
    grid = _brick_grid(view, wb.min(axis=0), wb.max(axis=0) + 2)
    step = 1 << 16  # bricks per block (bounds the scratch memory)
    for s in range(0, n, step):
        rows[s:s + step] = _window_rows(wb[s:s + step, None, :] + g[None], view, grid)
    return wb, rows


# (27, 3) offsets of the window bricks, index x + 3 y + 9 z
CORNERS_27 = np.array([[i % 3, (i // 3) % 3, i // 9] for i in range(27)], np.int64)


def make_plan(m: OccupancyMap, T: np.ndarray, method: str, space: str, chunk: int,
              out_capacity: int | None, bounds=None) -> Plan:
    """Destination cells and bricks (``_cells.refine``), the source's brick table and the
    key-frame constants for ``transform_map(m, T, method, space=space)`` with ``chunk`` bricks
    per loop step; ``out_capacity`` ``None``: a guess from the leaf and brick counts;
    ``bounds``: ``transformed_bounds(m, T)`` if known. Raises ``MemoryBudgetError`` before
    allocating over the memory budget."""
    T_key = key_transform(T, m.resolution)
    R, t_key = T_key
    cells = refine(m, T_key, *(transformed_bounds(m, T) if bounds is None else bounds))
    dest = cells.bricks
    n_b = dest.shape[0]
    b_cap = max(bucket_capacity(n_b, minimum=1024), chunk)
    b_cap = int(math.ceil(b_cap / chunk) * chunk)
    if out_capacity is None:
        out_capacity = quarter_octave_capacity(2 * m.num_leaves + 8 * n_b, minimum=1 << 15)
    # windows (host), brick inputs, first output buffers and one chunk's work arrays
    check_allocation(n_b * 27 * 24 + b_cap * 33 * 4 + 2 * int(out_capacity) * 16
                     + chunk * BRICK_VOXELS * 8 * 16,
                     f"transform_map: resampling {n_b} destination bricks (a map of "
                     f"{m.num_leaves} leaves at {m.resolution:g} m)")
    view = _source_view(m)
    wb, rows = _dest_windows(dest, T_key, view)
    live = np.any(rows != view.nan_row, axis=1)  # an all-unknown window gives nothing
    dest, wb, rows = dest[live], wb[live], rows[live]
    # Relative coordinates keep float32 precision: u_rel = R^T (k - K_d) + c, with
    # K_s = round(R^T (K_d - t_key)) so that |c| <= 0.5.
    n_b = dest.shape[0]
    K_d = (np.round(dest.mean(axis=0) * BRICK_EDGE).astype(np.int64) if n_b
           else np.zeros(3, np.int64))
    u_s = R.T @ (K_d.astype(np.float64) - t_key)
    K_s = np.round(u_s).astype(np.int64)
    c = u_s - K_s
    b_cap = max(bucket_capacity(n_b, minimum=1024), chunk)
    b_cap = int(math.ceil(b_cap / chunk) * chunk)
    bkeys = np.zeros((b_cap, 3), np.int32)
    bkeys[:n_b] = dest
    wbp = np.zeros((b_cap, 3), np.int32)
    wbp[:n_b] = wb
    wrows = np.full((b_cap, 27), view.nan_row * BRICK_VOXELS, np.int32)
    wrows[:n_b] = rows * BRICK_VOXELS
    inputs = KernelInputs(
        m, _shared_on_device_of(view.table, m.log_odds), to_device(R.T, np.float32), to_device(c, np.float32),
        to_device(K_d, np.int32), to_device(K_s, np.int32), to_device(bkeys), to_device(wbp),
        to_device(wrows.reshape(-1)), to_device(n_b, np.int32), to_device(mode_index(method, space), np.int32))
    return Plan(inputs, chunk, int(out_capacity), n_b, view.n_dense, cells)
