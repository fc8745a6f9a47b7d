"""A coarse voxel grid of a map's occupied leaf centres, its neighbours and surface normals,
for registration without an initial guess.

An occupancy map is already voxelised, so a coarser grid of its occupied leaf centres is a
natural downsample (``coarse_cloud``): one point per occupied coarse cell, the centroid of
the leaf centres in it. Neighbours within a radius are found by enumerating the grid offsets
inside that radius and looking each neighbour cell up in the sorted cell codes (no tree, no
SciPy): the coarse points sit one per cell, so the offsets are the search. ``normals`` fits a
plane to each point's neighbours (PCA). Host NumPy: a few thousand points.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = ["CoarseCloud", "cell_codes", "cell_keys", "coarse_cloud", "coarse_voxel_size", "neighbor_pairs", "normals"]

_BITS = 21  # bits per axis of a cell code
_OFF = 1 << (_BITS - 1)


class CoarseCloud(NamedTuple):
    """A point cloud reduced to one point per occupied cell of a grid of ``voxel`` [m]."""

    points: np.ndarray  # (m, 3) float64 [m]: centroid of the input points in each cell
    keys: np.ndarray  # (m, 3) int64: cell indices, floor(point / voxel)
    codes: np.ndarray  # (m,) int64: sorted cell codes (keys packed, 21 bits per axis)
    counts: np.ndarray  # (m,) int64: input points per cell
    voxel: float  # [m] cell edge


def cell_codes(keys) -> np.ndarray:
    """Cell keys ``(..., 3)`` int (each within +-2^20) packed into int64 codes ``(...)``."""
    k = np.asarray(keys).astype(np.int64) + _OFF
    return (k[..., 0] << (2 * _BITS)) | (k[..., 1] << _BITS) | k[..., 2]


def cell_keys(codes) -> np.ndarray:
    """``cell_codes``' inverse: int64 cell keys ``(..., 3)`` of ``codes (...)``."""
    c = np.asarray(codes, np.int64)
    mask = (1 << _BITS) - 1
    return np.stack([(c >> (2 * _BITS)) & mask, (c >> _BITS) & mask, c & mask], axis=-1) - _OFF


def coarse_cloud(points, voxel: float) -> CoarseCloud:
    """``points (n, 3)`` [m] reduced to the centroids of the occupied cells of edge ``voxel``
    [m], sorted by cell code. Raises ``ValueError`` for a non-positive ``voxel`` or cells
    beyond the 21-bit code range."""
    if not (np.isfinite(voxel) and voxel > 0):
        raise ValueError(f"voxel must be a positive number of metres, got {voxel!r}")
    p = np.asarray(points, np.float64).reshape(-1, 3)
    keys = np.floor(p / voxel).astype(np.int64)
    if keys.size and np.abs(keys).max() >= _OFF:
        raise ValueError(f"points span more than 2^{_BITS} cells of {voxel:g} m")
    codes, inverse, counts = np.unique(cell_codes(keys), return_inverse=True, return_counts=True)
    sums = np.zeros((codes.shape[0], 3))
    np.add.at(sums, inverse, p)
    centroids = sums / np.maximum(counts, 1)[:, None]
    # the cells' keys from their codes, exactly
    shift = (np.arange(3)[::-1] * _BITS).astype(np.int64)
    cell_keys = ((codes[:, None] >> shift) & ((1 << _BITS) - 1)) - _OFF
    return CoarseCloud(centroids, cell_keys, codes, counts, float(voxel))


def coarse_voxel_size(num_points_fn, resolution: float, target: int = 6000, minimum: float = 0.25) -> float:
    """The coarse cell edge [m]: ``max(3 resolution, minimum)``, grown by 1.25x until
    ``num_points_fn(voxel)`` (occupied coarse cells of the larger cloud) is at most
    ``target`` (at most 20 steps)."""
    v = max(3.0 * float(resolution), float(minimum))
    for _ in range(20):
        if num_points_fn(v) <= target:
            break
        v *= 1.25
    return v


def _offsets(radius_cells: float) -> np.ndarray:
    r = int(np.ceil(radius_cells))
    g = np.arange(-r, r + 1)
    o = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    n = np.linalg.norm(o, axis=1)
    return o[(n <= radius_cells + 1e-9) & (n > 0)]


def neighbor_pairs(cloud: CoarseCloud, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs ``(i, j)`` (each ``(k,)`` int64, ``i != j``, both directions) of coarse
    points whose cells lie within ``radius`` [m] of each other (centre to centre)."""
    i_all, j_all = [], []
    m = cloud.codes.shape[0]
    if m == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    for o in _offsets(radius / cloud.voxel):
        q = cell_codes(cloud.keys + o)
        j = np.searchsorted(cloud.codes, q)
        j = np.minimum(j, m - 1)
        hit = cloud.codes[j] == q
        i_all.append(np.nonzero(hit)[0])
        j_all.append(j[hit])
    return np.concatenate(i_all), np.concatenate(j_all)


def normals(cloud: CoarseCloud, pairs) -> tuple[np.ndarray, np.ndarray]:
    """Unit surface normals ``(m, 3)`` (sign arbitrary) from the covariance of each point's
    neighbours (``pairs`` from ``neighbor_pairs``, the point itself included), and their
    validity ``(m,)`` bool (at least 3 neighbours)."""
    i, j = pairs
    m = cloud.points.shape[0]
    p = cloud.points
    cnt = np.bincount(i, minlength=m) + 1.0
    s = p.copy()
    np.add.at(s, i, p[j])
    mean = s / cnt[:, None]
    d_self = p - mean
    cov = d_self[:, :, None] * d_self[:, None, :]
    d = p[j] - mean[i]
    np.add.at(cov, i, d[:, :, None] * d[:, None, :])
    _, vecs = np.linalg.eigh(cov / cnt[:, None, None])
    return vecs[:, :, 0], cnt >= 4
