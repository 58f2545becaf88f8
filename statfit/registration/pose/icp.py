"""Step 3 of the pose search: trimmed point-to-plane similarity ICP of many poses at once, against
one shape's nearest vertices and their tangent planes."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from statfit.geometry.closest import ClosestPointQuery
from statfit.registration.pose.hypotheses import Poses
from statfit.structures.kdtree import kd_tree

KEEP = 0.7                 # fraction of the normal-compatible points kept per ICP round (the nearest)
NORMAL_COSINE = 0.5        # |cos| between scan and surface normals for a point to count (60°)


class Matcher:
    """Nearest points and normals on one shape (N, 3) for many scan points in its frame: the
    nearest vertex's tangent plane (a KD-tree query; ICP's classic approximation of the surface,
    within a fraction of the vertex spacing of the true distance)."""

    def __init__(self, faces: np.ndarray, vertices: np.ndarray):
        self.faces = np.asarray(faces)
        self.query = ClosestPointQuery(faces, len(vertices), k=2)
        self.set_shape(vertices)

    def set_shape(self, vertices: np.ndarray) -> None:
        self.vertices = vertices
        self.tree = kd_tree(vertices)
        self.normals = vertex_normals(self.faces, vertices)
        a, b = vertices[self.faces[:, 0]], vertices[self.faces[:, 1]]
        self.spacing = float(np.linalg.norm(b - a, axis=1).mean())

    def __call__(self, local: np.ndarray, local_normals: np.ndarray) -> tuple[np.ndarray, ...]:
        """For ``local`` (H, M, 3): nearest vertices and their normals (H, M, 3), distances (H, M)
        (the tangent plane's, plus how far beyond a vertex spacing the point lies sideways) and
        whether the normals agree up to sign (H, M)."""
        _, nearest = self.tree.query(local.reshape(-1, 3))
        nearest = nearest.reshape(local.shape[:2])
        surface, normals = self.vertices[nearest], self.normals[nearest]
        offset = local - surface
        along = (offset * normals).sum(axis=-1)
        sideways = np.sqrt(np.maximum((offset * offset).sum(axis=-1) - along**2, 0))
        distance = np.sqrt(along**2 + np.maximum(sideways - self.spacing, 0) ** 2)
        agree = np.abs((normals * local_normals).sum(axis=-1)) >= NORMAL_COSINE
        return surface, normals, distance, agree


def trimmed_icp(matcher: Matcher, points: np.ndarray, normals: np.ndarray, poses: Poses, rounds: int,
                scale_bounds: tuple[float, float]) -> Poses:
    """Trimmed point-to-plane similarity ICP of every pose at once, scale kept within bounds: of the
    points whose normals agree, the nearest KEEP fraction count."""
    for _ in range(rounds):
        local = poses.to_model(points)
        surface, surface_normals, distance, agree = matcher(local, np.einsum("mi,hij->hmj", normals, poses.rotation))
        cut = row_quantile(distance, agree, KEEP)
        weight = (agree & (distance <= cut[:, None])).astype(np.float64)
        centre = (weight[..., None] * surface).sum(axis=1) / np.maximum(weight.sum(axis=1), 1)[:, None]
        q, p = surface - centre[:, None], local - centre[:, None]
        columns = np.concatenate([np.cross(q, surface_normals), surface_normals,
                                  (surface_normals * q).sum(axis=-1, keepdims=True)], axis=-1)   # (H, M, 7)
        rhs = ((p - q) * surface_normals).sum(axis=-1)
        lhs = np.einsum("hmi,hm,hmj->hij", columns, weight, columns)
        lhs += 1e-9 * np.eye(7) * (np.trace(lhs, axis1=1, axis2=2)[:, None, None] + 1e-12)
        step = np.linalg.solve(lhs, np.einsum("hmi,hm,hm->hi", columns, weight, rhs)[..., None])[..., 0]
        step[weight.sum(axis=1) < 10] = 0.0            # too few matches to say where to go: stay
        step[:, 6] = np.clip(step[:, 6], -0.2, 0.2)    # a linearised scale step is trusted only so far
        step_rotation = Rotation.from_rotvec(step[:, :3]).as_matrix()
        step_scale = np.exp(step[:, 6])
        step_translation = centre + step[:, 3:6] - step_scale[:, None] * np.einsum("hij,hj->hi", step_rotation, centre)
        poses = Poses(np.clip(poses.scale * step_scale, *scale_bounds),
                       np.einsum("hij,hjk->hik", poses.rotation, step_rotation),
                       poses.scale[:, None] * np.einsum("hij,hj->hi", poses.rotation, step_translation)
                       + poses.translation)
    return poses


def row_quantile(values: np.ndarray, mask: np.ndarray, q: float) -> np.ndarray:
    """Per row of ``values`` (H, M), the ``q`` quantile of the entries ``mask`` (H, M) keeps, as
    ``np.quantile`` (linear) computes it, or inf for a row keeping 10 or fewer: all rows at once."""
    count = mask.sum(axis=1)
    last = np.maximum(count, 1) - 1
    ordered = np.sort(np.where(mask, values, np.inf), axis=1)
    position = q * last
    low = np.floor(position).astype(np.int64)
    t = position - low
    a = np.take_along_axis(ordered, low[:, None], 1)[:, 0]
    b = np.take_along_axis(ordered, np.minimum(low + 1, last)[:, None], 1)[:, 0]
    with np.errstate(invalid="ignore"):      # inf − inf on rows that keep nothing, masked below
        diff = b - a
        value = np.where(t >= 0.5, b - diff * (1 - t), a + diff * t)   # numpy's own interpolation
    return np.where(count > 10, value, np.inf)


def vertex_normals(faces: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """Unit vertex normals (N, 3) of ``vertices`` (N, 3) and ``faces`` (F, 3): the area-weighted sum
    of the triangles' normals at each vertex."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    corner_normals = np.repeat(np.cross(b - a, c - a), 3, axis=0)
    normals = np.stack([np.bincount(faces.reshape(-1), corner_normals[:, i], len(vertices)) for i in range(3)], axis=1)
    return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
