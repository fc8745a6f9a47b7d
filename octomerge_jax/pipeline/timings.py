"""Seconds per pipeline stage: ``Timings`` (a dict of stage name -> seconds) and its
``stage`` context manager; ``stage_listener`` lets an application watch the stages go by
(the command line's progress bars)."""

from __future__ import annotations

import contextlib
import contextvars
import time

import jax

__all__ = ["Timings", "stage_listener"]

_listener: contextvars.ContextVar = contextvars.ContextVar("octomerge_stage_listener", default=None)


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
        listener = _listener.get()
        if listener is not None:
            listener(name, None)
        t0 = time.perf_counter()
        try:
            yield _STAGE
        finally:
            dt = time.perf_counter() - t0
            self[name] = self.get(name, 0.0) + dt
            if listener is not None:
                listener(name, dt)


class Stage:
    """Handed out by ``Timings.stage``."""

    @staticmethod
    def ready(x):
        """``x`` after its arrays are computed (``jax.block_until_ready``)."""
        jax.block_until_ready(x)
        return x


_STAGE = Stage()


@contextlib.contextmanager
def stage_listener(callback):
    """While inside, every ``Timings.stage`` of this thread / task calls ``callback(name, None)``
    when it starts and ``callback(name, seconds)`` when it ends. Nothing is watched outside."""
    token = _listener.set(callback)
    try:
        yield
    finally:
        _listener.reset(token)
