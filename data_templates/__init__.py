"""Data files shipped with statfit (installed as the package ``statfit_data``)."""
from __future__ import annotations

import importlib.resources
from pathlib import Path


def default_model_path() -> Path:
    """Path of ``default_head.npz``, the synthetic default head model (see README.md here)."""
    return Path(importlib.resources.files(__name__) / "default_head.npz")
