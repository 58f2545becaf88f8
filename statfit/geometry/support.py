"""Where a fit saw data and where it guessed: per fitted vertex, the distance to the nearest data
and whether the data observed it (the fitted PLY's ``data_distance`` and ``observed`` fields,
docs/formats.md "Output mesh").

A scan's data are its points. A normal map or a photograph carries no depth, so its data are its
covered pixels lifted onto the fitted surface (the visible surface point under each pixel centre):
``data_distance`` is then the 3D distance to the nearest such point, about a triangle's size or
less on the seen side, the distance through the head on the far side.
"""
from __future__ import annotations

import numpy as np
import torch

from statfit.geometry.metrics import nearest_point_distance
from statfit.renderer import Camera, interpolate_fragments, rasterize
from statfit.structures.kdtree import kd_tree


def scan_support(vertices: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N,) distance of each vertex (N, 3) to the nearest scan point (M, 3), and (N,) bool
    observed: within three median point spacings of a point (the rule of ``statfit eval --scan``)."""
    distance, observed = nearest_point_distance(vertices, points)
    return distance.astype(np.float64), observed


def view_support(vertices: np.ndarray, faces: np.ndarray, views: list[tuple[Camera, np.ndarray | None]]
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(N,) distance of each vertex (N, 3) to the nearest covered pixel's point on the fitted
    surface, over ``views`` (camera, mask (H, W) bool or None: every pixel the mesh covers), and
    (N,) bool observed: a vertex of a triangle visible in such a pixel."""
    points_t = torch.as_tensor(vertices, dtype=torch.float64)
    faces_t = torch.as_tensor(faces, dtype=torch.long)
    lifted, observed = [], np.zeros(len(vertices), dtype=bool)
    for camera, mask in views:   # one rasterisation per view
        fragments = rasterize(points_t, faces_t, camera)
        keep = np.ones(len(fragments.pixel), dtype=bool) if mask is None else \
            np.asarray(mask).reshape(-1)[fragments.pixel.numpy()]
        with torch.no_grad():
            surface = interpolate_fragments(points_t, faces_t, fragments).T.numpy()   # (M, 3)
        lifted.append(surface[keep])
        observed[faces[np.unique(fragments.face.numpy()[keep])].reshape(-1)] = True
    points = np.concatenate(lifted) if lifted else np.zeros((0, 3))
    if len(points) == 0:
        return np.full(len(vertices), np.inf), observed
    distance, _ = kd_tree(points).query(vertices, k=1)
    return distance.astype(np.float64), observed
