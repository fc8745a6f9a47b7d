"""Run one function over many items as Dask tasks (``octomerge batch --workers/--scheduler``)."""

from __future__ import annotations

import time
from typing import Callable, Iterator, Sequence

from ..hostmem import child_env
from .cache import worker_env

__all__ = ["NoWorkersError", "SchedulerError", "map_on_dask"]


class SchedulerError(RuntimeError):
    """The Dask scheduler could not be reached (or a local cluster could not start)."""


class NoWorkersError(RuntimeError):
    """Every Dask worker was gone for longer than the timeout; the task was not run."""

    kind = "no_workers"


def map_on_dask(func: Callable, items: Sequence, *args, scheduler=None, workers: int = 0,
                key: Callable[[object], str], timeout_s: float = 60.0
                ) -> Iterator[tuple[object, object, Exception | None]]:
    """Submit ``func(item, *args)`` for every item as one impure Dask task named ``key(item)``
    and yield ``(item, result, None)`` as each finishes, or ``(item, None, error)`` for a task
    that failed (worker died, pickling failed, ...).

    ``scheduler``: a scheduler address (``tcp://host:8786``) or a ``distributed.Client`` (left
    open); else a local cluster of ``workers`` single-thread worker processes is started on
    free ports (its HTTP server too: no fixed 8787, only on 127.0.0.1; its workers keep XLA:CPU
    scratch memory as this process does: ``hostmem.child_env``) and closed when the iteration
    ends.

    ``timeout_s`` [s]: how long to wait for the scheduler to answer, and, once the cluster
    has no worker left, for one to come back: then every unfinished item is yielded with a
    ``NoWorkersError`` (never a hang). Raises ``SchedulerError`` if the scheduler cannot be
    reached, ``RuntimeError`` if ``distributed`` is not installed.
    """
    try:
        from distributed import Client, LocalCluster, wait
    except ImportError:
        raise RuntimeError('running on a Dask cluster needs dask.distributed: '
                           'pip install "dask[distributed]"') from None
    own_cluster = None
    try:
        if scheduler and not isinstance(scheduler, str):
            client, own_client = scheduler, False
        elif scheduler:
            client, own_client = Client(scheduler, timeout=timeout_s), True
        else:
            own_cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                       scheduler_port=0, dashboard_address="127.0.0.1:0",
                                       env={**child_env(), **worker_env()})
            client, own_client = Client(own_cluster, timeout=timeout_s), True
    except (OSError, TimeoutError) as err:
        if own_cluster is not None:
            own_cluster.close()
        what = f"the Dask scheduler {scheduler}" if scheduler else "a local Dask cluster"
        reason = (str(err).strip().splitlines() or [type(err).__name__])[0]
        raise SchedulerError(f"cannot reach {what} within {timeout_s:g} s: {reason}") from None
    try:
        futures = [client.submit(func, item, *args, key=key(item), pure=False) for item in items[:1]]
        if own_cluster is not None and worker_env():
            # the first task compiles the kernels into the shared cache; the rest, submitted when
            # it is done, load them instead of compiling the same programs side by side (no
            # waiting without workers: the loop below then fails the items after timeout_s)
            while futures and not futures[0].done() and client.nthreads():
                time.sleep(0.2)
        futures += [client.submit(func, item, *args, key=key(item), pure=False) for item in items[1:]]
        by_key = {f.key: item for f, item in zip(futures, items)}
        pending, alone_since = set(futures), None
        while pending:
            try:
                done, pending = wait(pending, timeout=min(1.0, timeout_s), return_when="FIRST_COMPLETED")
            except TimeoutError:
                done = set()
            for fut in done:
                item = by_key[fut.key]
                try:
                    result = fut.result()
                except Exception as err:  # worker died, pickling failed, ...
                    yield item, None, err
                else:
                    yield item, result, None
            if not pending or client.nthreads():
                alone_since = None
            elif alone_since is None:
                alone_since = time.monotonic()
            elif time.monotonic() - alone_since > timeout_s:
                for fut in pending:
                    fut.cancel()
                    yield by_key[fut.key], None, NoWorkersError(
                        f"no Dask worker for {timeout_s:g} s; not run")
                return
    finally:
        if own_client:
            client.close()
        if own_cluster is not None:
            own_cluster.close()
