"""A team of robots' maps of one scene: overlapping tiles of the scene's surface, each robot's
map in a frame of its own (random yaw and offset), with the true transforms into robot 0's
frame. The input of ``merge_many``'s tests, ``benchmarks/bench_many.py`` and the many-robots
notebook (NumPy and trimesh, deterministic for a seed, no ray casting: every surface of a tile
is seen)."""

from __future__ import annotations

import dataclasses

import numpy as np
import trimesh

from .. import se3
from ..map import OccupancyMap
from ..tree import from_voxels
from .scenes import make_scene

__all__ = ["TeamMaps", "team_maps", "tile_grid"]


@dataclasses.dataclass(frozen=True)
class TeamMaps:
    """``team_maps``'s result.

    - ``maps``: one ``OccupancyMap`` per robot, each in its own frame.
    - ``T_0_k``: ``(n, 4, 4)`` float64, the true transform of robot k's frame into robot 0's
      [m] (identity for k = 0).
    - ``tiles``: ``(n, 2, 2)`` float64, each robot's tile ``[[x_lo, y_lo], [x_hi, y_hi]]`` in the
      world frame [m].
    - ``T_world_k``: ``(n, 4, 4)`` float64, each robot's frame in the world frame.
    """

    maps: tuple[OccupancyMap, ...]
    T_0_k: np.ndarray
    tiles: np.ndarray
    T_world_k: np.ndarray


def tile_grid(bounds_xy, num_tiles: int, overlap_m: float) -> np.ndarray:
    """``(num_tiles, 2, 2)`` xy tiles ``[[x_lo, y_lo], [x_hi, y_hi]]`` [m] covering
    ``bounds_xy`` ``[[x_lo, y_lo], [x_hi, y_hi]]``: a grid of ``cols x rows`` cells (as square
    as the bounds allow, read row by row), each grown by ``overlap_m`` on every side so that
    neighbours share a band ``2 overlap_m`` wide. Raises ``ValueError`` for fewer than one tile."""
    if num_tiles < 1:
        raise ValueError(f"num_tiles must be >= 1, got {num_tiles}")
    (x0, y0), (x1, y1) = np.asarray(bounds_xy, np.float64)
    aspect = (x1 - x0) / max(y1 - y0, 1e-9)
    rows = max(1, int(round(np.sqrt(num_tiles / aspect))))
    while num_tiles % rows:
        rows -= 1
    cols = num_tiles // rows
    xs, ys = np.linspace(x0, x1, cols + 1), np.linspace(y0, y1, rows + 1)
    out = [[[xs[c] - overlap_m, ys[r] - overlap_m], [xs[c + 1] + overlap_m, ys[r + 1] + overlap_m]]
           for r in range(rows) for c in range(cols)]
    return np.asarray(out)


def team_maps(scene="office", num_robots: int = 4, resolution: float = 0.2, *, seed: int = 0,
              overlap_m: float = 1.5, max_offset_m: float = 5.0, free_height_m: float = 2.0,
              points_per_m2: float | None = None,
              tiles=None) -> TeamMaps:
    """``num_robots`` maps of ``scene`` (a ``Scene`` or ``"lab"``, ``"office"``, ``"campus"``):
    robot k maps the scene surfaces above its tile (``tile_grid`` over the scene's footprint,
    or ``tiles``) in frame k, turned by a random yaw in ``[-pi, pi)`` and shifted by up to
    ``max_offset_m`` in x and y from the world frame (``seed`` draws both; robot 0's frame is
    drawn too, so no map is in the world frame). Occupied voxels get log-odds 2.0; every other
    voxel of the tile between 0.3 m and ``free_height_m`` above the ground, more than one voxel
    from a surface, is observed free (log-odds -1.2, every second voxel along each axis): the
    free space that lets map agreement tell a right placement from a wrong one (insides of
    closed boxes count as free, the same for every robot).

    Args:
      resolution: voxel size [m].
      overlap_m: each tile grows by this on every side [m].
      free_height_m: top of the observed free space above the ground [m].
      points_per_m2: surface samples per square metre (default: 9 per voxel face) before
        voxelisation in each robot's frame, so every robot has a lattice of its own.

    Returns a ``TeamMaps``. Raises ``ValueError`` for a tile list of the wrong shape.
    """
    sc = make_scene(scene, seed)
    rng = np.random.default_rng(seed)
    bounds = sc.bounds
    if tiles is None:
        tiles = tile_grid(bounds[:, :2], num_robots, overlap_m)
    tiles = np.asarray(tiles, np.float64)
    if tiles.shape != (num_robots, 2, 2):
        raise ValueError(f"tiles: expected shape ({num_robots}, 2, 2), got {tiles.shape}")
    density = 9.0 / resolution**2 if points_per_m2 is None else float(points_per_m2)
    count = int(sc.mesh.area * density)
    pts, _ = trimesh.sample.sample_surface(sc.mesh, count, seed=seed)
    pts = np.asarray(pts, np.float64)
    T_world_k = []
    for _ in range(num_robots):
        x, y = rng.uniform(-max_offset_m, max_offset_m, 2)
        T_world_k.append(se3.from_xyz_rpy(x, y, rng.uniform(-0.2, 0.2), 0.0, 0.0, rng.uniform(-np.pi, np.pi),
                                          xp=np))
    T_world_k = np.stack(T_world_k)
    maps = []
    for k in range(num_robots):
        (xl, yl), (xh, yh) = tiles[k]
        inside = (pts[:, 0] >= xl) & (pts[:, 0] < xh) & (pts[:, 1] >= yl) & (pts[:, 1] < yh)
        T_k_world = np.linalg.inv(T_world_k[k])
        p = pts[inside] @ T_k_world[:3, :3].T + T_k_world[:3, 3]
        keys = np.unique(np.floor(p / resolution).astype(np.int64), axis=0)
        free = _free_keys(keys, T_world_k[k], tiles[k], (bounds[0, 2] + 0.3, bounds[0, 2] + free_height_m),
                          resolution)
        centres = (np.concatenate([keys, free]) + 0.5) * resolution
        values = np.concatenate([np.full(len(keys), 2.0, np.float32), np.full(len(free), -1.2, np.float32)])
        maps.append(from_voxels(centres, values, resolution))
    T_0_k = np.linalg.inv(T_world_k[0]) @ T_world_k
    return TeamMaps(tuple(maps), T_0_k, tiles, T_world_k)


def _free_keys(occupied_keys, T_world_k, tile, z_range, resolution: float) -> np.ndarray:
    """Voxel keys ``(f, 3)`` int64 of frame k, every second one along each axis, whose centres
    lie in ``tile`` (world xy) and ``z_range`` (world z) [m] and more than one voxel from
    ``occupied_keys``."""
    lo, hi = occupied_keys.min(0) - 1, occupied_keys.max(0) + 2
    shape = hi - lo
    grid = np.zeros(shape, bool)
    o = occupied_keys - lo
    for d in np.stack(np.meshgrid(*[(-1, 0, 1)] * 3, indexing="ij"), -1).reshape(-1, 3):  # dilate by 1
        q = np.clip(o + d, 0, shape - 1)
        grid[q[:, 0], q[:, 1], q[:, 2]] = True
    axes = [np.arange(0, n, 2) for n in shape]
    cand = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    cand = cand[~grid[cand[:, 0], cand[:, 1], cand[:, 2]]] + lo
    w = ((cand + 0.5) * resolution) @ T_world_k[:3, :3].T + T_world_k[:3, 3]
    (xl, yl), (xh, yh) = tile
    keep = (w[:, 0] >= xl) & (w[:, 0] < xh) & (w[:, 1] >= yl) & (w[:, 1] < yh)
    keep &= (w[:, 2] >= z_range[0]) & (w[:, 2] <= z_range[1])
    return cand[keep]
