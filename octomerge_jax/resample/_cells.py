"""Host refinement of ``transform_map``'s destination: coarse cells where the source is uniform,
bricks for the kernel only near a change of value.

Destination cells are refined top-down, from a few cells covering the transformed bounds to
bricks (depth 13). A cell's *stencil box* is the box of source keys that the trilinear stencils
(eqs. 3.6-3.13: the 8 neighbours ``k0 + {0, 1}^3`` of each mapped-back voxel centre) of all its
voxels can read. It is classified against the source leaves:

- *empty*: no known source leaf meets the box: no voxel of the cell is made;
- *uniform*: known leaves of one log-odds ``v`` cover the box: every voxel of the cell gets
  ``v`` exactly (the kernel's exact rule), so the cell is one output leaf of value
  ``clip(v)``, resampled at its own scale;
- *mixed*: otherwise. A mixed cell is split into its 8 children; a mixed brick goes to the
  kernel (``_kernel.py``).

The classification is conservative (a box is tested against at most 8 aligned source nodes at
least as large as the box), so a mixed cell may turn out uniform in the kernel; never the other
way. Cost: cells in proportion to the surfaces where the source's value changes, not to the
volume. See ``docs/design.md``, "Coarse cells where the source is uniform".
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .. import morton
from ..budget import check_allocation
from ..map import OccupancyMap
from ._interp import KEY_MAX

__all__ = ["BRICK_DEPTH", "CELL_BYTES", "KeyTransform", "Refinement", "SourceLeaves", "key_transform",
           "refine", "source_leaves"]

_D = morton.TREE_DEPTH
BRICK_DEPTH = 13  # a brick is a depth-13 node: 8^3 finest voxels
_MARGIN = 0.05  # voxels; covers float32 rounding of the kernel's inverse map
_LATTICE_TOL = 1e-7  # voxels: an axis whose inverse map lands this close to keys is snapped
_CHUNK = 1 << 18  # cells classified per step (bounds the scratch memory)
CELL_BYTES = 48  # host bytes per listed cell (keys, flags), for the budget
_SCRATCH_BYTES = 1200  # host bytes per cell while it is classified (8 node queries)


class KeyTransform(NamedTuple):
    """The forward map ``u' = R u + t_key`` of ``T_dst_src`` in key units."""

    R: np.ndarray  # (3, 3) float64 rotation
    t_key: np.ndarray  # (3,) float64 translation [voxels]


def key_transform(T, resolution) -> KeyTransform:
    """``T (4, 4)`` in key units, for voxel-centre coordinates ``u = x / res + 32768 - 0.5``."""
    R = T[:3, :3]
    o = morton.KEY_OFFSET - 0.5
    t_key = T[:3, 3] / resolution + o - R @ np.full(3, o)
    return KeyTransform(R, t_key)


class SourceLeaves(NamedTuple):
    """The source's leaves as Morton ranges, for box queries (``source_leaves``)."""

    start: np.ndarray  # (n,) uint64 first finest code of each leaf, sorted
    end: np.ndarray  # (n,) uint64 one past its last finest code
    log_odds: np.ndarray  # (n,) float32
    run: np.ndarray  # (n,) int64 id of the run of adjacent leaves of equal log-odds


class Refinement(NamedTuple):
    """Result of ``refine``: uniform output cells and the bricks left to the kernel."""

    codes: np.ndarray  # (c,) uint64 min-corner codes of uniform cells, Morton order
    depths: np.ndarray  # (c,) int32 their depths (<= 13)
    log_odds: np.ndarray  # (c,) float32 their clamped log-odds
    bricks: np.ndarray  # (b, 3) int64 brick keys (finest key >> 3) of mixed bricks, Morton order
    cells_visited: int  # cells classified, all levels


def source_leaves(m: OccupancyMap) -> SourceLeaves:
    """The leaves of ``m`` as Morton ranges with run ids: a new run starts where the log-odds
    changes or a gap (unknown space) lies between two leaves."""
    n = m.num_leaves
    start = morton.join_codes(np.asarray(m.code)[:n])
    depth = np.asarray(m.depth)[:n].astype(np.uint64)
    lo = np.asarray(m.log_odds)[:n]
    end = start + (np.uint64(1) << (np.uint64(3) * (np.uint64(_D) - depth)))
    new = np.ones(n, bool)
    new[1:] = (lo[1:] != lo[:-1]) | (start[1:] != end[:-1])
    return SourceLeaves(start, end, lo, np.cumsum(new) - 1)


def _lattice_axes(T_key: KeyTransform) -> np.ndarray:
    """``(3,) bool``: source axes along which every mapped-back voxel centre lands on a key
    (a right-angle rotation and a whole-voxel shift on that axis). There the kernel snaps the
    offset to 0 (``_kernel._SNAP``), so the stencil is the single key ``k0``."""
    R, t_key = T_key
    A = R.T.astype(np.float32)  # the kernel's matrix
    one = np.abs(A) == 1
    tiny = np.abs(A) < 1e-12
    u0 = -(R.T @ t_key)  # source key of destination key 0
    near = np.abs(u0 - np.rint(u0)) < _LATTICE_TOL
    return (one.sum(axis=1) == 1) & np.all(one | tiny, axis=1) & near


def _stencil_boxes(keys, size: int, T_key: KeyTransform, lattice):
    """Source key boxes ``(lo, hi)`` (inclusive, ``(n, 3)`` int64) read by the stencils of the
    voxels of destination cells with min keys ``keys (n, 3)`` and edge ``size`` voxels."""
    R, t_key = T_key
    base = (keys.astype(np.float64) - t_key) @ R  # R^T (k - t_key), row-wise
    span = (size - 1) * R  # row j: the change of u along destination axis j
    umin = base + np.minimum(span, 0).sum(axis=0)
    umax = base + np.maximum(span, 0).sum(axis=0)
    lo = np.where(lattice, np.rint(umin), np.floor(umin - _MARGIN))
    hi = np.where(lattice, np.rint(umax), np.floor(umax + _MARGIN) + 1)
    return lo.astype(np.int64), hi.astype(np.int64)


def _classify(keys, size: int, T_key: KeyTransform, lattice, src: SourceLeaves):
    """Classify destination cells ``keys (n, 3)`` of edge ``size``: ``(state (n,) int8,
    value (n,) float32)``, state 0 empty, 1 uniform (of ``value``), 2 mixed."""
    n = keys.shape[0]
    lo, hi = _stencil_boxes(keys, size, T_key, lattice)
    partial = np.any((lo < 0) | (hi >= KEY_MAX), axis=1)
    outside = np.any((hi < 0) | (lo >= KEY_MAX), axis=1)
    lo, hi = np.clip(lo, 0, KEY_MAX - 1), np.clip(hi, 0, KEY_MAX - 1)
    ext = (hi - lo + 1).max(axis=1)
    shift = np.minimum(np.ceil(np.log2(np.maximum(ext, 1))).astype(np.int64), _D)
    shift[(1 << shift) < ext] += 1  # guard the float log2
    shift = np.minimum(shift, _D)
    n_lo, n_hi = lo >> shift[:, None], hi >> shift[:, None]  # 1 or 2 nodes per axis
    corner = np.array([[c & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)])
    node = (n_lo[:, None, :] + corner[None] * (n_hi - n_lo)[:, None, :]) << shift[:, None, None]
    start = morton.keys_to_codes(node.astype(np.uint64))  # (n, 8)
    stop = start + (np.uint64(1) << (np.uint64(3) * shift.astype(np.uint64)))[:, None]
    i0 = np.searchsorted(src.end, start, side="right")
    i1 = np.searchsorted(src.start, stop, side="left")
    empty = i0 >= i1
    last = np.maximum(i1 - 1, 0)
    first = np.minimum(i0, last)
    uniform = (~empty & (src.run[first] == src.run[last]) & (src.start[first] <= start)
               & (src.end[last] >= stop))
    value = src.log_odds[first]
    all_empty = np.all(empty, axis=1) | outside
    all_uniform = (np.all(uniform, axis=1) & np.all(value == value[:, :1], axis=1)
                   & ~partial & ~all_empty)
    state = np.full(n, 2, np.int8)
    state[all_empty] = 0
    state[all_uniform] = 1
    return state, value[:, 0]


def _start_cells(m: OccupancyMap, T_key: KeyTransform, p_min, p_max):
    """A few destination cells covering the transformed bounds ``p_min, p_max`` [m]:
    ``(keys (n, 3) int64, depth)``."""
    res = m.resolution
    kmin = np.clip(np.floor(p_min / res).astype(np.int64) + morton.KEY_OFFSET - 1, 0, KEY_MAX - 1)
    kmax = np.clip(np.floor(p_max / res).astype(np.int64) + morton.KEY_OFFSET + 1, 0, KEY_MAX - 1)
    ext = int((kmax - kmin + 1).max())
    depth = max(1, _D - int(np.ceil(np.log2(ext))))
    depth = min(depth, BRICK_DEPTH)
    sh = _D - depth
    axes = [np.arange(a >> sh, (b >> sh) + 1) << sh for a, b in zip(kmin, kmax)]
    keys = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    return keys.astype(np.int64), depth


def _describe(m: OccupancyMap) -> str:
    n = m.num_leaves
    dmin = int(np.asarray(m.depth)[:n].min()) if n else _D
    return f"a map of {n} leaves at {m.resolution:g} m (coarsest leaf depth {dmin})"


def refine(m: OccupancyMap, T_key: KeyTransform, p_min, p_max) -> Refinement:
    """Refine the destination of ``transform_map(m, T)`` top-down (module docstring).

    ``p_min, p_max``: the transformed bounds [m] (``transformed_bounds``). Raises
    ``MemoryBudgetError`` (``budget.check_allocation``) before listing more cells than the
    memory budget allows: the output itself would have at least that many leaves.
    """
    src = source_leaves(m)
    lattice = _lattice_axes(T_key)
    params = m.params
    cmin, cmax = np.float32(params.clamp_min_log_odds), np.float32(params.clamp_max_log_odds)
    keys, depth = _start_cells(m, T_key, p_min, p_max)
    out_keys, out_depth, out_val = [], [], []
    visited = 0
    while True:
        size = 1 << (_D - depth)
        state = np.empty(keys.shape[0], np.int8)
        value = np.empty(keys.shape[0], np.float32)
        for s in range(0, keys.shape[0], _CHUNK):
            state[s:s + _CHUNK], value[s:s + _CHUNK] = _classify(
                keys[s:s + _CHUNK], size, T_key, lattice, src)
        visited += keys.shape[0]
        uni = state == 1
        out_keys.append(keys[uni])
        out_depth.append(np.full(int(uni.sum()), depth, np.int32))
        out_val.append(np.clip(value[uni], cmin, cmax))
        mixed = keys[state == 2]
        if depth == BRICK_DEPTH:
            break
        n_next = 8 * mixed.shape[0]
        check_allocation(n_next * CELL_BYTES + min(n_next, _CHUNK) * _SCRATCH_BYTES,
                         f"transform_map: {n_next} destination cells at depth {depth + 1} "
                         f"for {_describe(m)}")
        half = size >> 1
        corner = np.array([[c & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)]) * half
        keys = (mixed[:, None, :] + corner[None]).reshape(-1, 3)
        depth += 1
    cell_keys = np.concatenate(out_keys)
    codes = morton.keys_to_codes(cell_keys.astype(np.uint64))
    order = np.argsort(codes, kind="stable")
    bricks = mixed >> 3
    border = np.argsort(morton.keys_to_codes(mixed.astype(np.uint64)), kind="stable")
    return Refinement(codes[order], np.concatenate(out_depth)[order],
                      np.concatenate(out_val)[order], bricks[border], visited)
