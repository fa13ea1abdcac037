"""Where a batch's solver calls run: in this process, or as chunks on Dask workers.

A batch of parameter sets is split into chunks of at most ``max_batch`` members, the same chunks
whatever runs them, so the results do not depend on the executor or on the number of workers.
``Executor.map(fn, chunks)`` returns [fn(chunk) for chunk in chunks] in order:

* ``LocalExecutor``: one chunk after another in this process (the default; needs no Dask);
* ``DaskExecutor``: the chunks as tasks of a Dask distributed cluster, a LocalCluster of ``workers``
  processes on this machine or the scheduler at ``scheduler`` (``tcp://host:8786``; on a machine with
  several GPUs, start the workers with dask-cuda's ``dask-cuda-worker`` and point ``scheduler`` at
  them). ``fn`` is sent to the workers once per call (scattered), the chunks are gathered in order, and
  a progress bar counts finished chunks. When a worker dies, the scheduler runs its chunks again on
  another (a chunk is retried until it has killed ``distributed.scheduler.allowed-failures`` workers);
  a chunk whose function raises is retried ``retries`` times and then raises here.

Dask is an optional extra (``pip install torchslide[dask]``).
"""
from __future__ import annotations

import os
from typing import Callable, Sequence

EXECUTORS = ("local", "dask")


class LocalExecutor:
    """The chunks one after another in this process."""

    workers = 1

    def map(self, fn: Callable, chunks: Sequence, progress: bool = False, desc: str = "chunks") -> list:
        return [fn(c) for c in chunks]

    def close(self) -> None:
        pass


def _call(fn, chunk):
    return fn(chunk)


class DaskExecutor:
    """The chunks as tasks of a Dask distributed cluster (module doc).

    scheduler: address of a running scheduler; else a LocalCluster of ``workers`` processes (default:
    the CPU count), torch and the fused step limited to ``threads_per_worker`` threads per worker."""

    def __init__(self, scheduler: str | None = None, workers: int | None = None, threads_per_worker: int = 1,
                 retries: int = 1):
        try:
            from distributed import Client, LocalCluster
        except ImportError:
            raise RuntimeError("executor \"dask\" needs Dask distributed: pip install torchslide[dask]") from None
        self.retries = retries
        self._cluster = None
        if scheduler:
            self.client = Client(scheduler)
        else:
            n = int(workers or os.cpu_count() or 1)
            env = {k: str(threads_per_worker) for k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")}
            self._cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None,
                                         env=env)
            self.client = Client(self._cluster)

    @property
    def workers(self) -> int:
        return max(1, len(self.client.scheduler_info().get("workers", {})))

    def map(self, fn: Callable, chunks: Sequence, progress: bool = False, desc: str = "chunks") -> list:
        from distributed import as_completed

        chunks = list(chunks)
        if not chunks:
            return []
        f = self.client.scatter(fn, broadcast=True, hash=False)
        futures = self.client.map(_call, [f] * len(chunks), chunks, pure=False, retries=self.retries)
        if progress:
            from tqdm.auto import tqdm

            with tqdm(total=len(futures), desc=desc, unit="chunk") as bar:
                for _ in as_completed(futures):
                    bar.update(1)
        return self.client.gather(futures)

    def close(self) -> None:
        self.client.close()
        if self._cluster is not None:
            self._cluster.close()


def make_executor(kind: str = "local", scheduler: str | None = None, workers: int | None = None):
    """The executor of ``kind`` ("local" | "dask"; module doc)."""
    if kind == "local":
        return LocalExecutor()
    if kind == "dask":
        return DaskExecutor(scheduler=scheduler, workers=workers)
    raise ValueError(f"executor must be one of {EXECUTORS}, got {kind!r}")
