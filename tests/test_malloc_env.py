"""A Dask-style fixed malloc threshold neither leaks from a local cluster nor slows a batch worker."""
import os
import subprocess
import sys

import pytest


def test_a_worker_undoes_a_fixed_malloc_threshold():
    """In a process started with MALLOC_TRIM_THRESHOLD_ (as Dask starts its workers), the worker set-up
    restores large thresholds: glibc then keeps a freed 8 MiB block mapped, so allocating it again
    costs no new page faults (counted by the kernel: minor faults)."""
    code = """
import resource, sys, torch
from statfit.batch.fits import prepare_worker, keep_freed_memory
if sys.argv[1] == "prepare":
    prepare_worker(1)
def faults(repeats=50):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(repeats):
        torch.ones(2 << 20).sum()          # 8 MiB allocated, touched, freed
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
faults(2)
print(faults())
"""
    if not sys.platform.startswith("linux"):
        pytest.skip("glibc's malloc only")
    env = os.environ | {"MALLOC_TRIM_THRESHOLD_": "65536"}
    counts = {mode: int(subprocess.run([sys.executable, "-c", code, mode], env=env, capture_output=True, text=True,
                                       check=True).stdout) for mode in ("plain", "prepare")}
    # each fresh 8 MiB block is 2048 pages: 50 of them fault ~100k times; kept blocks fault once (measured 6k)
    assert counts["plain"] > 50 * 1000, counts
    assert counts["prepare"] < counts["plain"] / 10, counts


def test_a_local_dask_cluster_leaves_this_process_environment_alone(tmp_path):
    pytest.importorskip("distributed")
    code = """
import os
from statfit.batch.engines import DaskPool
before = dict(os.environ)
pool = DaskPool("local", 1)
pool.close()
print(sorted(k for k in os.environ if k.startswith("MALLOC_") and before.get(k) != os.environ[k]))
"""
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True, cwd=tmp_path)
    assert out.stdout.strip().splitlines()[-1] == "[]", out.stdout
