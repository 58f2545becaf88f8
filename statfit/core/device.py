"""Which torch device a job runs on: one rule for every job and command."""
from __future__ import annotations

import os

import torch

from statfit.errors import StatfitError

# Names the default device: ``STATFIT_DEVICE=cuda pytest`` runs the whole suite's fits on the GPU.
DEVICE_ENV = "STATFIT_DEVICE"


def resolve_device(device: str | torch.device | None = None) -> torch.device:
    """``cpu``, ``cuda`` or ``auto`` (CUDA when available); None: ``$STATFIT_DEVICE``, else the CPU."""
    device = str(device or os.environ.get(DEVICE_ENV) or "cpu")
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device.split(":")[0] not in ("cpu", "cuda"):
        raise StatfitError(f"unknown device {device!r}; choose auto, cpu or cuda")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise StatfitError("--device cuda was asked for but no CUDA device is available")
    return torch.device(device)
