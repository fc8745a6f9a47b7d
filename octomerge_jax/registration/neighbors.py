"""Jittable fixed-radius nearest neighbours on a hashed uniform grid.

Points are binned into cubic cells of edge ``cell_size`` (the search radius); a query looks at
the 27 cells around its own cell, which contain every point within ``cell_size`` of it. Cells
go to buckets of a table of ``M`` (power of two) buckets x ``K = cell_capacity`` slots: by a
linear index when the points' cell bounding box has at most ``M`` cells (collision-free), else
by a spatial hash (Teschner et al. 2003 with a murmur3 finaliser, as in KISS-ICP's voxel map). Everything has static shape,
so building and querying are plain sorts, scatters and gathers under ``jit``/``vmap``:

- build: sort points by (bucket, pseudo-random rank) and scatter the first ``K`` of each bucket
  into the table. Buckets with more than ``K`` points keep a pseudo-random subset (a spatially
  uniform subsample); the dropped points are counted in ``overflow`` (a status, not an error).
  Hash collisions only add candidates, never wrong answers: distances are always exact.
- query: 27 gathers of ``K`` candidates per query point and an exact squared distance; the
  result is exact (the true nearest neighbour within ``cell_size``; among points whose squared
  distances agree to a relative ``2^-15``, the first slot) whenever ``overflow == 0``.
  Candidates farther than ``cell_size`` may be returned; callers filter by distance. By default
  in two phases: the 8 cells nearest to the query first, which hold every point within half a
  cell of it, and the 27 only for the queries that this does not settle (same answers; see
  ``docs/design.md``, "Hashed-grid nearest neighbours, searched in two phases").

No SciPy/KD-tree: the same code runs for one query set or ``vmap``-ed over many transforms.
"""

from __future__ import annotations

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from .._ops import any_of, column_extent, count_true, cumsum, nonzero_rows, to_device
from .._sort import lexsort_rows

__all__ = ["HashGrid", "build_grid", "build_grids", "nearest", "nearest_with_points", "any_within", "grid_table_size",
           "level_table_sizes", "QUERY_BLOCK"]

_FAR = 1.0e7  # coordinate of empty slots [m]: farther than anything real, finite squares
_P1, _P2, _P3 = np.uint32(73856093), np.uint32(19349663), np.uint32(83492791)
_OFFSETS = np.array([(i, j, k) for k in (-1, 0, 1) for j in (-1, 0, 1) for i in (-1, 0, 1)], np.int32)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class HashGrid:
    """Hashed grids over one point set, one per level (cell size), flattened for gathers.

    Level ``l`` has ``M_l`` buckets (a power of two) of ``K = cell_capacity`` slots, stored at
    rows ``base[l] .. base[l] + M_l`` (row ``base[l] + M_l`` is an always-empty sink) of:

    - ``xyz``: ``(3, R, K)`` float32 slot coordinates [m] (structure of arrays: one gather per
      axis); empty slots hold ``1e7``.
    - ``index``: ``(R, K)`` int32 row of each slot's point, ``-1`` if empty.
    - ``base``: ``(L,)`` int32 first row of each level; ``mask``: ``(L,)`` int32 ``M_l - 1``.
    - ``origin``, ``dims``: ``(L, 3)`` int32 cell bounding box of the points; ``dense``:
      ``(L,)`` bool, the box has at most ``M_l`` cells, so cells are indexed linearly
      (collision-free) instead of hashed.
    - ``cell_size``: ``(L,)`` float32 cell edge of each level [m].
    - ``overflow``: ``(L,)`` int32 valid points not stored because their bucket was full.
    """

    xyz: jax.Array
    index: jax.Array
    base: jax.Array
    mask: jax.Array
    origin: jax.Array
    dims: jax.Array
    dense: jax.Array
    cell_size: jax.Array
    overflow: jax.Array

    @property
    def num_levels(self) -> int:
        return int(self.cell_size.shape[-1])

    @property
    def cell_capacity(self) -> int:
        return int(self.index.shape[-1])


def grid_table_size(capacity: int, factor: float = 2.0) -> int:
    """Hash-table size for a point set of ``capacity`` rows: the power of two
    ``>= factor * capacity`` (at least 256)."""
    return 1 << max(8, int(np.ceil(np.log2(max(factor * int(capacity), 1.0)))))


def level_table_sizes(capacity: int, cell_sizes) -> tuple[int, ...]:
    """Host: static table sizes for the levels of ``cell_sizes`` (values known on the host).
    The finest level gets ``4 x capacity`` buckets: collision-free (a linear index) when the
    points' cells span at most that many, else hashed, and then cells sharing a bucket
    overflow when together they hold more than ``cell_capacity`` points (a cell holds up to 8
    voxel centres at cell = 2 voxels), which the grid's ``overflow`` and ICP's
    ``grid_overflow`` report. A level ``r`` times coarser needs about ``r^2`` times fewer cells on surfaces, so it gets
    ``4 capacity / r^2`` (>= 256)."""
    sizes = np.asarray(cell_sizes, np.float64).reshape(-1)
    finest = float(np.min(sizes))
    return tuple(grid_table_size(capacity, 4.0 / (float(c) / finest) ** 2) for c in sizes)


def _cells(points, cell_size):
    # times the reciprocal, not a division: XLA:CPU turns ``x / h`` into ``x * (1 / h)`` in some
    # compiled contexts and not in others, which moved boundary points between cells depending
    # on the block size of a query; a product rounds the same everywhere
    return jnp.floor(points * (1.0 / cell_size)).astype(jnp.int32)


def _hash(cells, mask):
    """Spatial hash of integer cells (Teschner et al. 2003) with a murmur3 finaliser, so
    that neighbouring cells spread over the table (fewer collisions than the plain XOR);
    ``mask = table_size - 1`` (static or traced)."""
    c = cells.astype(jnp.uint32)
    h = (c[..., 0] * _P1) ^ (c[..., 1] * _P2) ^ (c[..., 2] * _P3)
    h = h ^ (h >> 16)
    h = h * np.uint32(0x85EBCA6B)
    h = h ^ (h >> 13)
    h = h * np.uint32(0xC2B2AE35)
    h = h ^ (h >> 16)
    return (h & jnp.asarray(mask).astype(jnp.uint32)).astype(jnp.int32)


def _bucket(cells, mask, origin, dims, dense):
    """Bucket of integer ``cells (..., 3)``: linear index inside the box when ``dense``
    (cells outside the box go to the sink ``mask + 1``), else the hash."""
    rel = cells - origin
    inside = jnp.all((rel >= 0) & (rel < dims), axis=-1)
    lin = rel[..., 0] + dims[0] * (rel[..., 1] + dims[1] * rel[..., 2])
    return jnp.where(dense, jnp.where(inside, lin, mask + 1), _hash(cells, mask))


def _build_level(points, count, cell_size, table_size, bits: int, cell_capacity: int, centroids: bool):
    """One level's slots: ``table_size`` (a power of two, may be traced) buckets whose numbers
    fit in ``bits`` (static) bits. Returns ``(bucket or -1, slot, value, order, overflow,
    origin, dims, dense)`` of the level's ``n`` entries (``n`` = the points' rows)."""
    points = jnp.asarray(points, jnp.float32)
    n = points.shape[0]
    cell_size = jnp.asarray(cell_size, jnp.float32)
    rows = jnp.arange(n, dtype=jnp.int32)
    valid = (rows < count) & jnp.all(jnp.isfinite(points), axis=-1)
    safe = jnp.where(valid[:, None], points, 0.0)
    sub = _cells(safe, cell_size * 0.5)  # half-size sub-cells (for centroid levels)
    cells = jnp.right_shift(sub, 1) if centroids else _cells(safe, cell_size)
    origin, top = column_extent(cells, valid)  # cells come from float32 floors: exact in float32
    dims = jnp.where(any_of(valid), top - origin + 1, 1)
    table_size = jnp.asarray(table_size, jnp.int32)
    dense = jnp.prod(dims.astype(jnp.float32)) <= table_size.astype(jnp.float32)
    mask = table_size - 1
    bucket = jnp.where(valid, _bucket(cells, mask, origin, dims, dense), table_size)
    if centroids:
        # one entry per occupied half-size sub-cell: its centroid (a voxel-grid downsample at
        # cell/2, as PCL's VoxelGrid in the thesis code); a cell has at most 8 of them
        cell_id = _hash(cells, jnp.int32(0x7FFFFFFF))  # separates colliding cells of a bucket
        octant = (sub[:, 0] & 1) | ((sub[:, 1] & 1) << 1) | ((sub[:, 2] & 1) << 2)
        # (bucket, octant) as one key (tables stay below 2^28 buckets), then the cell
        bucket_octant = bucket * 8 + octant
        order = lexsort_rows(((bucket_octant, bits + 3), (cell_id, 31)))
        sbo, sc = bucket_octant[order], cell_id[order]
        sb = jnp.right_shift(sbo, 3)
        seg_start = jnp.concatenate([jnp.ones((1,), bool), (sbo[1:] != sbo[:-1]) | (sc[1:] != sc[:-1])])
        seg = cumsum(seg_start.astype(jnp.int32)) - 1
        sums = jax.ops.segment_sum(safe[order], seg, num_segments=n)
        cnt = jax.ops.segment_sum(jnp.ones((n,), jnp.float32), seg, num_segments=n)
        value = (sums / jnp.maximum(cnt, 1.0)[:, None])[seg]
        b_start = jnp.concatenate([jnp.ones((1,), bool), sb[1:] != sb[:-1]])
        first = jax.lax.cummax(jnp.where(b_start, rows, 0), axis=0)
        rank = seg - seg[first]
        entry = seg_start
    else:
        # pseudo-random order within a bucket, so that full buckets keep a spatially uniform
        # subset: a multiplicative scramble of the rows (a permutation when n is a power of two)
        scramble = rows.astype(jnp.uint32) * np.uint32(2654435761)
        if n & (n - 1) == 0:
            order = lexsort_rows(((bucket, bits),),
                                 first=(scramble & np.uint32(n - 1)).astype(jnp.int32))
        else:
            order = lexsort_rows(((bucket, bits), (scramble >> 1, 31)))
        sb = bucket[order]
        value = safe[order]
        is_start = jnp.concatenate([jnp.ones((1,), bool), sb[1:] != sb[:-1]])
        rank = rows - jax.lax.cummax(jnp.where(is_start, rows, 0), axis=0)
        entry = jnp.ones((n,), bool)
    keep = entry & (sb < table_size) & (rank < cell_capacity)
    overflow = count_true(entry & (sb < table_size) & (rank >= cell_capacity))
    # the slots to fill: (bucket, rank) of the kept entries, -1 for the others (dropped by the scatter)
    return jnp.where(keep, sb, -1), jnp.where(keep, rank, 0), value, order, overflow, origin, dims, dense


def build_grids(points, count, cell_sizes, *, table_sizes, cell_capacity: int = 8,
                centroid_levels=None) -> HashGrid:
    """Bin ``points (n, 3)`` [m] (rows ``>= count`` are padding; non-finite rows are ignored)
    into one hashed grid per entry of ``cell_sizes (L,)`` [m] (traced). ``table_sizes``
    (static tuple of powers of two, one per level, e.g. ``level_table_sizes``) and
    ``cell_capacity`` are static. Jittable and vmappable.

    ``centroid_levels`` (static tuple of bools, default all False): levels that store, instead
    of the points, the centroids of the occupied half-size sub-cells (a voxel-grid downsample
    at ``cell_size / 2``, at most 8 per cell, so ``cell_capacity = 8`` never overflows except
    on hash collisions). ICP uses this for its coarse stages: exact nearest *centroid* search
    instead of a random subset of crowded cells. ``index`` then names one point of the
    sub-cell.
    """
    table_sizes = tuple(int(t) for t in np.atleast_1d(table_sizes))
    for t in table_sizes:
        if t < 1 or t & (t - 1) or t > 1 << 27:
            raise ValueError(f"table sizes must be powers of two up to 2^27, got {table_sizes}")
    sizes = _as_sizes(cell_sizes)
    if sizes.shape[0] != len(table_sizes):
        raise ValueError(f"{sizes.shape[0]} cell sizes but {len(table_sizes)} table sizes")
    cl = (False,) * len(table_sizes) if centroid_levels is None else tuple(bool(c) for c in centroid_levels)
    if len(cl) != len(table_sizes):
        raise ValueError(f"centroid_levels needs {len(table_sizes)} entries, got {len(cl)}")
    return _build_grids_jit(points, count, sizes, table_sizes=table_sizes, cell_capacity=int(cell_capacity),
                            centroid_levels=cl)


@partial(jax.jit, static_argnames=("table_sizes", "cell_capacity", "centroid_levels"))
def _build_grids_jit(points, count, sizes, *, table_sizes, cell_capacity, centroid_levels):
    num_rows = sum(t + 1 for t in table_sizes)  # each level's row t is its always-empty sink
    bases = np.cumsum([0] + [t + 1 for t in table_sizes[:-1]]).tolist()
    rows, slots, values, orders, ovs, boxes = [], [], [], [], [], []
    # consecutive levels of one kind are built by one loop over them (one body to compile),
    # their bucket numbers packed in the widest level's bits
    start = 0
    while start < len(table_sizes):
        stop = start + 1
        while stop < len(table_sizes) and centroid_levels[stop] == centroid_levels[start]:
            stop += 1
        group = range(start, stop)
        bits = max(table_sizes[l].bit_length() for l in group)
        build = partial(_build_level, points, count, bits=bits, cell_capacity=cell_capacity,
                        centroids=centroid_levels[start])
        per_level = jnp.asarray([table_sizes[l] for l in group], jnp.int32)
        r, k, value, order, ov, origin, dims, dense = jax.lax.map(
            lambda a: build(a[0], a[1]), (sizes[start:stop], per_level))
        for i, l in enumerate(group):
            rows.append(jnp.where(r[i] >= 0, bases[l] + r[i], num_rows))  # num_rows: out of bounds, dropped
            slots.append(k[i]), values.append(value[i]), orders.append(order[i]), ovs.append(ov[i])
            boxes.append((origin[i], dims[i], dense[i]))
        start = stop
    # one table for all levels, filled by one scatter per array (no per-level tables to concatenate)
    rows, slots = jnp.concatenate(rows), jnp.concatenate(slots)
    xyz = jnp.full((3, num_rows, cell_capacity), _FAR, jnp.float32).at[:, rows, slots].set(
        jnp.concatenate(values).T, mode="drop")
    index = jnp.full((num_rows, cell_capacity), -1, jnp.int32).at[rows, slots].set(
        jnp.concatenate(orders), mode="drop")
    return HashGrid(
        xyz=xyz,
        index=index,
        base=jnp.asarray(bases, jnp.int32),
        mask=jnp.asarray([t - 1 for t in table_sizes], jnp.int32),
        origin=jnp.stack([b[0] for b in boxes]),
        dims=jnp.stack([b[1] for b in boxes]),
        dense=jnp.stack([b[2] for b in boxes]),
        cell_size=sizes,
        overflow=jnp.stack(ovs),
    )


def _as_sizes(cell_sizes) -> jax.Array:
    """Cell sizes [m] as a ``(levels,)`` float32 array (host values shaped on the host: a
    device reshape compiles a program)."""
    if isinstance(cell_sizes, jax.Array):
        sizes = jnp.asarray(cell_sizes, jnp.float32)
        return sizes if sizes.ndim else sizes.reshape(1)
    return to_device(np.atleast_1d(np.asarray(cell_sizes, np.float32)))


def build_grid(points, count, cell_size, *, table_size: int, cell_capacity: int = 8) -> HashGrid:
    """A single-level ``HashGrid`` with cells of edge ``cell_size`` [m]."""
    return build_grids(points, count, _as_sizes(cell_size),
                       table_sizes=(table_size,), cell_capacity=cell_capacity)


QUERY_BLOCK = 2048  # rows of the query blocks of the nearest-neighbour search
_REDO_CHUNK = 256  # the second phase's blocks: its queries are few near a solution


def _slot_bits(k: int) -> int:
    """Bits that number the candidate slots of a 27-cell search (``27 K``)."""
    return int(np.ceil(np.log2(27 * k)))


def _nearest_in_rows(xyz, index, rows, q, finite):
    """The nearest stored point to each query ``q (b, 3)`` among the table rows ``rows (b, r)``
    (all ``K`` slots of each): ``(dist2, index, match)``, ``inf`` / ``-1`` when none (or the
    query is not ``finite``). Ties go to the first slot in ``rows`` order.

    The slot comes from one integer min over packed keys: a squared distance is >= 0, so its
    float32 bits order as an int32; their low ``_slot_bits(K)`` bits (8 for ``K = 8``) are
    replaced by the slot's number, so candidates whose squared distances agree to a relative
    ``2^-15`` (~1.5e-5 in distance, 6 um at 0.4 m) count as tied and the first slot wins.
    ``dist2`` is the exact minimum (one reduction instead of a min and then a first-index
    argmax over the distances). The 8- and 27-cell searches use the same bits and the same slot order,
    and the first phase settles a query only when every slot tied with its nearest lies in its
    8 cells, so the two agree. ``K > 37`` (more than 10 bits) uses the exact two-pass form."""
    d2 = 0.0
    for a in range(3):
        pa = xyz[a].at[rows].get(mode="promise_in_bounds")  # (b, r, K)
        d2 = d2 + (pa - q[:, None, None, a]) ** 2
    b, k = q.shape[0], xyz.shape[-1]
    bits = _slot_bits(k)
    if bits <= 10:
        slot = jnp.arange(rows.shape[1] * k, dtype=jnp.int32).reshape(1, rows.shape[1], k)
        key = (jax.lax.bitcast_convert_type(d2, jnp.int32) & ~((1 << bits) - 1)) | slot
        j = jnp.min(key, axis=(1, 2)) & ((1 << bits) - 1)
        best = jnp.min(d2, axis=(1, 2))
    else:  # min, then the first slot attaining it (= argmin)
        d2 = d2.reshape(b, rows.shape[1] * k)
        best = jnp.min(d2, axis=-1)
        j = jnp.argmax(d2 == best[:, None], axis=-1)
    row = jnp.take_along_axis(rows, (j // k)[:, None], axis=-1)[:, 0]
    idx = index[row, j % k]
    found = (idx >= 0) & finite
    match = jnp.stack([xyz[a][row, j % k] for a in range(3)], -1)
    return jnp.where(found, best, jnp.inf), jnp.where(found, idx, -1), match


def _nearest_block(xyz, index, base, mask, origin, dims, dense, h, q):
    finite = jnp.all(jnp.isfinite(q), axis=-1)
    q = jnp.where(finite[..., None], q, _FAR)
    c = _cells(q, h)
    rows = base + _bucket(c[:, None, :] + jnp.asarray(_OFFSETS)[None], mask, origin, dims, dense)  # (b, 27)
    return _nearest_in_rows(xyz, index, rows, q, finite)


@jax.jit
def nearest(grid: HashGrid, queries, level=0):
    """Nearest grid point to each query ``(n, 3)`` [m] among the 27 cells around it.

    ``level`` selects the grid level (traced int). Returns ``(dist2 (n,) float32 [m^2],
    index (n,) int32)``; ``index == -1`` and ``dist2 = inf`` when the 27 cells are empty.
    Exact for every point within ``cell_size`` of the query when ``overflow[level] == 0``.
    """
    d2, idx, _ = nearest_with_points(grid, queries, level)
    return d2, idx


# the 2x2x2 block of cells nearest to a query, in the order of _OFFSETS (x fastest)
_CORNERS = np.array([(i, j, k) for k in (0, 1) for j in (0, 1) for i in (0, 1)], np.int32)


def _near_block(xyz, index, base, mask, origin, dims, dense, h, q):
    """First phase: the nearest point among the 2 x 2 x 2 cells nearest to each query (8 of the
    27), and ``sure (b,)``: that point is the 27-cell answer. The block holds every point
    within ``g = h (1 - max_a min(f_a, 1 - f_a))`` (>= h / 2) of the query, ``f`` its
    position in its cell; so a point found nearer than ``g`` is the nearest of all, and the
    27-cell search picks the same slot (ties resolve in the same order)."""
    finite = jnp.all(jnp.isfinite(q), axis=-1)
    q = jnp.where(finite[..., None], q, _FAR)
    s = q * (1.0 / h)  # as _cells
    c = jnp.floor(s)
    f = s - c
    lo = c.astype(jnp.int32) - (f < 0.5).astype(jnp.int32)
    rows = base + _bucket(lo[:, None, :] + jnp.asarray(_CORNERS)[None], mask, origin, dims, dense)  # (b, 8)
    d2, idx, match = _nearest_in_rows(xyz, index, rows, q, finite)
    # float32 cells: the cell of a point may be off by rounding of p / h (relative 2^-24)
    slack = (jnp.max(jnp.abs(s), axis=-1) + 2.0) * 2.5e-7
    g = h * (1.0 - jnp.max(jnp.minimum(f, 1.0 - f), axis=-1) - slack)
    # d2 = inf when nothing was found; the margin keeps every slot tied with the nearest (within
    # 2^-15, see _nearest_in_rows) inside the block, so the 27-cell search picks the same slot
    sure = (d2 * (1.0 + 2.0**-14) < g * g) | ~finite
    return d2, idx, match, sure


def _blocked(f, q, count, outs, chunk: int = QUERY_BLOCK):
    """Apply the block kernel ``f`` to ``q (n, 3)`` in blocks of ``chunk`` rows; with ``count``
    (traced int) only the blocks that hold rows ``< count`` run (a loop of dynamic length, so
    padding blocks cost nothing), and rows of the blocks past it get ``outs``' fill values."""
    n = q.shape[0]
    if n <= chunk or n % chunk:
        return f(q)
    if count is None:
        out = jax.lax.map(f, q.reshape(n // chunk, chunk, 3))
        return tuple(x.reshape((n,) + x.shape[2:]) for x in out)

    def body(i, acc):
        res = f(jax.lax.dynamic_slice_in_dim(q, i * chunk, chunk))
        return tuple(jax.lax.dynamic_update_slice_in_dim(a, r, i * chunk, 0) for a, r in zip(acc, res))

    init = tuple(jnp.full((n,) + shape, v, dt) for v, shape, dt in outs)
    blocks = jnp.clip((jnp.asarray(count, jnp.int32) + chunk - 1) // chunk, 0, n // chunk)
    return jax.lax.fori_loop(0, blocks, body, init)


_FILL = ((jnp.inf, (), jnp.float32), (-1, (), jnp.int32), (0.0, (3,), jnp.float32))


def nearest_with_points(grid: HashGrid, queries, level=0, count=None, two_phase: bool = True):
    """As ``nearest``, plus the matched coordinates ``(n, 3)`` (the stored point, or the
    sub-cell centroid on a centroid level). Queries are processed in blocks of 2048; with
    ``count`` (traced int), rows ``>= count`` are padding: blocks entirely past it are skipped
    (their rows get ``inf`` / ``-1`` / zeros).

    ``two_phase`` (static; used when ``n`` is a multiple of 2048 above it): search the 8 cells
    nearest to each query first and the 27 cells only for the queries whose answer that does
    not settle (compacted, ~1 % of them near an ICP solution, all of them far from the target).
    Same answers as one phase, ~3x cheaper when most queries lie near the target. Under
    ``vmap`` the skipped blocks are computed anyway (``cond`` becomes ``select``): pass
    ``False`` there."""
    level = jnp.asarray(level, jnp.int32)
    base, mask, h = grid.base[level], grid.mask[level], grid.cell_size[level]
    origin, dims, dense = grid.origin[level], grid.dims[level], grid.dense[level]
    q = jnp.asarray(queries, jnp.float32)
    n = q.shape[0]
    full = lambda qb: _nearest_block(grid.xyz, grid.index, base, mask, origin, dims, dense, h, qb)  # noqa: E731
    if not two_phase or n <= QUERY_BLOCK or n % QUERY_BLOCK:
        return _blocked(full, q, count, _FILL)
    near = lambda qb: _near_block(grid.xyz, grid.index, base, mask, origin, dims, dense, h, qb)  # noqa: E731
    d2, idx, match, sure = _blocked(near, q, count, _FILL + ((True, (), jnp.bool_),))
    redo = ~sure if count is None else ~sure & (jnp.arange(n) < count)
    n_redo = count_true(redo)
    rows = nonzero_rows(redo, n, n)
    d2r, idxr, matchr = _blocked(full, q.at[rows].get(mode="fill", fill_value=_FAR), n_redo, _FILL, _REDO_CHUNK)
    put = lambda a, v: a.at[rows].set(v, mode="drop")  # noqa: E731
    return put(d2, d2r), put(idx, idxr), put(match, matchr)


@jax.jit
def any_within(grid: HashGrid, queries, radius, level=0):
    """``(n,)`` bool: some grid point lies within ``radius`` [m] of each query
    (exact for ``radius <= cell_size[level]`` when nothing overflowed)."""
    d2, index = nearest(grid, queries, level)
    r = jnp.asarray(radius, jnp.float32)
    return (index >= 0) & (d2 <= r * r)
