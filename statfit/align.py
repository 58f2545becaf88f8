"""Rigid and similarity pre-alignment of a template to a point set (trimmed ICP + Umeyama)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from statfit.closest import ClosestPointQuery


@dataclass(frozen=True)
class Similarity:
    """y = scale · R x + t."""

    scale: float = 1.0
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def apply(self, points: np.ndarray) -> np.ndarray:
        return self.scale * points @ self.rotation.T + self.translation

    def inverse_apply(self, points: np.ndarray) -> np.ndarray:
        return (points - self.translation) @ self.rotation / self.scale

    def as_matrix(self) -> list[list[float]]:
        m = np.eye(4)
        m[:3, :3] = self.scale * self.rotation
        m[:3, 3] = self.translation
        return m.tolist()


def umeyama(source: np.ndarray, target: np.ndarray, with_scale: bool) -> Similarity:
    """Least-squares similarity (or rigid) transform mapping ``source`` (M, 3) onto ``target``."""
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    s, t = source - mu_s, target - mu_t
    u, sing, vt = np.linalg.svd(t.T @ s / len(source))
    d = np.ones(3)
    d[2] = np.sign(np.linalg.det(u @ vt)) or 1.0
    rotation = u @ np.diag(d) @ vt
    scale = float((sing * d).sum() / (s**2).sum(axis=1).mean()) if with_scale else 1.0
    return Similarity(scale, rotation, mu_t - scale * rotation @ mu_s)


def icp(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, with_scale: bool,
        iterations: int = 40, trim: float = 0.2, start: Similarity | None = None) -> Similarity:
    """Transform mapping the mesh (``vertices``, ``faces``) onto ``points`` by trimmed
    point-to-surface ICP: each round attaches the points to the transformed mesh's closest
    surface points, drops the ``trim`` fraction farthest, and solves Umeyama."""
    query = ClosestPointQuery(faces, len(vertices))
    mesh = torch.as_tensor(vertices, dtype=torch.float64)
    target = torch.as_tensor(points, dtype=torch.float64)
    transform = start or Similarity()
    for _ in range(iterations):
        local = torch.as_tensor(transform.inverse_apply(points))
        hit = query(mesh, local)
        surface = (mesh[query.faces[hit.triangle]] * hit.barycentric[..., None]).sum(dim=1).numpy()
        keep = hit.distance.numpy() <= np.quantile(hit.distance.numpy(), 1.0 - trim)
        updated = umeyama(surface[keep], target.numpy()[keep], with_scale)
        moved = np.abs(updated.apply(vertices) - transform.apply(vertices)).max()
        transform = updated
        if moved < 1e-7 * np.ptp(vertices):
            break
    return transform


def initial_guess(vertices: np.ndarray, points: np.ndarray, with_scale: bool) -> Similarity:
    """A starting transform: scale from the ratio of extents (similarity only), then centroids matched."""
    scale = float(np.linalg.norm(np.ptp(points, axis=0)) / np.linalg.norm(np.ptp(vertices, axis=0))) if with_scale else 1.0
    return Similarity(scale, np.eye(3), points.mean(axis=0) - scale * vertices.mean(axis=0))
