"""Normal-map term: match rendered normals and silhouette to an observed normal map.

normal: mean over the pixels covered by both the target and the rendering of ``‖n − n̂‖₁``
(sum of absolute component differences, camera space); the rendered normals are interpolated
from the vertex normals of the current mesh, so the term is differentiable through them.
silhouette: ``Σ (m − m̂)² / |target|`` over all pixels, where ``m`` is the rendered coverage
antialiased at silhouette edges (its only gradients), ``m̂`` the target mask.
The total is ``normal + silhouette_weight · silhouette``. Visibility is recomputed every call.
"""
from __future__ import annotations

import torch

from statfit.render import Camera, MeshAdjacency, normal_image, rasterize, silhouette_crossings

SILHOUETTE_WEIGHT = 1.0


class NormalMapObjective:
    """Data term of inverse rendering, in camera space (OpenCV axes)."""

    def __init__(self, normals: torch.Tensor, mask: torch.Tensor, camera: Camera, faces: torch.Tensor,
                 silhouette_weight: float = SILHOUETTE_WEIGHT, adjacency: MeshAdjacency | None = None):
        """normals: (H, W, 3) target unit normals in camera space; mask: (H, W) bool target
        coverage; faces: (F, 3) long on the normals' device."""
        self.normals = normals
        self.mask = mask.to(normals.dtype)
        self.camera = camera
        self.faces = faces
        self.silhouette_weight = silhouette_weight
        self.adjacency = adjacency if adjacency is not None else MeshAdjacency.from_faces(faces)
        self.count = float(mask.sum())

    def prepare(self, vertices: torch.Tensor, iteration: int) -> None:
        """Nothing to precompute: visibility is part of each call."""

    def __call__(self, vertices: torch.Tensor) -> dict[str, torch.Tensor]:
        fragments = rasterize(vertices, self.faces, self.camera)
        coverage = fragments.coverage(vertices.dtype)
        normals = normal_image(vertices, self.faces, fragments, self.camera, space="camera")
        both = coverage[..., 0] * self.mask
        normal = ((normals - self.normals).abs().sum(dim=-1) * both).sum() / both.sum().clamp_min(1.0)
        terms = {"normal": normal}
        if self.silhouette_weight:
            mask = silhouette_crossings(fragments, self.faces, self.adjacency).blend(coverage)[..., 0]
            terms["silhouette"] = self.silhouette_weight * (mask - self.mask).square().sum() / self.count
        return terms
