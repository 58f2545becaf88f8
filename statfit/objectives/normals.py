"""Normal-map term: match rendered normals and silhouette to an observed normal map.

normal: mean over the pixels covered by both the target and the rendering of ``‖n − n̂‖₁``
(sum of absolute component differences, camera space); the rendered normals are interpolated
from the vertex normals of the current mesh and antialiased at silhouette edges, so the term is
differentiable through them and through the position of every occluding outline — an arm's over
the torso as well as the body's against the background (as nvdiffrast antialiases a shaded
image; plain rasterisation gives an edge inside the mask no gradient, so a normal map could only
bend a misplaced limb, never move it: docs/studies.md §13).
silhouette: ``Σ (m − m̂)² / |target|`` over all pixels, where ``m`` is the rendered coverage
antialiased at silhouette edges (its only gradients), ``m̂`` the target mask; one-sided,
``Σ max(m − m̂, 0)² / |target|``: only coverage outside the target counts (for a model of part of
what the map shows, a face mask in a map of a head, whose outline is not the subject's); covering,
``Σ max(m̂ − m, 0)² / |target|``: only target the model leaves uncovered counts (for a map of part of
the model, a face cut out of a photo fitted with a head).
The total is ``normal + silhouette_weight · silhouette``. Visibility is recomputed every call.
With a region (a mask over triangles), the normal term counts only the pixels that show a region
triangle.
"""
from __future__ import annotations

import torch

from statfit.renderer import Camera, MeshAdjacency
from statfit.renderer.steady import SteadyRenderer

SILHOUETTE_WEIGHT = 1.0


class NormalMapObjective:
    """Data term of inverse rendering, in camera space (OpenCV axes).

    Rendered by :class:`statfit.renderer.steady.SteadyRenderer` (static shapes, no host reads in the
    steady state); the normal term is evaluated on the covered pixels only, the silhouette term over
    the whole (padded) image. Non-finite vertices cover no pixel and give a non-finite loss, which
    the loop's record step finds: its divergence check waits for the device at records only
    (``deferred_checks``).
    """

    deferred_checks = True
    capturable = True       # static shapes, no host reads: a CUDA graph can capture it (statfit.core.graphs)

    def __init__(self, normals: torch.Tensor, mask: torch.Tensor, camera: Camera, faces: torch.Tensor,
                 silhouette_weight: float = SILHOUETTE_WEIGHT, adjacency: MeshAdjacency | None = None,
                 region_faces: torch.Tensor | None = None, one_sided: bool = False, covering: bool = False):
        """normals: (H, W, 3) target unit normals in camera space; mask: (H, W) bool target
        coverage; faces: (F, 3) long on the normals' device; adjacency: ``MeshAdjacency.from_faces(faces)``,
        pass it to share it between objectives; region_faces: (F,) bool, the triangles whose pixels
        the normal term uses (all when None); one_sided, covering: the one-sided silhouette terms."""
        self.mask = mask.to(normals.dtype)
        self.camera = camera
        self.faces = faces
        self.silhouette_weight = silhouette_weight
        self.one_sided, self.covering = one_sided, covering
        self.adjacency = adjacency if adjacency is not None else MeshAdjacency.from_faces(faces)
        self.count = float(mask.sum())
        self.region_faces = region_faces
        # The target on the renderer's padded pixel grid (one border pixel, then a dump pixel and
        # its neighbours): normals (3, E), mask (E,); region (F+1,) per triangle, 0 for "none".
        height, width = mask.shape
        padded = normals.new_zeros(4, height + 2, width + 2)
        padded[:3, 1:-1, 1:-1] = normals.permute(2, 0, 1)
        padded[3, 1:-1, 1:-1] = self.mask
        self._target = torch.nn.functional.pad(padded.view(4, -1), (0, width + 3))    # (4, E)
        self._target_rows = self._target.T.contiguous()                                 # (E, 4)
        self._region = torch.ones(len(faces) + 1, dtype=normals.dtype, device=normals.device)
        self._region[-1] = 0
        if region_faces is not None:
            self._region[:-1] = region_faces.to(normals.dtype)
        self._renderer: SteadyRenderer | None = None

    def prepare(self, vertices: torch.Tensor, iteration: int) -> None:
        """Nothing to precompute: visibility is part of each call."""

    def reset(self) -> None:
        """Nothing is kept between calls (the renderer's buffers are sizes, not state)."""

    def replayed(self) -> bool:
        """After a replay of a captured call: whether the renderer's buffers were found too small
        (then the next call must run eagerly, to size them afresh)."""
        return self._renderer is not None and self._renderer.replayed()

    def __call__(self, vertices: torch.Tensor) -> dict[str, torch.Tensor]:
        if self._renderer is None or self._renderer.dtype != vertices.dtype:
            self._renderer = SteadyRenderer(self.faces, self.camera, self.adjacency, vertices.dtype)
            self._target = self._target.to(vertices.dtype)
            self._target_rows = self._target_rows.to(vertices.dtype)
            self._region = self._region.to(vertices.dtype)
        view = self._renderer(vertices)
        pixels = self._renderer.pixels
        with torch.no_grad():
            # The covered pixels (before antialiasing) that the target covers too and, with a
            # region, that show one of its triangles; the target's normals there.
            target = self._target_rows.index_select(0, view.pixel).T                   # (4, M)
            both = target[3] * self._region.index_select(0, view.face)
        normals = view.blended_normals()                                                # (3, M)
        normal = ((normals - target[:3]).abs().sum(dim=0) * both).sum() / both.sum().clamp_min(1.0)
        terms = {"normal": normal}
        if self.silhouette_weight:
            coverage = view.blended_coverage(len(self.faces), vertices.dtype)[:pixels]
            difference = coverage - self._target[3, :pixels]
            if self.one_sided:
                difference = difference.clamp_min(0.0)
            elif self.covering:
                difference = difference.clamp_max(0.0)
            terms["silhouette"] = difference.square().sum() * (self.silhouette_weight / self.count)
        return terms
