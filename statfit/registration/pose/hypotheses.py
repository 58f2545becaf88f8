"""Step 2 of the pose search: the starting poses, one per rotation of the icosahedral group (and,
where the first search leaves doubt, of the same group turned between its rotations), and the poses
as arrays."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from statfit.geometry.align import Similarity

HYPOTHESES = Rotation.create_group("I").as_matrix()   # (60, 3, 3)
# The second grid: the group turned by 18° (about half the ~38° within which every rotation lies of
# one of the group's) about an axis none of its rotations shares, so that its starts lie between the
# first's (docs/studies.md §44).
SECOND_HYPOTHESES = (Rotation.create_group("I")
                     * Rotation.from_rotvec(np.radians(18.0) * np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0))).as_matrix()
DISTINCT_DEGREES = 30.0
VISIBLE_COSINE = 0.3       # a vertex faces the scanner when its normal is within ~73° of the view


@dataclass
class Poses:
    """H similarities x ↦ s R x + t, as arrays: s (H,), R (H, 3, 3), t (H, 3)."""

    scale: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray

    def to_model(self, points: np.ndarray) -> np.ndarray:
        """Points (M, 3) mapped back by each pose: (H, M, 3)."""
        return np.einsum("hmi,hij->hmj", points[None] - self.translation[:, None], self.rotation) \
            / self.scale[:, None, None]

    @classmethod
    def of(cls, pose: Similarity) -> "Poses":
        """One pose."""
        return cls(np.array([pose.scale]), pose.rotation[None], pose.translation[None])

    def subset(self, indices: np.ndarray) -> "Poses":
        """The poses at ``indices`` (K,)."""
        return Poses(self.scale[indices], self.rotation[indices], self.translation[indices])

    def pick(self, index: int) -> Similarity:
        return Similarity(float(self.scale[index]), self.rotation[index], self.translation[index])


def hypothesis_starts(model_unit: np.ndarray, model_normals: np.ndarray, facing: np.ndarray,
                      rotations: np.ndarray = HYPOTHESES) -> Poses:
    """One pose per rotation of ``rotations`` (H, 3, 3): the model's vertices (N, 3) facing
    ``facing`` (3,) (scan frame) centred on the origin (the scan's centroid). A rotation that shows
    the scanner no vertex (a face mask turned away: it has no back) places the whole template there
    instead; such a pose fits the scan badly and is screened out by its score."""
    translation = np.empty((len(rotations), 3))
    for h, rotation in enumerate(rotations):       # 60 rotations, each a vectorised pass over the vertices
        visible = model_normals @ (rotation.T @ facing) > VISIBLE_COSINE
        translation[h] = -rotation @ (model_unit[visible] if visible.any() else model_unit).mean(axis=0)
    return Poses(np.ones(len(rotations)), rotations.copy(), translation)


def distinct_poses(poses: Poses, order: np.ndarray, count: int) -> list[int]:
    """The first ``count`` poses in ``order`` that differ pairwise by ≥ DISTINCT_DEGREES."""
    chosen: list[int] = []
    for index in order:
        if all(angle_between(poses.rotation[index], poses.rotation[other]) >= DISTINCT_DEGREES for other in chosen):
            chosen.append(int(index))
        if len(chosen) == count:
            break
    return chosen


def angle_between(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(Rotation.from_matrix(a.T @ b).magnitude()))
