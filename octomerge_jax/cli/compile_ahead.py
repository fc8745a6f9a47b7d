"""Compiling a merge's later kernels while its registration compiles: a cold command's compile
time spread over both cores. docs/design.md, "Compile cache and warm-up"."""

from __future__ import annotations

import contextlib
import math
import threading

import jax
import numpy as np

from .. import se3
from ..budget import current_budget, memory_budget
from ..kernel_store import compile_listener
from ..map import OccupancyMap
from ..pipeline import MergeConfig, Timings, transform_and_fuse

__all__ = ["compile_ahead", "BYTES_PER_ROW", "SHARE_OF_BUDGET", "UNGUESSED_YAW_RAD"]

SHARE_OF_BUDGET = 0.25
"""The share of the memory budget (``budget.current_budget``) the work ahead may take; a pair
that needs more is not worked ahead."""

BYTES_PER_ROW = 512
"""The work ahead's peak memory per leaf row of the two maps' capacities [bytes], compiling
included (measured: docs/design.md, "Compiling the merge's later kernels during the registration")."""

UNGUESSED_YAW_RAD = 0.5
"""The turn (about the z axis through the origin) the work ahead moves map 2 by when the merge
has no guess: a map turned off the grid's axes by any angle touches about twice the destination
bricks of the unturned map, so a found transform's buckets are a turned map's, not the
identity's (docs/design.md)."""


@contextlib.contextmanager
def compile_ahead(m1: OccupancyMap, m2: OccupancyMap, T_1_2, config: MergeConfig):
    """Within the block (one ``merge`` of ``m1`` and ``m2`` with ``config``), the first time the
    registration compiles a stored kernel afresh (``kernel_store.compile_listener``: only with
    the kernel store open and the program in neither the process nor the store), a second
    thread runs the rest of the merge (``transform_and_fuse``) from ``T_1_2`` ((4, 4); the
    guess; ``None``: a turn by ``UNGUESSED_YAW_RAD``) and drops its result. The GICP polish is
    not worked ahead (``docs/design.md``, "Compiling the merge's later kernels during the registration"). Its programs'
    shapes are bucketed, so they are the ones the real merge needs unless the final transform
    changes a bucket; the real merge then loads them, or waits for the thread compiling them,
    instead of compiling them after the registration. A warm merge starts no thread. A pair
    whose work ahead would need more than ``SHARE_OF_BUDGET`` of the memory budget
    (``BYTES_PER_ROW`` per row of both maps' capacities), and maps of two resolutions
    (resampled by ``merge`` first), are not worked ahead; work ahead that fails, or allocates
    over that share, is dropped silently (the real merge reports its own errors). The block's
    exit waits for the thread."""
    threads: list[threading.Thread] = []
    budget = int(current_budget() * SHARE_OF_BUDGET)
    T = se3.from_xyz_rpy(0.0, 0.0, 0.0, 0.0, 0.0, UNGUESSED_YAW_RAD, xp=np) if T_1_2 is None \
        else np.asarray(T_1_2, np.float64)

    def work():
        with memory_budget(budget), contextlib.suppress(Exception):
            jax.block_until_ready(transform_and_fuse(m1, m2, T, config, Timings())[1:])

    def on_compile(kernel: str):
        if not threads and ".registration." in kernel:
            threads.append(threading.Thread(target=work, name="octomerge-compile-ahead", daemon=True))
            threads[0].start()

    if not math.isclose(m1.resolution, m2.resolution, rel_tol=1e-9) or \
            (m1.capacity + m2.capacity) * BYTES_PER_ROW > budget:
        yield
        return
    try:
        with compile_listener(on_compile):
            yield
    finally:
        for t in threads:
            t.join()
