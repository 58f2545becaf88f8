"""Thread counts chosen from the problem size and the machine's load; subnormals flushed on every
worker thread."""
from __future__ import annotations

import subprocess
import sys

import pytest
import torch

from statfit.errors import StatfitError
import statfit.core.threads as threads_module
from statfit.core.threads import PARALLEL_WORK, available_cores, choose_threads, idle_cores, intra_op_threads


def test_small_fits_run_on_one_thread_large_ones_on_every_idle_core(monkeypatch):
    monkeypatch.setattr(threads_module, "idle_cores", lambda: float(available_cores()))
    assert choose_threads(11_248 * 3 * 100) == 1  # the ICT head
    assert choose_threads(PARALLEL_WORK) == available_cores()
    assert choose_threads(10, threads=3) == 3


@pytest.mark.parametrize("idle, expected", [(4.0, 4), (3.8, 4), (3.7, 3), (1.0, 1), (0.0, 1), (None, 4)])
def test_large_fits_leave_busy_cores_alone(monkeypatch, idle, expected):
    """A core counts as free at ≥ 75% idle; no measurement (not Linux): every core."""
    monkeypatch.setattr(threads_module, "available_cores", lambda: 4)
    monkeypatch.setattr(threads_module, "idle_cores", lambda: idle)
    assert choose_threads(PARALLEL_WORK) == expected
    assert choose_threads(PARALLEL_WORK, threads=4) == 4   # asked for: never second-guessed


def test_a_busy_process_is_seen_as_a_busy_core():
    if idle_cores() is None:
        pytest.skip("no per-CPU times on this system")
    spinner = subprocess.Popen([sys.executable, "-c", "print('ready', flush=True)\nwhile True: pass"],
                               stdout=subprocess.PIPE, text=True)
    try:
        assert spinner.stdout.readline().strip() == "ready"
        idle = idle_cores(0.3)
    finally:
        spinner.kill()
        spinner.wait()
    assert 0 <= idle <= available_cores() - 0.5


@pytest.mark.parametrize("bad", [0, -1, 10_000])
def test_thread_count_out_of_range_is_refused(bad):
    with pytest.raises(StatfitError, match="--threads"):
        choose_threads(10, threads=bad)


def test_thread_count_is_restored():
    before = torch.get_num_threads()
    with intra_op_threads(1):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == before


PROBE = """
import torch
from statfit.core.threads import workers_flush_denormals
{setup}
torch.set_num_threads(2)
print(workers_flush_denormals())
"""


@pytest.mark.parametrize("setup, expected", [
    # The CLI's start-up: the flag is set before the first parallel kernel, so the workers inherit it.
    ("from statfit.core.threads import flush_denormals_everywhere; flush_denormals_everywhere()", "True"),
    # torch's own behaviour, which is why the CLI does it first: set later, it reaches this thread only.
    ("torch.set_num_threads(2); torch.ones(1 << 18).mul(2); torch.set_flush_denormal(True)", "False"),
])
def test_subnormals_are_flushed_on_every_worker_thread(setup, expected):
    if not torch.set_flush_denormal(False):
        pytest.skip("this CPU cannot flush subnormals")
    out = subprocess.run([sys.executable, "-c", PROBE.format(setup=setup)], capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == expected


def test_the_cli_flushes_before_any_parallel_kernel():
    """A command flushes once its options are parsed, before its work (here: a scan it then refuses);
    ``--help`` imports no torch (tests/test_cli.py), so it is not where the flag is set."""
    code = ("import sys; from statfit_cli import main as m;"
            "sys.argv=['statfit', 'register', 'no such scan.ply'];\ntry: m.main()\nexcept SystemExit: pass\n"
            "import torch; from statfit.core.threads import workers_flush_denormals\n"
            "torch.set_num_threads(2); print(workers_flush_denormals(), file=sys.stderr)")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.stderr.strip().splitlines()[-1] == "True"


def test_work_mapped_on_threads_comes_back_in_order_and_the_first_failure_is_raised():
    import threading
    import time

    from statfit.core.threads import map_in_threads

    seen = set()

    def square(item: int) -> int:
        seen.add(threading.get_ident())
        time.sleep(0.02)         # busy: the next items go to threads of their own, not to an idle one
        return item * item

    assert map_in_threads(square, list(range(8)), 3) == [item * item for item in range(8)]
    assert len(seen) > 1                                   # it did run on threads of its own
    assert map_in_threads(square, [], 3) == []

    def fail(item: int) -> int:
        if item >= 2:
            raise ValueError(f"item {item}")
        return item

    with pytest.raises(ValueError, match="item 2"):
        map_in_threads(fail, [0, 1, 2, 3], 4)


def test_host_tasks_take_the_cores_left_by_the_batch_share_and_the_intra_op_threads(monkeypatch):
    from statfit.core.threads import limit_threads, task_threads

    monkeypatch.setattr(threads_module, "available_cores", lambda: 8)
    with intra_op_threads(1):
        assert task_threads(3) == 3 and task_threads(20) == 8
        limit_threads(2)
        try:
            assert task_threads(3) == 2
        finally:
            limit_threads(None)
    with intra_op_threads(4):
        assert task_threads(3) == 2
    with intra_op_threads(1):
        assert task_threads(3, cap=1) == 1 and task_threads(3, cap=2) == 2
        monkeypatch.setattr(threads_module, "available_cores", lambda: 1)
        assert task_threads(3) == 1
