"""A scan as the fit sees it: points with unit normals.

A mesh scan's vertices crowd where the scanner looked straight on and thin out at grazing angles,
so its points are drawn from its triangles by area instead (a fit weighted by where the scanner
happened to look would lean that way); their normals are the triangles'. A point cloud's normals
are estimated from its nearest neighbours. Normals are oriented away from the scan's centroid, a
guess that holds for a convex object seen from outside: use them up to sign.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from statfit.errors import StatfitError

# Points drawn from a mesh scan: as many as it has vertices, within these bounds (a head is well
# covered by far fewer than the most; the fit's cost grows with the count).
MESH_SAMPLES = (1_000, 20_000)
# Neighbours whose spread gives a point cloud's normal.
NORMAL_NEIGHBOURS = 12


@dataclass(frozen=True)
class Scan:
    """``points`` (M, 3) and their unit ``normals`` (M, 3)."""

    points: np.ndarray
    normals: np.ndarray

    @classmethod
    def from_points(cls, points: np.ndarray) -> "Scan":
        """A point cloud (M, 3), normals estimated."""
        points = np.asarray(points, dtype=np.float64)
        return cls(points, _outward(points, estimate_normals(points)))

    @classmethod
    def from_mesh(cls, vertices: np.ndarray, faces: np.ndarray, seed: int = 0,
                  count: int | None = None) -> "Scan":
        """Points drawn uniformly by area from a triangle mesh (``count``: as many as it has
        vertices, within MESH_SAMPLES), with their triangles' normals; deterministic for ``seed``."""
        vertices, faces = np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64)
        if faces.ndim != 2 or faces.shape[1] != 3 or faces.min(initial=0) < 0 or faces.max(initial=0) >= len(vertices):
            raise StatfitError("the scan mesh's faces must be vertex index triples")
        a, b, c = (vertices[faces[:, i]] for i in range(3))
        cross = np.cross(b - a, c - a)
        area = np.linalg.norm(cross, axis=1)
        if not np.isfinite(area).all() or area.sum() <= 0:
            raise StatfitError("the scan mesh has no triangle of positive area")
        count = count or int(np.clip(len(vertices), *MESH_SAMPLES))
        rng = np.random.default_rng(seed)
        triangle = rng.choice(len(faces), size=count, p=area / area.sum())
        r1, r2 = np.sqrt(rng.random(count))[:, None], rng.random(count)[:, None]
        points = (1 - r1) * a[triangle] + r1 * (1 - r2) * b[triangle] + r1 * r2 * c[triangle]
        return cls(points, _outward(points, cross[triangle] / area[triangle, None]))


def estimate_normals(points: np.ndarray, neighbours: int = NORMAL_NEIGHBOURS) -> np.ndarray:
    """Unit normals (M, 3) of a point cloud (M, 3), unoriented: the direction of least spread of
    each point's ``neighbours`` nearest points."""
    k = min(neighbours, len(points))
    _, nearest = cKDTree(points).query(points, k=k)
    local = points[nearest.reshape(len(points), k)]
    local = local - local.mean(axis=1, keepdims=True)
    _, vectors = np.linalg.eigh(np.einsum("mki,mkj->mij", local, local))
    return vectors[:, :, 0]


def _outward(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """``normals`` (M, 3) flipped to point away from the points' centroid."""
    return normals * np.where(((points - points.mean(axis=0)) * normals).sum(axis=1) < 0, -1.0, 1.0)[:, None]
