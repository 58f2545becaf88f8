"""Normal-map term: match rendered normals and silhouette to an observed normal map.

normal: mean over the pixels covered by both the target and the rendering of ``‖n − n̂‖₁``
(sum of absolute component differences, camera space); the rendered normals are interpolated
from the vertex normals of the current mesh and antialiased at silhouette edges, so the term is
differentiable through them and through the position of every occluding outline — an arm's over
the torso as well as the body's against the background (as nvdiffrast antialiases a shaded
image; plain rasterisation gives an edge inside the mask no gradient, so a normal map could only
bend a misplaced limb, never move it: docs/studies.md §13).
silhouette: ``Σ (m − m̂)² / |target|`` over all pixels, where ``m`` is the rendered coverage
antialiased at silhouette edges (its only gradients), ``m̂`` the target mask.
The total is ``normal + silhouette_weight · silhouette``. Visibility is recomputed every call.
With a region (a mask over triangles), the normal term counts only the pixels that show a region
triangle.
"""
from __future__ import annotations

import torch

from statfit.renderer import Camera, MeshAdjacency, fragment_normals, rasterize, silhouette_crossings

SILHOUETTE_WEIGHT = 1.0


class NormalMapObjective:
    """Data term of inverse rendering, in camera space (OpenCV axes)."""

    def __init__(self, normals: torch.Tensor, mask: torch.Tensor, camera: Camera, faces: torch.Tensor,
                 silhouette_weight: float = SILHOUETTE_WEIGHT, adjacency: MeshAdjacency | None = None,
                 region_faces: torch.Tensor | None = None):
        """normals: (H, W, 3) target unit normals in camera space; mask: (H, W) bool target
        coverage; faces: (F, 3) long on the normals' device; adjacency: ``MeshAdjacency.from_faces(faces)``,
        pass it to share it between objectives; region_faces: (F,) bool, the triangles whose pixels
        the normal term uses (all when None)."""
        self.mask = mask.to(normals.dtype)
        # Per-pixel lookups of the target at the covered pixels: normals (3, H·W), mask (H·W,).
        self._normals_by_pixel = normals.reshape(-1, 3).T.contiguous()
        self._mask_by_pixel = self.mask.reshape(-1)
        self.camera = camera
        self.faces = faces
        self.silhouette_weight = silhouette_weight
        self.adjacency = adjacency if adjacency is not None else MeshAdjacency.from_faces(faces)
        self.count = float(mask.sum())
        self.region_faces = region_faces

    def prepare(self, vertices: torch.Tensor, iteration: int) -> None:
        """Nothing to precompute: visibility is part of each call."""

    def reset(self) -> None:
        """Nothing is kept between calls."""

    def __call__(self, vertices: torch.Tensor) -> dict[str, torch.Tensor]:
        fragments = rasterize(vertices, self.faces, self.camera)
        crossings = silhouette_crossings(fragments, self.faces, self.adjacency)
        # The normal term is evaluated on the covered pixels only (C, M), never on the whole image.
        normals = fragment_normals(vertices, self.faces, fragments, self.camera)                 # (3, M)
        normals = crossings.blend_covered(normals.T, fragments.pixel).T
        target = self._normals_by_pixel.index_select(1, fragments.pixel)
        both = self._mask_by_pixel.index_select(0, fragments.pixel)
        if self.region_faces is not None:
            both = both * self.region_faces.index_select(0, fragments.face).to(both.dtype)
        normal = ((normals - target).abs().sum(dim=0) * both).sum() / both.sum().clamp_min(1.0)
        terms = {"normal": normal}
        if self.silhouette_weight:
            mask = crossings.blend(fragments.coverage(vertices.dtype))[..., 0]
            terms["silhouette"] = self.silhouette_weight * (mask - self.mask).square().sum() / self.count
        return terms
