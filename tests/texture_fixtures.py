"""Test fixtures for inpainting: a generated family of face-like textures with structured features
(also used by benchmarks/ and studies/), a hole over one eyebrow, and the errors on a hole.

Each texture: a skin colour with low-frequency shading, two eyebrow strokes (arched, their height,
length, thickness, arch and hair colour vary; left and right alike but not identical), two eyes
(white, iris colour) and a mouth, all with soft 1-pixel edges. A PCA model of ~150 of them knows
what an eyebrow looks like; a held-out texture with a hole over one eyebrow is the test case.
"""
from __future__ import annotations

import numpy as np


def _smooth_inside(distance: np.ndarray, pixel: float) -> np.ndarray:
    """Soft indicator of ``distance < 0`` with a ramp one pixel wide."""
    return np.clip(0.5 - distance / pixel, 0.0, 1.0)


def _paint(image: np.ndarray, coverage: np.ndarray, colour: np.ndarray) -> None:
    """Blend ``colour`` (n, 1, 1, 3) into ``image`` (n, H, W, 3) with ``coverage`` (n, H, W)."""
    image += coverage[..., None] * (colour - image)


def face_textures(n: int, size: int | tuple[int, int] = 64, seed: int = 0) -> np.ndarray:
    """``n`` face-like RGB textures (n, H, W, 3) float32 in [0, 1], reproducible from ``seed``."""
    height, width = (size, size) if isinstance(size, int) else size
    rng = np.random.default_rng(seed)
    y = (np.arange(height)[:, None] + 0.5) / height          # (H, 1) in (0, 1), down
    x = (np.arange(width)[None, :] + 0.5) / width            # (1, W), right
    pixel = 1.0 / min(height, width)

    def param(low: float, high: float, *shape: int) -> np.ndarray:
        return rng.uniform(low, high, (n, *shape) if shape else (n, 1, 1))

    skin = np.array([0.85, 0.64, 0.52]) * param(0.75, 1.1, 1, 1, 1) + param(-0.04, 0.04, 1, 1, 3)
    shading = 1.0 + param(-0.15, 0.15) * (x - 0.5) + param(-0.1, 0.1) * (y - 0.5) \
        - param(0.1, 0.3) * ((x - 0.5) ** 2 + (y - 0.55) ** 2)
    image = np.broadcast_to(skin * shading[..., None], (n, height, width, 3)).copy()

    hair = np.array([0.30, 0.20, 0.12]) * param(0.3, 1.3, 1, 1, 1)
    brow_y, brow_len, brow_thick, arch = param(0.27, 0.31), param(0.09, 0.14), param(0.025, 0.06), param(0.0, 4.0)
    for side in (-1.0, 1.0):                                  # two brows: shared parameters, small differences
        cx = 0.5 + side * param(0.19, 0.21)
        cy = brow_y + param(-0.005, 0.005)
        length = brow_len * param(0.95, 1.05)
        centre_line = cy - arch * (length**2 - (x - cx) ** 2).clip(0.0) * 1.5
        across = np.abs(y - centre_line) - brow_thick / 2
        along = np.abs(x - cx) - length
        _paint(image, _smooth_inside(np.maximum(across, along), pixel), hair)

    iris = np.stack([param(0.1, 0.5), param(0.2, 0.6), param(0.2, 0.7)], axis=-1)
    eye_y, eye_w, eye_h = param(0.42, 0.44), param(0.06, 0.09), param(0.025, 0.04)
    for side in (-1.0, 1.0):
        cx = 0.5 + side * param(0.195, 0.205)
        eye = np.sqrt(((x - cx) / eye_w) ** 2 + ((y - eye_y) / eye_h) ** 2) - 1.0
        _paint(image, _smooth_inside(eye * eye_h, pixel), np.array([0.95, 0.95, 0.93]))
        ball = np.sqrt((x - cx) ** 2 + (y - eye_y) ** 2) - eye_h * 0.9
        _paint(image, _smooth_inside(ball, pixel), iris)

    lips = np.array([0.70, 0.30, 0.30]) * param(0.7, 1.15, 1, 1, 1)
    mouth_y, mouth_w, mouth_h = param(0.74, 0.78), param(0.10, 0.17), param(0.02, 0.05)
    mouth = np.sqrt(((x - 0.5) / mouth_w) ** 2 + ((y - mouth_y) / mouth_h) ** 2) - 1.0
    _paint(image, _smooth_inside(mouth * mouth_h, pixel), lips)
    return np.clip(image, 0.0, 1.0).astype(np.float32)


def brow_hole(size: int | tuple[int, int] = 64, side: str = "left") -> np.ndarray:
    """Visibility mask (H, W) bool with a large hole (about 16% of the image) over one eyebrow region."""
    height, width = (size, size) if isinstance(size, int) else size
    y = (np.arange(height)[:, None] + 0.5) / height
    x = (np.arange(width)[None, :] + 0.5) / width
    cx = 0.3 if side == "left" else 0.7
    hole = (np.abs(x - cx) < 0.2) & (y > 0.1) & (y < 0.5)
    return ~hole


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
