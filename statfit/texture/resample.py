"""Resampling images, masks and chart labels to another grid size (vectorised, torch)."""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as nnf

# A resampled pixel is visible only if at least this fraction of its area was visible, so hole
# colours never leak into "visible" pixels.
VISIBLE_FRACTION = 0.99


def resize_image(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``image`` (H, W, C) resampled to ``size`` = (H', W'): bilinear with antialiasing (area-like
    when shrinking), float32."""
    if image.shape[:2] == tuple(size):
        return image.astype(np.float32, copy=False)
    batch = torch.as_tensor(np.ascontiguousarray(image, dtype=np.float32)).permute(2, 0, 1)[None]
    out = nnf.interpolate(batch, size=tuple(size), mode="bilinear", antialias=True, align_corners=False)
    return out[0].permute(1, 2, 0).contiguous().numpy()


def resize_mask(mask: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """A visibility mask (H, W) bool resampled to ``size``; see ``VISIBLE_FRACTION``."""
    if mask.shape == tuple(size):
        return mask
    return resize_image(mask[..., None].astype(np.float32), size)[..., 0] >= VISIBLE_FRACTION


def resize_labels(labels: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Integer labels (H, W) resampled to ``size`` by nearest neighbour."""
    if labels.shape == tuple(size):
        return labels
    rows = np.minimum(((np.arange(size[0]) + 0.5) * labels.shape[0] / size[0]).astype(np.int64), labels.shape[0] - 1)
    cols = np.minimum(((np.arange(size[1]) + 0.5) * labels.shape[1] / size[1]).astype(np.int64), labels.shape[1] - 1)
    return labels[rows[:, None], cols[None, :]]
