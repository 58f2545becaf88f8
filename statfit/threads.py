"""Thread counts chosen for the problem, and subnormal floats flushed on every thread.

A fit of a head-sized mesh (≈10⁴ vertices, 100 modes) is a few hundred small kernels per second:
a second OpenMP thread saves little on a quiet machine and, when the other core is busy, makes
every kernel wait for a thread that is not running (8× slower was measured on a loaded 2-core
machine). So fits run on one thread below ``PARALLEL_WORK`` and on every available core above it;
``threads`` overrides (docs/benchmarks.md has the measurements behind the threshold).

Filtered gradients and Adam moments decay to subnormal floats, which CPUs process ~100× slower.
``torch.set_flush_denormal`` sets the flag on the calling thread only, and OpenMP worker threads
copy it when they are created, not later: :func:`flush_denormals_everywhere` must run before the
first parallel kernel (the CLI does it at start-up); :func:`workers_flush_denormals` checks.
"""
from __future__ import annotations

import os
from contextlib import contextmanager
from typing import Iterator

import torch

from statfit.errors import StatfitError

# Floats a fit streams per iteration (model basis: 3N·K) above which several threads pay off.
PARALLEL_WORK = 1 << 23
MAX_THREADS = 256
_limit: int | None = None  # set by limit_threads: a batch worker's share of the machine


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def choose_threads(work: int, threads: int | None = None) -> int:
    """Intra-op threads for a fit streaming ``work`` floats per iteration; ``threads`` (≥ 1)
    overrides the choice."""
    if threads is not None:
        if not 1 <= threads <= MAX_THREADS:
            raise StatfitError(f"--threads must be between 1 and {MAX_THREADS}, got {threads}")
        return threads
    return 1 if work < PARALLEL_WORK else min(available_cores(), _limit or MAX_THREADS)


def limit_threads(count: int | None) -> None:
    """Cap the threads :func:`choose_threads` picks in this process (``None``: no cap) — a batch
    worker's share of the cores, so W workers never run more than the machine's threads."""
    global _limit
    if count is not None and count < 1:
        raise StatfitError(f"thread limit must be at least 1, got {count}")
    _limit = count


@contextmanager
def intra_op_threads(count: int) -> Iterator[None]:
    """Run the block on ``count`` torch intra-op threads, restoring the previous count after."""
    previous = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def flush_denormals_everywhere() -> bool:
    """Flush subnormal floats to zero on this thread and on the worker threads created after this
    call (all of them, if no parallel kernel has run yet). False where the CPU cannot."""
    return torch.set_flush_denormal(True)


def workers_flush_denormals() -> bool:
    """Whether every current intra-op thread flushes subnormal results to zero (measured: a
    product whose exact value is subnormal, computed across all threads, must come out 0)."""
    tiny = torch.full(((1 << 16) * max(1, torch.get_num_threads()),), 1e-30, dtype=torch.float32)
    return bool(((tiny * 1e-10) == 0).all())
