"""Errors of an inpainting on its hole pixels, against the ground truth."""
from __future__ import annotations

import numpy as np


def hole_errors(result: np.ndarray, truth: np.ndarray, visible: np.ndarray) -> dict[str, float]:
    """RMS error and correlation over the hole pixels (``visible`` False) of images (H, W, C).

    The correlation is Pearson's over all hole entries after removing each channel's mean, so it
    measures structure (features in the right place), not the overall colour.
    """
    hole = ~np.asarray(visible, dtype=bool)
    a, b = result[hole].astype(np.float64), truth[hole].astype(np.float64)
    rmse = float(np.sqrt(np.mean((a - b) ** 2)))
    a, b = a - a.mean(axis=0), b - b.mean(axis=0)
    norm = np.sqrt((a * a).sum() * (b * b).sum())
    return {"rmse": rmse, "correlation": float((a * b).sum() / norm) if norm > 0 else 0.0}
