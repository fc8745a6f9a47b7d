"""Occupied-voxel point clouds from maps (thesis §6.1, Alg. 1).

``occupied_points`` runs on the host (its output size is data dependent) and returns a NumPy
``(n, 3)`` float64 array of metres; ``icp.pad_points`` turns it into the padded, static-shape
``(capacity, 3)`` float32 JAX array + count that the jitted registration kernels take.
"""

from __future__ import annotations

import numpy as np

from .. import morton

__all__ = ["occupied_points"]


def occupied_points(occupancy_map, min_log_odds=None, max_points_per_leaf: int | None = None,
                    *, max_points: int = 1 << 26) -> np.ndarray:
    """Centres ``(n, 3)`` float64 [m] of the occupied finest voxels of ``occupancy_map``.

    Occupied means ``log_odds >= min_log_odds`` (default: the map's occupancy threshold, i.e.
    OctoMap ``isNodeOccupied`` as the thesis code uses; the thesis text (§6.1) requires the
    clamping maximum: pass ``map.params.clamp_max_log_odds`` for that). A pruned leaf at depth
    ``d < 16`` contributes the centres of all its ``8^(16-d)`` finest voxels (a coarse leaf is
    not one point, cf. ethz-asl/volumetric_mapping#59), or, with ``max_points_per_leaf``, the
    centres of its descendants at the deepest level with at most that many nodes (a uniform
    sub-grid; 1 gives the thesis's one centre per leaf). Points come in Morton order of the
    leaves. Raises ``ValueError`` if more than ``max_points`` points would be produced.
    """
    thr = occupancy_map.params.occupancy_threshold_log_odds if min_log_odds is None else min_log_odds
    thr = np.float32(np.asarray(thr))
    if max_points_per_leaf is not None and int(max_points_per_leaf) < 1:
        raise ValueError(f"max_points_per_leaf must be >= 1, got {max_points_per_leaf!r}")
    # only the occupied leaves are decoded (not ``leaves()``: every leaf's keys and centres)
    n = occupancy_map.num_leaves
    occ = np.asarray(occupancy_map.log_odds)[:n].astype(np.float32) >= thr
    depths = np.asarray(occupancy_map.depth)[:n][occ].astype(np.int64)
    keys = morton.codes_to_keys(morton.join_codes(np.asarray(occupancy_map.code)[:n][occ])).astype(np.int64)
    if max_points_per_leaf is None:
        levels = morton.TREE_DEPTH - depths
    else:
        cap_levels = int(np.floor(np.log(int(max_points_per_leaf)) / np.log(8) + 1e-9))
        levels = np.minimum(morton.TREE_DEPTH - depths, cap_levels)
    total = int(np.sum(np.left_shift(np.int64(1), 3 * levels)))
    if total > max_points:
        raise ValueError(f"occupied_points: {total} points exceed max_points={max_points} (coarse "
                         "occupied leaves expand to 8^(16-depth) voxels); pass max_points_per_leaf")
    res = occupancy_map.resolution
    if np.all(depths == morton.TREE_DEPTH):  # finest leaves only: one centre each, in leaf order
        return (keys - morton.KEY_OFFSET + 0.5) * res
    out = []
    for lv in np.unique(levels):
        sel = levels == lv
        d_out = depths[sel] + lv  # depth of the emitted sub-nodes
        step = np.left_shift(np.int64(1), morton.TREE_DEPTH - d_out)  # keys per sub-node
        side = 1 << int(lv)
        g = np.arange(side, dtype=np.int64)
        off = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)[:, ::-1]  # x fastest
        k = keys[sel][:, None, :] + off[None] * step[:, None, None]
        centres = (np.floor_divide(k - morton.KEY_OFFSET, step[:, None, None]) + 0.5) * (res * step[:, None, None])
        out.append((np.flatnonzero(sel), centres.reshape(-1, side ** 3, 3)))
    if not out:
        return np.zeros((0, 3), np.float64)
    # restore leaf order
    order = np.concatenate([i for i, _ in out])
    blocks = [c for _, c in out]
    counts = np.concatenate([np.full(len(i), c.shape[1]) for i, c in out])
    flat = np.concatenate([c.reshape(-1, 3) for c in blocks])
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    inv = np.argsort(order, kind="stable")  # leaf i's block is block inv[i] of ``flat``
    length = counts[inv]
    first = np.cumsum(length) - length  # where leaf i's points start in the output
    idx = np.repeat(starts[inv] - first, length) + np.arange(int(length.sum()))
    return flat[idx]
