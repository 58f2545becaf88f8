"""A normal map as the fits use it: the observation of ``statfit render``."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from statfit.structures.camera import Camera


@dataclass(frozen=True)
class NormalMap:
    """normals (H, W, 3) float32, unit on the mask; mask (H, W) bool; camera from the header, if any."""

    normals: np.ndarray
    mask: np.ndarray
    camera: Camera | None = None
