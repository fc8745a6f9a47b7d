"""A small furnished room (4 x 3 x 2 m) as voxel centres and as robots' occupancy maps: the
built-in scene of the pipeline's tests and ``benchmarks/bench_merge.py`` (NumPy, deterministic,
no ray casting)."""

from __future__ import annotations

import numpy as np

from ..map import OccupancyMap
from ..resample import transform_map
from ..tree import from_voxels

__all__ = ["small_room_voxels", "small_room_map"]

# the room's walls, floor and ceiling, then furniture and partitions (min, max corners) [m];
# the partitions run across x and y, so an overlap constrains every direction
_BOXES = [((0, 0, 0), (4.0, 3.0, 2.0)),
          ((0.6, 0.5, 0.0), (1.2, 1.3, 0.8)), ((2.4, 1.6, 0.0), (3.0, 2.2, 1.2)),
          ((1.6, 0.3, 0.0), (1.9, 0.6, 1.6)), ((3.2, 0.4, 0.0), (3.6, 1.0, 0.5)),
          ((2.0, 0.0, 0.0), (2.1, 1.0, 2.0)), ((1.2, 2.0, 0.0), (2.2, 2.1, 1.5))]


def _surface(lo, hi, resolution: float) -> np.ndarray:
    """Voxel centres ``(n, 3)`` [m] on the faces of the box ``[lo, hi]``."""
    axes = [np.arange(a + resolution / 2, b, resolution) for a, b in zip(lo, hi)]
    g = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    lo, hi = np.asarray(lo), np.asarray(hi)
    on = np.any((g - lo < resolution) | (hi - g < resolution), axis=1)
    return g[on]


def small_room_voxels(resolution: float) -> tuple[np.ndarray, np.ndarray]:
    """``(occupied (n, 3), free (k, 3))`` voxel centres [m] of the room in the world frame: the
    surfaces of its boxes, and a slab of observed free space at 1.4-1.9 m height."""
    res = resolution
    occ = np.concatenate([_surface(lo, hi, res) for lo, hi in _BOXES])
    occ = np.unique(np.round(occ / res * 2).astype(np.int64), axis=0) * (res / 2)
    axes = [np.arange(0.2 + res / 2, 3.8, 2 * res), np.arange(0.2 + res / 2, 2.8, 2 * res),
            np.arange(1.4 + res / 2, 1.9, 2 * res)]
    free = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    return occ, free


def small_room_map(x_range, resolution: float, T_world_map=None, voxels=None) -> OccupancyMap:
    """The part of the room with ``x_range[0] <= x < x_range[1]`` [m] as a robot's map in its
    own frame: occupied voxels at log-odds 2.0, free at -1.2. ``T_world_map (4, 4)`` maps the
    robot's frame into the world (default: the world frame itself; otherwise the map is
    resampled with ``transform_map(..., "nearest")``). ``voxels``: ``small_room_voxels``'s
    output, to reuse."""
    occ, free = small_room_voxels(resolution) if voxels is None else voxels
    keep_o = (occ[:, 0] >= x_range[0]) & (occ[:, 0] < x_range[1])
    keep_f = (free[:, 0] >= x_range[0]) & (free[:, 0] < x_range[1])
    centers = np.concatenate([occ[keep_o], free[keep_f]])
    values = np.concatenate([np.full(keep_o.sum(), 2.0, np.float32), np.full(keep_f.sum(), -1.2, np.float32)])
    m = from_voxels(centers, values, resolution)
    if T_world_map is None or np.allclose(T_world_map, np.eye(4)):
        return m
    return transform_map(m, np.linalg.inv(T_world_map), "nearest")
