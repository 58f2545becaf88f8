"""Multi-view photographs with their cameras: the observations of ``statfit splat``."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from statfit.structures.camera import Camera

SPLITS = ("train", "test")


@dataclass(frozen=True)
class View:
    """One photograph: ``name`` (its file name), ``camera``, ``image`` (H, W, 3) float32 in [0, 1],
    ``mask`` (H, W) bool (None: no mask), ``split`` 'train' (fitted) or 'test' (held out)."""

    name: str
    camera: Camera
    image: np.ndarray
    mask: np.ndarray | None
    split: str
