"""Run independent tasks serially or on Dask (``dask.distributed``), results in input order.

``scheduler="serial"`` runs a plain loop; ``"local"`` (default) starts a local cluster of
``workers`` single-threaded processes; any other value is the address of a running
scheduler (``tcp://host:8786``; start one with ``dask scheduler`` and workers with
``dask worker tcp://host:8786`` on each machine, all with derender installed and the data
on a shared path). Tasks must be deterministic functions of their arguments, so every
scheduler gives the same results.
"""

from __future__ import annotations

from contextlib import contextmanager
from typing import Any, Callable, Iterator, Sequence

__all__ = [
    "run_tasks",
    "one_blas_thread",
]


@contextmanager
def one_blas_thread() -> Iterator[None]:
    """BLAS (OpenBLAS) on one thread inside the block, for small dense algebra in a busy process.

    OpenBLAS splits a 256 x 256 solve over its threads; when the other core is busy (decoder,
    kernel or writer threads of a merge, or another process) its worker waits to be scheduled
    and the solve takes 70-150 ms instead of 0.4 ms (measured here, numpy 2 with OpenBLAS
    0.3.31, 2 cores: bimodal 0.4 / 80 ms per solve under load, 0.4 ms with one thread). Costs
    ~1-2 ms per entry (threadpoolctl; its import ~15 ms once)."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        yield


def _single_blas_thread(fn: Callable[..., Any], *args: Any) -> Any:
    """Run ``fn`` with one BLAS/OpenMP thread, as Dask workers do, so that floating-point
    reductions are identical whether a task runs serially or on a worker."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):
        return fn(*args)


def run_tasks(fn: Callable[..., Any], arg_tuples: Sequence[tuple], scheduler: str | None = "local", workers: int = 2,
              progress: Callable[[int, int], None] | None = None) -> list[Any]:
    """``[fn(*args) for args in arg_tuples]``, possibly in parallel; results in input order."""
    n = len(arg_tuples)
    if scheduler == "serial" or n == 0:
        out = []
        for i, args in enumerate(arg_tuples):
            out.append(_single_blas_thread(fn, *args))
            if progress:
                progress(i + 1, n)
        return out
    from dask.distributed import Client, LocalCluster, as_completed

    cluster = None
    if scheduler in (None, "", "local"):
        cluster = LocalCluster(n_workers=max(1, int(workers)), threads_per_worker=1, processes=True,
                               dashboard_address=None)
        client = Client(cluster)
    else:
        client = Client(scheduler)
    try:
        futures = [client.submit(_single_blas_thread, fn, *args, pure=False) for args in arg_tuples]
        index = {f.key: i for i, f in enumerate(futures)}
        results: list[Any] = [None] * n
        for done, fut in enumerate(as_completed(futures), 1):
            results[index[fut.key]] = fut.result()
            if progress:
                progress(done, n)
        return results
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
