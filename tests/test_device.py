"""Which device a job runs on: ``auto`` follows the measured rule (statfit.core.device.AUTO_ON_GPU)."""
from __future__ import annotations

import subprocess
import sys

import pytest
import torch

import statfit.core.device as device_module
from statfit.core.device import resolve_device
from statfit.errors import StatfitError


@pytest.fixture
def a_gpu(monkeypatch):
    """A machine that reports a CUDA device (without making this process's CUDA state deterministic)."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(device_module, "same_seed_same_bytes", lambda: None)
    monkeypatch.setattr(device_module, "load_cuda_linear_algebra", lambda device: None)


def test_auto_sends_render_to_the_gpu_and_keeps_register_on_the_cpu(a_gpu):
    assert resolve_device("auto", "render").type == "cuda"
    assert resolve_device("auto", "register").type == "cpu"
    assert resolve_device("auto", "splat").type == "cuda"       # not measured: the GPU
    assert resolve_device("cuda", "register").type == "cuda"    # asked for by name: always


def test_auto_without_a_gpu_is_the_cpu(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto", "render").type == "cpu"
    with pytest.raises(StatfitError, match="no CUDA device"):
        resolve_device("cuda", "render")


def test_auto_on_a_gpu_makes_cuda_deterministic(monkeypatch):
    calls = []
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(device_module, "same_seed_same_bytes", lambda: calls.append(1))
    monkeypatch.setattr(device_module, "load_cuda_linear_algebra", lambda device: calls.append(device.type))
    resolve_device("auto", "render")
    assert calls == [1, "cuda"]


def test_an_unknown_device_is_refused():
    with pytest.raises(StatfitError, match="unknown device"):
        resolve_device("tpu")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_threads_making_their_first_cuda_solve_at_once_do_not_fail():
    """torch loads its CUDA linear-algebra library at the first solve, and two threads doing that at
    once fail (an H200, session 43); a fresh process that chose its device first runs 8 at once."""
    script = """
import threading, torch
from statfit.core.device import resolve_device
device = resolve_device("cuda")
start, errors = threading.Barrier(8), []
def solve():
    start.wait()
    try:
        torch.linalg.solve(torch.eye(3, device=device) * 2, torch.ones(3, device=device))
    except RuntimeError as error:
        errors.append(str(error))
threads = [threading.Thread(target=solve) for _ in range(8)]
for thread in threads: thread.start()
for thread in threads: thread.join()
assert not errors, errors[0]
"""
    ran = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert ran.returncode == 0, ran.stderr[-2000:]
