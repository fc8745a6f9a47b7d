"""Helpers shared by the tests (not part of the package)."""

import contextlib
import functools

import numpy as np

from octomerge_jax import kernel_store, morton, se3

#: float64 NumPy ``(4, 4)`` from OctoMap ``Pose6D`` parameters (exact ground truth).
xyz_rpy64 = functools.partial(se3.from_xyz_rpy, xp=np)


def voxel_log_odds(m) -> dict:
    """``{finest code: log-odds}`` of every voxel the map ``m`` knows (its leaves expanded)."""
    L = m.leaves()
    codes, leaf = morton.leaf_cell_codes(L.codes, L.depths)
    return dict(zip(codes.tolist(), L.log_odds[leaf].tolist()))


@contextlib.contextmanager
def own_kernel_store(path, kernels=()):
    """A kernel store of a test's own in directory ``path`` (yielded), with the programs the
    ``kernels`` (``StoredJit`` s) already hold in this process forgotten, so they are read or
    compiled again; the run's store (tests/conftest.py) is put back after."""
    for k in kernels:
        k._loaded.clear()
    run_store = kernel_store.store_dir()
    kernel_store.open_store(path)
    try:
        yield path
    finally:
        kernel_store.close_store()
        if run_store is not None:
            kernel_store.open_store(run_store)
