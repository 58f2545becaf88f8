"""Which torch device a job runs on: one rule for every job and command."""
from __future__ import annotations

import os
import threading

import torch

from statfit.errors import StatfitError

# Names the default device: ``STATFIT_DEVICE=cuda pytest`` runs the whole suite's fits on the GPU.
DEVICE_ENV = "STATFIT_DEVICE"
# "0" lets CUDA reduce in any order (atomics): faster, but the same seed no longer gives the same bytes.
DETERMINISTIC_ENV = "STATFIT_DETERMINISTIC"


# Where ``auto`` runs each job when a GPU is there: where it was measured faster (2026-11-26, an
# NVIDIA H200, ICT, docs/benchmarks.md §12). register's default fit took 3.75 s on the GPU, no faster
# than one CPU core (2.6–4.2 s; its loop waits on kernel launches, its set-up runs on the host): the
# CPU. render's took 21.3 s against ~30 s: the GPU (4.6 s on an H100 since session 23, captured, against
# 25 s at 512² on one CPU core since the fit's stages reuse their visibility, docs/benchmarks.md §12;
# register's 3.35-4.3 s there). Session 29 (an H200, the same process, alternating): register's fit 4.4-5.0 s on
# the card against 5.7-6.1 s on one core of its host, whose pose search is 3.1 s of it either way; the
# whole command, with CUDA's start, is not measured yet (benchmarks/gpu.py now does): still the CPU.
# Jobs not named (splat, inpaint; not measured on a GPU yet) go to the GPU.
AUTO_ON_GPU = {"register": False, "render": True}


def resolve_device(device: str | torch.device | None = None, job: str | None = None) -> torch.device:
    """``cpu``, ``cuda`` or ``auto``; None: ``$STATFIT_DEVICE``, else the CPU. ``auto``: CUDA when
    available and :data:`AUTO_ON_GPU` has ``job`` (register, render, ...) faster there."""
    device = str(device or os.environ.get(DEVICE_ENV) or "cpu")
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() and AUTO_ON_GPU.get(job or "", True) else "cpu"
    if device.split(":")[0] not in ("cpu", "cuda"):
        raise StatfitError(f"unknown device {device!r}; choose auto, cpu or cuda")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise StatfitError("--device cuda was asked for but no CUDA device is available")
    if device.startswith("cuda"):
        same_seed_same_bytes()
        load_cuda_linear_algebra(torch.device(device))
    return torch.device(device)


_linear_algebra_lock = threading.Lock()
_linear_algebra_loaded = False


def load_cuda_linear_algebra(device: torch.device) -> None:
    """Load torch's CUDA linear-algebra library now, once a process, on this thread. torch loads it at
    the first CUDA factorisation or solve, and two threads making that first call at once fail
    ("lazy wrapper should be called at most once"): on an H200 (session 43, torch 2.11) fits stepped
    together in ``batch register``, whose host work runs on threads, failed so."""
    global _linear_algebra_loaded
    with _linear_algebra_lock:
        if not _linear_algebra_loaded:
            torch.linalg.cholesky_ex(torch.ones(1, 1, device=device))
            _linear_algebra_loaded = True


def same_seed_same_bytes() -> None:
    """Make CUDA's reductions deterministic (torch's deterministic algorithms, cuBLAS's fixed
    workspace), so a seed gives the same bytes on every run, as on the CPU; an op with no
    deterministic CUDA kernel warns instead of failing. ``STATFIT_DETERMINISTIC=0`` opts out.

    The flag is set where ``torch.use_deterministic_algorithms`` sets it: that function also
    imports torch's compiler to set the compiler's own flag (1.5 s a process, docs/benchmarks.md
    §12), and statfit compiles nothing."""
    if os.environ.get(DETERMINISTIC_ENV, "1") == "0":
        return
    os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    torch._C._set_deterministic_algorithms(True, warn_only=True)
