"""Unit normalisation: every fit runs in a frame where the model's template is centred with
unit RMS radius, so results do not depend on whether inputs are in mm, cm or m."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Data whose extent differs from the model's by more than this factor is taken to be in other units
# (register's scans, render's silhouettes).
UNIT_MISMATCH_FACTOR = 8.0


@dataclass(frozen=True)
class Frame:
    """``normalised = (x - center) / scale``."""

    center: np.ndarray
    scale: float

    @classmethod
    def of(cls, vertices: np.ndarray, faces: np.ndarray | None = None) -> "Frame":
        """The frame that centres ``vertices`` (N, 3) with unit RMS distance from the centroid; with
        ``faces`` (F, 3), of the vertices some face uses (:func:`surface_vertices`)."""
        if faces is not None:
            vertices = surface_vertices(vertices, faces)
        center = vertices.mean(axis=0)
        return cls(center, float(np.sqrt(((vertices - center) ** 2).sum(axis=1).mean())))

    def to_unit(self, points: np.ndarray) -> np.ndarray:
        return (points - self.center) / self.scale

    def from_unit(self, points: np.ndarray) -> np.ndarray:
        return points * self.scale + self.center


def surface_vertices(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The rows of ``vertices`` (N, 3) that some face of ``faces`` (F, 3) uses, in order (``vertices``
    itself where every one is: most meshes). A vertex no face uses (a model's spare points) has no
    surface to be seen or fitted, so it takes no part in a mesh's size, centre or units."""
    used = np.zeros(len(vertices), dtype=bool)
    used[np.asarray(faces).reshape(-1)] = True
    return vertices if used.all() else vertices[used]
