"""A synthetic box room for registration tests, benchmarks and notebooks (NumPy only, deterministic).

An asymmetric room (floor, four walls, an L-shaped partition, boxes and a pillar at irregular
places) whose surfaces are sampled densely and voxelised like an occupied-voxel cloud of an
OctoMap (centres of occupied finest voxels) in each robot's own map frame.
"""

from __future__ import annotations

import numpy as np

from .. import se3

__all__ = ["surface_samples", "voxel_centres", "scene_pair"]

# axis-aligned boxes (min xyz, max xyz) in the world frame [m]
_BOXES = [
    ((0.0, 0.0, -0.1), (12.0, 9.0, 0.0)),  # floor slab
    ((0.0, -0.1, 0.0), (12.0, 0.0, 3.0)),  # walls
    ((0.0, 9.0, 0.0), (12.0, 9.1, 3.0)),
    ((-0.1, 0.0, 0.0), (0.0, 9.0, 3.0)),
    ((12.0, 0.0, 0.0), (12.1, 9.0, 3.0)),
    ((4.0, 5.5, 0.0), (4.2, 9.0, 2.2)),  # L-shaped partition
    ((4.0, 5.5, 0.0), (6.5, 5.7, 2.2)),
    ((1.0, 1.0, 0.0), (2.2, 1.8, 0.9)),  # boxes / furniture
    ((6.8, 2.0, 0.0), (7.4, 3.5, 1.6)),
    ((9.5, 6.0, 0.0), (10.1, 6.6, 2.9)),  # pillar
    ((2.5, 6.5, 0.0), (3.1, 7.9, 0.5)),
    ((8.0, 0.5, 0.0), (10.5, 1.2, 0.8)),
    ((5.2, 3.4, 0.0), (5.9, 3.9, 1.1)),
    ((8.5, 6.0, 0.0), (12.0, 9.0, 3.0)),  # closed corner room: the outline is an L, not a rectangle
    ((0.0, 0.0, 2.2), (3.0, 4.0, 3.0)),  # a low ceiling over one corner
]


def surface_samples(spacing: float) -> np.ndarray:
    """Dense samples ``(n, 3)`` [m] of all box faces at ``spacing``, world frame."""
    out = []
    for lo, hi in _BOXES:
        lo, hi = np.asarray(lo), np.asarray(hi)
        for axis in range(3):
            u, v = [a for a in range(3) if a != axis]
            gu = np.arange(lo[u], hi[u] + 1e-9, spacing)
            gv = np.arange(lo[v], hi[v] + 1e-9, spacing)
            U, V = np.meshgrid(gu, gv, indexing="ij")
            for side in (lo[axis], hi[axis]):
                P = np.zeros((U.size, 3))
                P[:, u], P[:, v], P[:, axis] = U.ravel(), V.ravel(), side
                out.append(P)
    return np.concatenate(out)


def voxel_centres(points: np.ndarray, resolution: float) -> np.ndarray:
    """Centres of the distinct OctoMap voxels ``floor(p / res)`` hit by ``points``."""
    k = np.unique(np.floor(points / resolution).astype(np.int64), axis=0)
    return (k + 0.5) * resolution


def scene_pair(resolution: float = 0.2, T_world_2=None, crop_1=(-1.0, 8.0), crop_2=(3.5, 13.0),
               z_max: float = 3.5):
    """Occupied-voxel clouds of two robots' maps of one room.

    Map 1 is in the world frame and sees ``crop_1`` of world x; map 2 sees ``crop_2`` and is
    built in frame 2 with ``T_world_2`` (default: yaw pi/4 about the room centre plus an
    offset, like the thesis's pi/4-rotated second map). Points above world ``z_max`` are
    not seen (a low sensor). Returns ``(points_1, points_2,
    T_1_2)`` with ``points_1 (n1, 3)``, ``points_2 (n2, 3)`` float64 [m] and the true
    ``T_1_2 (4, 4)`` float64 (= ``T_world_2``).
    """
    if T_world_2 is None:
        T_world_2 = se3.from_xyz_rpy(1.0, -0.5, 0.0, 0.0, 0.0, np.pi / 4, xp=np)
    T_world_2 = np.asarray(T_world_2, np.float64)
    dense = surface_samples(resolution / 3.0)
    dense = dense[dense[:, 2] <= z_max]
    in1 = (dense[:, 0] >= crop_1[0]) & (dense[:, 0] <= crop_1[1])
    in2 = (dense[:, 0] >= crop_2[0]) & (dense[:, 0] <= crop_2[1])
    p1 = voxel_centres(dense[in1], resolution)
    T_2_world = np.linalg.inv(T_world_2)
    d2 = dense[in2] @ T_2_world[:3, :3].T + T_2_world[:3, 3]
    p2 = voxel_centres(d2, resolution)
    return p1, p2, T_world_2
