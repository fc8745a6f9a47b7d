"""A coarse grid over a map's leaves that narrows each key lookup to its cell's rows.

``tree.lookup_keys`` finds a key's leaf by a binary search over all of the map's Morton-sorted
leaves: ``ceil(log2(capacity + 1))`` dependent gathers (20 at 0.5M rows). The leaves inside one
cell of ``8^shift`` voxels (an aligned node of depth ``16 - shift``) are contiguous in Morton
order, so ``leaf_index`` records per cell of the leaves' bounding box the rows that can hold a
key of that cell: the row before the cell's first code (a coarser leaf that starts before the
cell and may cover it) up to the first row at or past its end. ``lookup_keys`` then searches
only those rows: ``3 shift + 1`` halvings and two gathers, the same rows as the whole search.
A key outside the box lies in no leaf.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from . import morton, tree
from ._ops import bucket_capacity, to_device
from .budget import current_budget
from .map import OccupancyMap

__all__ = ["MAX_INDEX_CELLS", "LeafIndex", "index_shift", "key_box", "leaf_index", "lookup_keys"]

#: the most cells a ``LeafIndex`` holds (8 bytes each); a box that needs more at every cell size is not indexed
MAX_INDEX_CELLS = 1 << 20
_MAX_SHIFT = 4  # cells of up to 16^3 voxels (13 halvings)
_KEY_LIMIT = 2 * morton.KEY_OFFSET
_HOST_BYTES_PER_CELL = 64  # the cells' keys and codes while building (int64 / uint64), then 8 bytes of rows


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class LeafIndex:
    """Per cell of ``8^shift`` voxels of a map's leaf box, the rows a lookup searches (a pytree;
    arrays may carry leading batch axes)."""

    start: jax.Array  # (C,) int32: the last row whose code lies before the cell (0 if none)
    end: jax.Array  # (C,) int32: the first row whose code lies at or past the cell's end
    lo: jax.Array  # (3,) int32: the box's first cell (finest key >> shift)
    dims: jax.Array  # (3,) int32: cells per axis, x fastest in ``start`` / ``end``
    shift: int = dataclasses.field(metadata=dict(static=True), default=2)  # cells of 2^shift voxels per edge


def key_box(m: OccupancyMap) -> tuple[np.ndarray, np.ndarray]:
    """Host: the first and last finest keys ``(3,)`` int64 (inclusive) that ``m``'s leaves cover."""
    lv = m.leaves()
    first = lv.keys.astype(np.int64)
    side = np.left_shift(np.int64(1), morton.TREE_DEPTH - lv.depths.astype(np.int64))
    return first.min(axis=0), (first + side[:, None] - 1).max(axis=0)


def index_shift(box) -> int | None:
    """The smallest cell shift from 2 whose cells of the key ``box`` ``(first, last)`` fit
    ``MAX_INDEX_CELLS``, or ``None``."""
    first, last = (np.asarray(b, np.int64) for b in box)
    for s in range(2, _MAX_SHIFT + 1):
        if int(np.prod((last >> s) - (first >> s) + 1)) <= MAX_INDEX_CELLS:
            return s
    return None


def leaf_index(m: OccupancyMap, capacity: int | None = None, shift: int | None = None,
               box=None) -> LeafIndex | None:
    """Host: the ``LeafIndex`` of ``m``: the key ``box`` ``(first (3,), last (3,))`` (inclusive
    finest keys; default ``key_box(m)``, which decodes the leaves) cut into cells of
    ``2^shift`` voxels per edge (default ``index_shift(box)``). ``capacity``: rows of
    ``start`` / ``end`` (at least the box's cells; default ``bucket_capacity`` of them).
    ``None`` for a map without leaves, a box that does not fit ``MAX_INDEX_CELLS``, or one whose
    building would take over a quarter of the memory budget (``budget.current_budget``).
    Raises ``ValueError`` when ``capacity`` is smaller than the box's cells or a leaf lies
    outside ``box``."""
    n = m.num_leaves
    if n == 0:
        return None
    first, last = (np.asarray(b, np.int64) for b in (key_box(m) if box is None else box))
    s = index_shift((first, last)) if shift is None else int(shift)
    if s is None:
        return None
    lo = first >> s
    dims = (last >> s) - lo + 1
    cells = int(np.prod(dims))
    if cells > MAX_INDEX_CELLS or _HOST_BYTES_PER_CELL * cells > current_budget() // 4:
        return None
    capacity = bucket_capacity(cells) if capacity is None else int(capacity)
    if capacity < cells:
        raise ValueError(f"leaf_index: capacity {capacity} is smaller than the box's {cells} cells")
    g = [np.arange(int(d), dtype=np.int64) for d in dims]
    cell = np.stack(np.meshgrid(*g, indexing="ij"), -1).transpose(2, 1, 0, 3).reshape(-1, 3) + lo  # x fastest
    first_code = morton.keys_to_codes((cell << s).astype(np.uint64))
    codes = morton.join_codes(np.asarray(m.code)[:n])
    if codes[0] < first_code[0] or codes[-1] >= first_code[-1] + np.uint64(8 ** s):
        raise ValueError("leaf_index: a leaf lies outside the given box")
    start = np.full(capacity, 0, np.int32)
    end = np.full(capacity, 0, np.int32)
    start[:cells] = np.maximum(np.searchsorted(codes, first_code, side="left") - 1, 0)
    end[:cells] = np.searchsorted(codes, first_code + np.uint64(8 ** s), side="left")
    return LeafIndex(to_device(start), to_device(end), to_device(lo, np.int32), to_device(dims, np.int32), s)


def lookup_keys(m: OccupancyMap, keys, index: LeafIndex | None):
    """``tree.lookup_keys`` of voxel ``keys (..., 3)`` int32 (OctoMap keys; any value) through
    ``index`` (``leaf_index(m)``; ``None``: ``tree.lookup_keys`` itself): ``(row (...,) int32,
    known (...,) bool)``, the same rows; ``known`` is False outside the key range and outside
    the index's box."""
    if index is None:
        return tree.lookup_keys(m, keys)
    words = morton.keys_to_words(jnp.clip(keys, 0, _KEY_LIMIT - 1))
    cell = jnp.right_shift(keys, index.shift) - index.lo
    inside = jnp.all((cell >= 0) & (cell < index.dims) & (keys >= 0) & (keys < _KEY_LIMIT), axis=-1)
    c = jnp.where(inside, cell[..., 0] + index.dims[0] * (cell[..., 1] + index.dims[1] * cell[..., 2]), 0)
    code = m.code

    def at_or_before(mid):  # the row at ``mid`` starts at or before the key
        return ~morton.words_less(words, code[jnp.clip(mid, 0, code.shape[0] - 1)])

    i = morton.partition_point(index.start[c], index.end[c], at_or_before, 3 * index.shift + 1) - 1
    row, known = tree.containing_leaf(m, words, i)
    return row, inside & known
