"""The query clouds of ICP's coarse stages.

With ``coarse_matching`` ``"centroid"`` or ``"nearest"`` the coarse stages (all but the
last) query every k-th source point (Open3D's ``uniform_down_sample``), ``k = clip(count //
COARSE_MIN_QUERIES, 1, COARSE_EVERY)``, packed into ``coarse_rows(n)`` rows; with
``"symmetric"`` they query the source's voxel-grid centroids at half the stage's
correspondence distance, weighted by their point counts (the thesis code downsampled both
clouds with PCL's VoxelGrid). The last stage always queries every source point.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ..._ops import count_true, cumsum
from .. import neighbors
from ...types import COARSE_MATCHING_CHOICES as COARSE_MATCHING

__all__ = ["COARSE_MATCHING", "check_coarse_matching", "COARSE_EVERY", "COARSE_MIN_QUERIES", "Queries", "voxel_downsample", "coarse_rows", "every_kth",
           "coarse_clouds", "coarse_cloud", "QueryClouds", "query_clouds"]

# coarse stages query every k-th source point, k <= COARSE_EVERY, keeping at least one query
# block (neighbors.QUERY_BLOCK): fewer would not save a block
COARSE_EVERY, COARSE_MIN_QUERIES = 4, 2048


def check_coarse_matching(coarse_matching: str) -> None:
    """Raises ``ValueError`` unless ``coarse_matching`` is one of ``COARSE_MATCHING``."""
    if coarse_matching not in COARSE_MATCHING:
        raise ValueError(f"coarse_matching must be one of {COARSE_MATCHING}, got {coarse_matching!r}")


class Queries(NamedTuple):
    """A stage's query cloud (a leading axis ``E`` where several are stacked)."""

    points: jax.Array  # (m, 3) float32 [m], source frame; rows >= count are padding
    weights: jax.Array  # (m,) float32, point counts behind each row (0 on padding)
    count: jax.Array  # () int32, valid rows


def voxel_downsample(points, valid, cell):
    """Voxel-grid downsample (PCL's VoxelGrid): the centroid of the valid ``points (n, 3)`` in
    each occupied cube of edge ``cell`` [m] (traced). Returns ``(centroids (n, 3), weights (n,)
    float32 point counts, m)``: rows ``< m`` hold the cells (weight >= 1), the rest weight 0.
    Jittable and vmappable (one sort and two segment sums)."""
    n = points.shape[0]
    big = jnp.iinfo(jnp.int32).max
    c = jnp.where(valid[:, None], jnp.floor(points / cell).astype(jnp.int32), big)
    rows = jnp.arange(n, dtype=jnp.int32)
    cx, cy, cz, order = jax.lax.sort((c[:, 0], c[:, 1], c[:, 2], rows), num_keys=3)
    start = jnp.concatenate([jnp.ones((1,), bool),
                             (cx[1:] != cx[:-1]) | (cy[1:] != cy[:-1]) | (cz[1:] != cz[:-1])])
    seg = cumsum(start.astype(jnp.int32)) - 1
    v = valid[order]
    sums = jax.ops.segment_sum(jnp.where(v[:, None], points[order], 0.0), seg, num_segments=n)
    counts = jax.ops.segment_sum(v.astype(jnp.float32), seg, num_segments=n)
    return sums / jnp.maximum(counts, 1.0)[:, None], counts, count_true(start & v)


def coarse_rows(n: int, downsample: bool) -> int:
    """Static rows of the coarse stages' query cloud for a source of capacity ``n``. Every k-th
    point (``every_kth``, ``m = COARSE_MIN_QUERIES``) leaves ``count`` rows for ``count <
    2 m`` (k = 1), at most ``1.5 m`` for k = 2 and 3, and ``count / 4 <= n / 4`` for k = 4:
    so ``max(min(n, 2 m), n / 4)`` rows, rounded up to whole query blocks, hold every count
    (``n`` itself for small clouds). The voxel-grid centroids (``downsample``) need ``n``."""
    if downsample:
        return n
    block = neighbors.QUERY_BLOCK  # the search's query block
    rows = max(min(n, 2 * COARSE_MIN_QUERIES), -(-n // COARSE_EVERY))
    return min(n, -(-rows // block) * block)


def every_kth(src, source_count, rows: int) -> Queries:
    """Every k-th of the ``source_count`` valid points of ``src (n, 3)`` [m], ``k =
    clip(count // COARSE_MIN_QUERIES, 1, COARSE_EVERY)``, packed to the front of ``rows`` rows
    (``coarse_rows``), weight 1 each."""
    n = src.shape[0]
    count = jnp.asarray(source_count, jnp.int32)
    k = jnp.clip(count // COARSE_MIN_QUERIES, 1, COARSE_EVERY)
    at = jnp.arange(rows, dtype=jnp.int32) * k
    keep = at < count
    pts = jnp.where(keep[:, None], src[jnp.minimum(at, n - 1)], 0.0)
    return Queries(pts, keep.astype(src.dtype), (count + k - 1) // k)


def coarse_clouds(src, valid, source_count, dists, downsample: bool) -> Queries | None:
    """The query clouds of the coarse stages, stacked: ``Queries`` with a leading axis ``E``
    and ``m = coarse_rows(n, downsample)`` rows: with ``downsample`` the voxel-grid centroids of
    ``src (n, 3)`` [m] (valid rows ``valid (n,)``) at ``d / 2`` for each coarse stage's
    distance ``d`` of ``dists (s,)`` [m] (``E = s - 1``), else every k-th point (``E = 1``,
    shared by all). ``None`` for a single stage."""
    num_stages = dists.shape[0]
    if num_stages == 1:
        return None
    if downsample:
        coarse = [voxel_downsample(src, valid, dists[s] * 0.5) for s in range(num_stages - 1)]
    else:
        coarse = [every_kth(src, source_count, coarse_rows(src.shape[0], False))]
    return Queries(*(jnp.stack([c[i] for c in coarse]) for i in range(3)))


def coarse_cloud(clouds: Queries, stage) -> Queries:
    """Coarse stage ``stage``'s query cloud of the stacked ``clouds`` (``coarse_clouds``)."""
    i = jnp.minimum(stage, clouds.points.shape[0] - 1)
    return Queries(clouds.points[i], clouds.weights[i], clouds.count[i])


class QueryClouds(NamedTuple):
    """Every query cloud of one registration."""

    full: Queries  # rows n: the source points, weight 1 (the last stage, and the final report)
    coarse: Queries | None  # leading axis E, rows coarse_rows(n): coarse_clouds; None for one stage


def query_clouds(source, source_count, dists, coarse_matching: str) -> QueryClouds:
    """The query clouds of ``source (n, 3)`` [m] (no gradient; rows ``>= source_count`` zeroed)
    for the stages ``dists (s,)`` [m] and ``coarse_matching`` (static)."""
    n = source.shape[0]
    valid = jnp.arange(n) < source_count
    src = jnp.where(valid[:, None], jax.lax.stop_gradient(source), 0.0)
    coarse = coarse_clouds(src, valid, source_count, dists, coarse_matching == "symmetric")
    full = Queries(src, valid.astype(src.dtype), jnp.asarray(source_count, jnp.int32))
    return QueryClouds(full, coarse)
