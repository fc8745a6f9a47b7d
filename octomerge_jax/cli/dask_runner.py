"""Run one function over many items as Dask tasks (``octomerge batch --workers/--scheduler``)."""

from __future__ import annotations

from typing import Callable, Iterator, Sequence

from ..hostmem import child_env
from .cache import worker_env

__all__ = ["map_on_dask"]


def map_on_dask(func: Callable, items: Sequence, *args, scheduler=None, workers: int = 0,
                key: Callable[[object], str]) -> Iterator[tuple[object, object, Exception | None]]:
    """Submit ``func(item, *args)`` for every item as one impure Dask task named ``key(item)``
    and yield ``(item, result, None)`` as each finishes, or ``(item, None, error)`` for a task
    that failed (worker died, pickling failed, ...).

    ``scheduler``: a scheduler address (``tcp://host:8786``) or a ``distributed.Client`` (left
    open); else a local cluster of ``workers`` single-thread worker processes is started (its
    workers keep XLA:CPU scratch memory as this process does, ``hostmem.child_env``, and load
    compiled kernels from its compilation cache, ``cache.worker_env``) and closed when the
    iteration ends. Raises ``RuntimeError`` if ``distributed`` is not installed.
    """
    try:
        from distributed import Client, LocalCluster, as_completed, wait
    except ImportError:
        raise RuntimeError('running on a Dask cluster needs dask.distributed: '
                           'pip install "dask[distributed]"') from None
    own_cluster = None
    if scheduler and not isinstance(scheduler, str):
        client, own_client = scheduler, False
    elif scheduler:
        client, own_client = Client(scheduler), True
    else:
        own_cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                   dashboard_address=None, env={**child_env(), **worker_env()})
        client, own_client = Client(own_cluster), True
    try:
        futures = [client.submit(func, item, *args, key=key(item), pure=False) for item in items[:1]]
        pending = as_completed(futures)
        if own_cluster is not None and worker_env():
            # the first task compiles the kernels into the shared cache; the rest, submitted when
            # it is done, load them instead of compiling the same programs side by side
            wait(futures)
        futures += [client.submit(func, item, *args, key=key(item), pure=False) for item in items[1:]]
        pending.update(futures[1:])
        by_key = {f.key: item for f, item in zip(futures, items)}
        for fut in pending:
            item = by_key[fut.key]
            try:
                result = fut.result()
            except Exception as err:  # worker died, pickling failed, ...
                yield item, None, err
            else:
                yield item, result, None
    finally:
        if own_client:
            client.close()
        if own_cluster is not None:
            own_cluster.close()
