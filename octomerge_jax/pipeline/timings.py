"""Seconds per pipeline stage: ``Timings`` (a dict of stage name -> seconds) and its
``stage`` context manager."""

from __future__ import annotations

import contextlib
import time

import jax

__all__ = ["Timings"]


class Timings(dict):
    """Seconds [s] per stage name; a stage timed twice adds up. ``MergeReport.timings`` is
    a plain ``dict(timings)``.

    ::

        with timings.stage("icp") as stage:
            r = stage.ready(icp(q2, q1, T_1_2_init))
    """

    @contextlib.contextmanager
    def stage(self, name: str):
        """Time the block under ``name``; the yielded ``Stage``'s ``ready(x)`` waits for the
        arrays of ``x`` (``jax.block_until_ready``) so that the block's device work counts."""
        t0 = time.perf_counter()
        try:
            yield _STAGE
        finally:
            self[name] = self.get(name, 0.0) + time.perf_counter() - t0


class Stage:
    """Handed out by ``Timings.stage``."""

    @staticmethod
    def ready(x):
        """``x`` after its arrays are computed (``jax.block_until_ready``)."""
        jax.block_until_ready(x)
        return x


_STAGE = Stage()
