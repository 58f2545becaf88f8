"""Rigid and similarity pre-alignment of a template to a point set (trimmed point-to-plane ICP)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
import trimesh
from scipy.spatial.transform import Rotation

from statfit.geometry.closest import ClosestPointQuery


# Rigid/similarity ICP: rounds (converged well before on the tested cases) and the fraction of
# farthest points dropped each round (a partial scan's points beyond the template's border).
ICP_ITERATIONS = 60
ICP_TRIM = 0.2

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

    def as_matrix(self) -> np.ndarray:
        """The 4 × 4 homogeneous matrix."""
        m = np.eye(4)
        m[:3, :3] = self.scale * self.rotation
        m[:3, 3] = self.translation
        return m


def umeyama(source: np.ndarray, target: np.ndarray, with_scale: bool, weights: np.ndarray | None = None
            ) -> Similarity:
    """Least-squares similarity (or rigid) transform mapping ``source`` (M, 3) onto ``target``,
    each pair weighted by ``weights`` (M,) if given."""
    w = np.full(len(source), 1.0 / len(source)) if weights is None else weights / weights.sum()
    mu_s, mu_t = w @ source, w @ target
    s, t = source - mu_s, target - mu_t
    u, sing, vt = np.linalg.svd((t * w[:, None]).T @ s)
    d = np.ones(3)
    d[2] = np.sign(np.linalg.det(u @ vt)) or 1.0
    rotation = u @ np.diag(d) @ vt
    scale = float((sing * d).sum() / (w @ (s**2).sum(axis=1))) if with_scale else 1.0
    return Similarity(scale, rotation, mu_t - scale * rotation @ mu_s)


def compose(outer: Similarity, inner: Similarity) -> Similarity:
    """The transform x ↦ outer(inner(x))."""
    return Similarity(outer.scale * inner.scale, outer.rotation @ inner.rotation,
                      outer.scale * outer.rotation @ inner.translation + outer.translation)


def _plane_step(surface: np.ndarray, normals: np.ndarray, targets: np.ndarray, with_scale: bool) -> Similarity:
    """Linearised point-to-plane update D (rotation vector, translation, log-scale) that moves
    ``surface`` points towards ``targets`` along ``normals``; about the points' centroid."""
    center = surface.mean(axis=0)
    q, p = surface - center, targets - center
    columns = [np.cross(q, normals), normals] + ([(normals * q).sum(axis=1, keepdims=True)] if with_scale else [])
    solution, *_ = np.linalg.lstsq(np.hstack(columns), ((p - q) * normals).sum(axis=1), rcond=None)
    rotation = Rotation.from_rotvec(solution[:3]).as_matrix()
    scale = float(np.exp(solution[6])) if with_scale else 1.0
    return Similarity(scale, rotation, center + solution[3:6] - scale * rotation @ center)


def icp(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, with_scale: bool,
        iterations: int = ICP_ITERATIONS, trim: float = ICP_TRIM, start: Similarity | None = None) -> Similarity:
    """Transform mapping the mesh (``vertices``, ``faces``) onto ``points`` by trimmed
    point-to-plane ICP: each round attaches the points, mapped into the mesh's frame, to their
    closest surface points, drops the ``trim`` fraction farthest, and solves a linearised update."""
    query = ClosestPointQuery(faces, len(vertices))
    mesh = torch.as_tensor(vertices, dtype=torch.float64)
    face_normals = trimesh.Trimesh(vertices, faces, process=False).face_normals
    transform = start or Similarity()
    tolerance = 1e-7 * float(np.ptp(vertices))
    for _ in range(iterations):
        local = transform.inverse_apply(points)
        hit = query(mesh, torch.as_tensor(local))
        surface = (mesh[query.faces[hit.triangle]] * hit.barycentric[..., None]).sum(dim=1).numpy()
        distance = hit.distance.numpy()
        keep = distance <= np.quantile(distance, 1.0 - trim)
        step = _plane_step(surface[keep], face_normals[hit.triangle.numpy()[keep]], local[keep], with_scale)
        transform = compose(transform, step)
        if np.abs(step.apply(vertices) - vertices).max() < tolerance:
            break
    return transform


def initial_guess(vertices: np.ndarray, points: np.ndarray, with_scale: bool) -> Similarity:
    """A starting transform: scale from the ratio of extents (similarity only), then centroids matched."""
    scale = float(np.linalg.norm(np.ptp(points, axis=0)) / np.linalg.norm(np.ptp(vertices, axis=0))) if with_scale else 1.0
    return Similarity(scale, np.eye(3), points.mean(axis=0) - scale * vertices.mean(axis=0))
