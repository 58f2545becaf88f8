"""Thread counts chosen from the problem size; subnormals flushed on every worker thread."""
from __future__ import annotations

import subprocess
import sys

import pytest
import torch

from statfit.errors import StatfitError
from statfit.threads import PARALLEL_WORK, available_cores, choose_threads, intra_op_threads


def test_small_fits_run_on_one_thread_large_ones_on_every_core():
    assert choose_threads(11_248 * 3 * 100) == 1  # the ICT head
    assert choose_threads(PARALLEL_WORK) == available_cores()
    assert choose_threads(10, threads=3) == 3


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
from statfit.threads import workers_flush_denormals
{setup}
torch.set_num_threads(2)
print(workers_flush_denormals())
"""


@pytest.mark.parametrize("setup, expected", [
    # The CLI's start-up: the flag is set before the first parallel kernel, so the workers inherit it.
    ("from statfit.threads import flush_denormals_everywhere; flush_denormals_everywhere()", "True"),
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
    code = ("import sys, torch; from statfit_cli import main as m; from statfit.threads import workers_flush_denormals;"
            "sys.argv=['statfit', '--help'];\ntry: m.main()\nexcept SystemExit: pass\n"
            "torch.set_num_threads(2); print(workers_flush_denormals(), file=sys.stderr)")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.stderr.strip().splitlines()[-1] == "True"
