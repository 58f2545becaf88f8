"""Scan landmarks: a text file of L rows ``x y z`` (one per model landmark, in the model's order)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from statfit.errors import StatfitError


def read_landmarks(path: str | Path) -> np.ndarray:
    """Points (L, 3) from a whitespace- or comma-separated text file; ``nan`` marks a missing landmark,
    ``#`` starts a comment."""
    path = Path(path)
    if not path.is_file():
        raise StatfitError(f"landmark file not found: {path}")
    try:
        text = path.read_text().replace(",", " ")
        rows = [line.split("#")[0].split() for line in text.splitlines()]
        points = np.array([row for row in rows if row], dtype=np.float64)
    except (UnicodeDecodeError, ValueError):
        raise StatfitError(f"{path}: landmarks must be rows of three numbers (x y z; nan for a missing one)") from None
    if points.ndim != 2 or points.shape[1] != 3:
        raise StatfitError(f"{path}: landmarks must be rows of three numbers (x y z; nan for a missing one)")
    if np.isinf(points).any():
        raise StatfitError(f"{path}: landmarks contain infinite values")
    return points
