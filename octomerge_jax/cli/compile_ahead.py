"""Compiling a merge's later kernels while its registration compiles: a cold command's compile
time spread over both cores. docs/design.md, "Compile cache and warm-up"."""

from __future__ import annotations

import contextlib
import math
import threading

import jax
import numpy as np

from ..budget import current_budget, memory_budget
from ..kernel_store import compile_listener
from ..map import OccupancyMap
from ..fusion import fuse_plan_shapes, precompile_fuse
from ..pipeline import MergeConfig, Timings, candidate_listener, fuse_in_frame_1, transform_to_frame_1
from ..pipeline.refine import precompile_polish

__all__ = ["compile_ahead", "BYTES_PER_ROW", "SHARE_OF_BUDGET"]

SHARE_OF_BUDGET = 0.25
"""The share of the memory budget (``budget.current_budget``) the work ahead may take; a pair
that needs more is not worked ahead."""

BYTES_PER_ROW = 512
"""The work ahead's peak memory per leaf row of the two maps' capacities [bytes], compiling
included (measured: docs/design.md, "Compiling the merge's later kernels during the registration")."""


def _precompile_fuse(m1: OccupancyMap, m2_in_1: OccupancyMap, plan_shapes) -> None:
    with contextlib.suppress(Exception):  # work ahead: the real merge reports its own errors
        precompile_fuse(m1, m2_in_1, plan_shapes)


@contextlib.contextmanager
def compile_ahead(m1: OccupancyMap, m2: OccupancyMap, T_1_2, config: MergeConfig):
    """Within the block (one ``merge`` of ``m1`` and ``m2`` with ``config``), the first time the
    registration compiles a stored kernel afresh (``kernel_store.compile_listener``: only with
    the kernel store open and the program in neither the process nor the store), a second
    thread runs the rest of the merge (``transform_to_frame_1``, then ``fuse_in_frame_1`` while a
    third thread compiles the fusion's second program, ``fusion.precompile_fuse``) from
    ``T_1_2`` ((4, 4); the guess; ``None``: once ``register_global`` has published its best
    screened pose, ``pipeline.candidate_listener``) and drops its result; then it compiles (without running)
    the GICP polish's program for that pose (``pipeline.refine.precompile_polish``; run there, it
    hung: ``docs/design.md``, "Compiling the merge's later kernels during the registration").
    Its programs' shapes are bucketed, so they are the ones the real merge needs unless the
    final transform changes a bucket; the real merge then loads them, or waits for the thread
    compiling them, instead of compiling them after the registration. A warm merge starts no
    thread. A pair whose work ahead would need more than ``SHARE_OF_BUDGET`` of the memory
    budget (``BYTES_PER_ROW`` per row of both maps' capacities), and maps of two resolutions
    (resampled by ``merge`` first), are not worked ahead; work ahead that fails, or allocates
    over that share, is dropped silently (the real merge reports its own errors). The block's
    exit waits for the thread."""
    threads: list[threading.Thread] = []
    budget = int(current_budget() * SHARE_OF_BUDGET)
    state = {"compiling": False, "T": None if T_1_2 is None else np.asarray(T_1_2, np.float64)}

    def work(T):
        with memory_budget(budget), contextlib.suppress(Exception):
            m2_in_1 = transform_to_frame_1(m2, T, config, Timings())
            # the fusion's second program compiles beside its first, on the core the registration frees; the
            # first one's trace (its shapes, which the second takes) once, here, before the fuse compiles from it
            shapes = fuse_plan_shapes(m1, m2_in_1)
            beside = threading.Thread(target=_precompile_fuse, args=(m1, m2_in_1, shapes),
                                      name="octomerge-compile-beside", daemon=True)
            beside.start()
            try:
                jax.block_until_ready(fuse_in_frame_1(m1, m2_in_1, config, Timings()))
            finally:
                beside.join()
            precompile_polish(m1, m2, T, config)

    def start():
        if not threads and state["compiling"] and state["T"] is not None:
            threads.append(threading.Thread(target=work, args=(state["T"],), name="octomerge-compile-ahead",
                                            daemon=True))
            threads[0].start()

    def on_compile(kernel: str):
        if ".registration." in kernel:
            state["compiling"] = True
            start()

    def on_candidate(T):
        if state["T"] is None:
            state["T"] = T
            start()

    if not math.isclose(m1.resolution, m2.resolution, rel_tol=1e-9) or \
            (m1.capacity + m2.capacity) * BYTES_PER_ROW > budget:
        yield
        return
    try:
        with compile_listener(on_compile), candidate_listener(on_candidate):
            yield
    finally:
        for t in threads:
            t.join()
