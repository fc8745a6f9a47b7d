"""Helpers shared by the tests (not part of the package)."""

import functools

import numpy as np

from octomerge_jax import morton, se3

#: float64 NumPy ``(4, 4)`` from OctoMap ``Pose6D`` parameters (exact ground truth).
xyz_rpy64 = functools.partial(se3.from_xyz_rpy, xp=np)


def voxel_log_odds(m) -> dict:
    """``{finest code: log-odds}`` of every voxel the map ``m`` knows (its leaves expanded)."""
    L = m.leaves()
    codes, leaf = morton.leaf_cell_codes(L.codes, L.depths)
    return dict(zip(codes.tolist(), L.log_odds[leaf].tolist()))
