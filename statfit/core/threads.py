"""Thread counts chosen for the problem, and subnormal floats flushed on every thread.

A fit of a head-sized mesh (≈10⁴ vertices, 100 modes) is a few hundred small kernels per second:
a second OpenMP thread saves little on a quiet machine and, when the other core is busy, makes
every kernel wait for a thread that is not running (8× slower was measured on a loaded 2-core
machine). So fits run on one thread below ``PARALLEL_WORK``; above it, on the available cores that
are idle when the fit starts (:func:`idle_cores`: beside one spinning process, a 768² body render
took 6× its quiet time on two threads, 1.2× on the one chosen). ``threads`` overrides
(docs/benchmarks.md has the measurements behind the threshold and the load rule).

Filtered gradients and Adam moments decay to subnormal floats, which CPUs process ~100× slower.
``torch.set_flush_denormal`` sets the flag on the calling thread only, and OpenMP worker threads
copy it when they are created, not later: :func:`flush_denormals_everywhere` must run before the
first parallel kernel (the CLI does it before each command's work); :func:`workers_flush_denormals` checks.
"""
from __future__ import annotations

import os
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import Callable, Iterator, Sequence, TypeVar

import torch

from statfit.errors import StatfitError

# Floats a fit streams per iteration (model basis: 3N·K) above which several threads pay off.
PARALLEL_WORK = 1 << 23
MAX_THREADS = 256
# A core counts as free when at least this share of it was idle over IDLE_WINDOW seconds.
FREE_CORE = 0.75
IDLE_WINDOW = 0.1
_limit: int | None = None  # set by limit_threads: a batch worker's share of the machine
Item = TypeVar("Item")
Result = TypeVar("Result")


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def usable_cores() -> int:
    """The cores this process may use: its CPU affinity, capped by a batch worker's share
    (:func:`limit_threads`)."""
    return min(available_cores(), _limit or MAX_THREADS)


def idle_cores(window: float = IDLE_WINDOW) -> float | None:
    """How many of this process's cores (its CPU affinity) sat idle over the next ``window``
    seconds, from the kernel's per-CPU time counters (``/proc/stat``: idle and I/O wait over all
    time); None where there are none (not Linux). The caller sleeps meanwhile, so it is the rest
    of the machine's load."""
    try:
        cpus = {f"cpu{index}" for index in os.sched_getaffinity(0)}
        before = _cpu_times(cpus)
        time.sleep(window)
        after = _cpu_times(cpus)
    except (AttributeError, OSError, ValueError):
        return None
    idle = 0.0
    for cpu, (idle_after, total_after) in after.items():
        idle_before, total_before = before.get(cpu, (idle_after, total_after))
        elapsed = total_after - total_before
        idle += (idle_after - idle_before) / elapsed if elapsed > 0 else 1.0
    return idle


def _cpu_times(cpus: set[str]) -> dict[str, tuple[int, int]]:
    """(idle, total) clock ticks so far of each of ``cpus`` ("cpu0", ...), from /proc/stat."""
    times = {}
    with open("/proc/stat") as stat:
        for line in stat:
            name, *fields = line.split()
            if name in cpus:
                ticks = [int(field) for field in fields[:8]]   # user nice system idle iowait irq softirq steal
                times[name] = (ticks[3] + ticks[4], sum(ticks))
    if not times:
        raise ValueError("no per-CPU times")
    return times


def choose_threads(work: int, threads: int | None = None) -> int:
    """Intra-op threads for a fit streaming ``work`` floats per iteration: 1 below PARALLEL_WORK,
    else the available cores that are free now (:func:`idle_cores`, at least 1); ``threads`` (≥ 1)
    overrides the choice."""
    if threads is not None:
        if not 1 <= threads <= MAX_THREADS:
            raise StatfitError(f"--threads must be between 1 and {MAX_THREADS}, got {threads}")
        return threads
    cores = usable_cores()
    if work < PARALLEL_WORK or cores == 1:
        return 1
    idle = idle_cores()
    return cores if idle is None else max(1, min(cores, int(idle + 1 - FREE_CORE)))


def limit_threads(count: int | None) -> None:
    """Cap the threads :func:`choose_threads` picks in this process (``None``: no cap) — a batch
    worker's share of the cores, so W workers never run more than the machine's threads."""
    global _limit
    if count is not None and count < 1:
        raise StatfitError(f"thread limit must be at least 1, got {count}")
    _limit = count


def task_threads(tasks: int, cap: int | None = None) -> int:
    """Threads for ``tasks`` independent pieces of host work (each on this process's intra-op
    threads): as many as the tasks, at most the cores this process may use (a batch worker's share,
    :func:`limit_threads`; ``cap``: the threads a caller asked for, e.g. ``--threads``) over the
    intra-op threads. No load test: such threads never wait for each other, so a busy core only
    shares its time."""
    cores = min(usable_cores(), cap or MAX_THREADS)
    return max(1, min(tasks, cores // max(1, torch.get_num_threads())))


def map_in_threads(work: Callable[[Item], Result], items: Sequence[Item], threads: int) -> list[Result]:
    """``[work(item) for item in items]`` on up to ``threads`` threads, in order: the same values to
    the bit (a thread inherits its creator's floating-point state, subnormals flushed or not, and
    torch's thread count is the process's); the first failure in order is raised. NumPy, SciPy and
    torch release the GIL inside their kernels, which is where such work spends its time."""
    if threads <= 1 or len(items) <= 1:
        return [work(item) for item in items]
    with ThreadPoolExecutor(min(threads, len(items))) as pool:
        futures = [pool.submit(work, item) for item in items]
        return [future.result() for future in futures]


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
