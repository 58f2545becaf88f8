"""Where a batch's fits run: a process pool on this machine (the standard library's) or a Dask
cluster, behind one small interface the batch loop drives.

Each engine runs a picklable ``work(job, source)`` and hands back futures. When a worker dies the
engine raises :class:`WorkerLost` from the future's ``result()``; :meth:`Engine.replace` kills
the workers running timed-out futures and returns the other futures it had to stop too.
"""
from __future__ import annotations

import concurrent.futures as cf
import logging
import multiprocessing
import multiprocessing.connection
import os
import signal
import sys
import threading
import time
from typing import Any, Callable, Iterable, Protocol

from statfit.batch.fits import prepare_worker
from statfit.errors import StatfitError


class WorkerLost(Exception):
    """The process running a fit died (a crash, a kill, out of memory)."""


class Engine(Protocol):
    workers: int  # fits it runs at once
    capacity: int  # fits it holds at once: running, and one queued behind each so no worker waits

    def submit(self, work: Callable, *args: Any) -> Any: ...
    def wait(self, futures: Iterable[Any], timeout: float) -> set[Any]: ...
    def result(self, future: Any) -> Any: ...
    def replace(self, hung: list[Any], running: list[Any]) -> list[Any]: ...
    def close(self) -> None: ...


def _exit_with_parent() -> None:
    """End this worker as soon as the batch process is gone (killed with SIGKILL, say): a pool
    worker holds its own queue's write end, so it would otherwise wait for work forever."""
    multiprocessing.connection.wait([multiprocessing.parent_process().sentinel])
    os._exit(1)


def _pid_after(seconds: float) -> int:
    """This worker's process id, after ``seconds`` (so that one worker cannot answer every call)."""
    time.sleep(seconds)
    return os.getpid()


def _start_worker(max_threads: int | None) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the batch's to handle, not each worker's
    threading.Thread(target=_exit_with_parent, daemon=True).start()
    prepare_worker(max_threads)


WORKER_START_SECONDS = 300   # the longest a new pool waits for all its workers to answer


def _worker_context() -> multiprocessing.context.BaseContext:
    """How the local pool starts its workers: on Linux, forked from a fork server (a fresh
    interpreter with no threads, started once per batch process, that has imported the fitting
    code): a worker then starts in milliseconds, not the ~3 s of CPU a fresh interpreter takes to
    import torch and statfit, and a pool replaced after a hang starts as fast (docs/benchmarks.md
    §7). Elsewhere (macOS, where a fork after system frameworks have loaded is unsafe and Python's
    own default is spawn; Windows) each worker is a fresh interpreter. Either way no worker
    inherits a thread."""
    if not sys.platform.startswith("linux"):
        return multiprocessing.get_context("spawn")
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload([prepare_worker.__module__])
    return context


class LocalPool:
    """``workers`` processes on this machine (:func:`_worker_context`: forked from a thread-free
    fork server, else spawned), each set up once; replaced as a whole when one hangs or dies (the
    standard pool cannot replace one). The fork server starts with the first pool and keeps this
    process's environment as it was then. A pool's workers start at its first fit, which waits
    until all of them have: a fit's timeout then counts the fit, not a worker's start, which can
    take seconds on a loaded machine."""

    def __init__(self, workers: int, max_threads: int | None = None):
        if workers < 1:
            raise StatfitError(f"--workers must be at least 1, got {workers}")
        self.workers = workers
        self.capacity = 2 * workers
        self._max_threads = max_threads
        self._pool = self._new_pool()
        self._started = False

    def _new_pool(self) -> cf.ProcessPoolExecutor:
        return cf.ProcessPoolExecutor(self.workers, mp_context=_worker_context(),
                                      initializer=_start_worker, initargs=(self._max_threads,))

    def _start_workers(self) -> None:
        """Wait (at most WORKER_START_SECONDS) until every worker of the pool has answered a call."""
        answered: set[int] = set()
        deadline = time.monotonic() + WORKER_START_SECONDS
        try:
            while len(answered) < self.workers and time.monotonic() < deadline:
                calls = [self._pool.submit(_pid_after, 0.05) for _ in range(self.workers)]
                answered |= {f.result(timeout=max(deadline - time.monotonic(), 0.0)) for f in calls}
        except cf.TimeoutError:         # a worker hangs starting: its fits will time out
            pass
        except cf.process.BrokenProcessPool:   # a worker died starting: a new pool, whose fits will say so
            self._restart()
        self._started = True

    def submit(self, work: Callable, *args: Any) -> cf.Future:
        if not self._started:
            self._start_workers()
        try:
            return self._pool.submit(work, *args)
        except cf.process.BrokenProcessPool:  # a worker died since the last submit
            self._restart()
            self._start_workers()
            return self._pool.submit(work, *args)

    def wait(self, futures: Iterable[cf.Future], timeout: float) -> set[cf.Future]:
        return cf.wait(list(futures), timeout=timeout, return_when=cf.FIRST_COMPLETED).done

    def result(self, future: cf.Future) -> Any:
        try:
            return future.result()
        except cf.process.BrokenProcessPool:
            raise WorkerLost from None

    def replace(self, hung: list[cf.Future], running: list[cf.Future]) -> list[cf.Future]:
        self._restart()
        return [f for f in running if f not in hung]

    def _restart(self) -> None:
        self._kill()
        self._pool = self._new_pool()
        self._started = False

    def _kill(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)
        for process in multiprocessing.active_children():  # the pool's workers, which shutdown leaves running
            process.kill()
        for process in multiprocessing.active_children():
            process.join()

    def close(self) -> None:
        self._kill()


class DaskPool:
    """A Dask distributed cluster: an existing scheduler at ``address`` (workers started with
    ``dask worker ADDRESS --nthreads 1``, e.g. by dask-jobqueue), or ``"local"``: a LocalCluster of
    ``workers`` single-threaded processes on this machine. Dask retries a fit whose worker died
    (``distributed.scheduler.allowed-failures`` times) before reporting it lost."""

    def __init__(self, address: str, workers: int, max_threads: int | None = None):
        try:
            import dask
            from distributed import Client, LocalCluster
        except ImportError:
            raise StatfitError('Dask is not installed; pip install "statfit[dask]"') from None
        self._cluster = None
        try:
            if address == "local":
                # Dask starts workers with OMP/MKL/OPENBLAS_NUM_THREADS=1, which changes which BLAS
                # kernels run (and so the last bits of a fit), and with MALLOC_TRIM_THRESHOLD_=65536,
                # which makes a fit up to 2× slower (statfit.batch.fits.keep_freed_memory) and which it
                # writes into this process's own environment too, for every process started later.
                # statfit picks its threads itself, so its workers keep this process's environment,
                # as the local pool's do.
                with dask.config.set({"distributed.nanny.pre-spawn-environ": {}}):
                    self._cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                                 dashboard_address=None, silence_logs=logging.ERROR)
                self._client = Client(self._cluster)
            else:
                self._client = Client(address, timeout="20s")
        except (OSError, TimeoutError) as exc:
            raise StatfitError(f"cannot reach the Dask scheduler at {address}: {exc}") from None
        threads = sum(self._client.nthreads().values())
        if threads == 0:
            self.close()
            raise StatfitError(f"the Dask scheduler at {address} has no workers")
        self.workers = threads
        self.capacity = 2 * threads
        self._client.run(prepare_worker, max_threads)

    def submit(self, work: Callable, *args: Any) -> Any:
        return self._client.submit(work, *args, pure=False)

    def wait(self, futures: Iterable[Any], timeout: float) -> set[Any]:
        from distributed import wait
        from distributed.client import FutureCancelledError
        futures = list(futures)
        try:
            return set(wait(futures, timeout=timeout, return_when="FIRST_COMPLETED").done)
        except TimeoutError:
            return set()
        except FutureCancelledError:
            return {f for f in futures if f.done()}

    def result(self, future: Any) -> Any:
        from distributed import KilledWorker
        try:
            return future.result()
        except KilledWorker:
            raise WorkerLost from None

    def replace(self, hung: list[Any], running: list[Any]) -> list[Any]:
        keys = {f.key for f in hung}
        workers = [w for w, tasks in self._client.processing().items() if keys & set(tasks)]
        for future in hung:
            future.cancel()
        if workers:
            self._client.restart_workers(workers, raise_for_error=False)
        return []

    def close(self) -> None:
        self._client.close()
        if self._cluster is not None:
            self._cluster.close()
