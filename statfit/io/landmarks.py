"""Landmark text files: scan landmarks (L rows ``x y z``, one per model landmark, in the model's
order) and model landmark vertex indices (L integers)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from statfit.errors import StatfitError
from statfit.io.files import existing_file


def _numbers(path: str | Path, what: str) -> list[list[str]]:
    """The non-empty rows of a whitespace- or comma-separated text file, ``#`` starting a comment."""
    path = existing_file(path, "landmark file")
    try:
        text = path.read_text().replace(",", " ")
    except (UnicodeDecodeError, OSError):
        raise StatfitError(f"{path}: {what}") from None
    return [row for row in (line.split("#")[0].split() for line in text.splitlines()) if row]


def read_landmarks(path: str | Path) -> np.ndarray:
    """Points (L, 3); ``nan`` marks a missing landmark."""
    what = "landmarks must be rows of three numbers (x y z; nan for a missing one)"
    try:
        points = np.array(_numbers(path, what), dtype=np.float64)
    except ValueError:  # ragged rows or text
        raise StatfitError(f"{path}: {what}") from None
    if points.ndim != 2 or points.shape[1] != 3:
        raise StatfitError(f"{path}: {what}")
    if np.isinf(points).any():
        raise StatfitError(f"{path}: landmarks contain infinite values")
    return points


def read_landmark_indices(path: str | Path) -> np.ndarray:
    """Vertex indices (L,), in landmark order (any number per row)."""
    what = "landmark indices must be non-negative integers"
    tokens = [token for row in _numbers(path, what) for token in row]
    if not tokens or not all(token.isdigit() for token in tokens):
        raise StatfitError(f"{path}: {what}")
    return np.array(tokens, dtype=np.int64)
