"""Shared fixtures: the embedded model, the real ICT model (../shared), small random problems."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from statfit.model import default_model_path, load_model

ICT_DIR = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "ict-face"


@pytest.fixture(scope="session")
def embedded_model():
    return load_model(default_model_path())


@pytest.fixture(scope="session")
def ict_model():
    path = ICT_DIR / "ict_face_identity.npz"
    if not path.is_file():
        pytest.skip(f"ICT data not found at {path}")
    return load_model(path)


@pytest.fixture(scope="session")
def ict_expressions():
    with np.load(ICT_DIR / "ict_face_expressions.npz") as data:
        return [str(n) for n in data["names"]], data["deltas"].astype(np.float64)


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture(autouse=True)
def _threads():
    torch.set_num_threads(2)
