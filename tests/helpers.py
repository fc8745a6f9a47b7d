"""Helpers shared by the tests (not part of the package)."""

import functools

import numpy as np

from octomerge_jax import se3

#: float64 NumPy ``(4, 4)`` from OctoMap ``Pose6D`` parameters (exact ground truth).
xyz_rpy64 = functools.partial(se3.from_xyz_rpy, xp=np)
