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
The total is ``normal + silhouette_weight · silhouette``. Visibility (which pixel shows which
triangle, where the silhouette pairs lie) is recomputed every call, or every ``visibility_every``
calls (``reset`` restarts the count): the calls in between draw the moved mesh at the pixels the
last refresh found (docs/method.md, "Visibility reused").
With a region (a mask over triangles), the normal term counts only the pixels that show a region
triangle.
"""
from __future__ import annotations

from typing import Sequence

import torch

from statfit.errors import StatfitError
from statfit.renderer import Camera, MeshAdjacency
from statfit.renderer.steady import SteadyRenderer
from statfit.objectives.weights import SILHOUETTE_WEIGHT

SPREAD = 1024       # partial sums per view on a GPU (per_view_sums)


class NormalMapObjective:
    """Data term of inverse rendering, in camera space (OpenCV axes).

    Rendered by :class:`statfit.renderer.steady.SteadyRenderer` (static shapes, no host reads in the
    steady state); the normal term is evaluated on the covered pixels only, the silhouette term over
    the whole (padded) image. Non-finite vertices cover no pixel and give a non-finite loss, which
    the loop's record step finds: its divergence check waits for the device at records only
    (``deferred_checks``).

    B views of one mesh topology (``normals`` (B, H, W, 3), one camera per view) are one term: the
    renderer draws B meshes (vertices (B, N, 3)) into B images stacked, each view's terms are
    normalised by its own counts, and the term is their sum, so each fit's gradient is what its own
    term gives it (:meth:`per_fit`: each view's terms).
    """

    deferred_checks = True

    def __init__(self, normals: torch.Tensor, mask: torch.Tensor, camera: Camera | Sequence[Camera],
                 faces: torch.Tensor, silhouette_weight: float = SILHOUETTE_WEIGHT,
                 adjacency: MeshAdjacency | None = None, region_faces: torch.Tensor | None = None,
                 one_sided: bool = False, covering: bool = False, visibility_every: int = 1,
                 visibility_moved: float | None = None):
        """normals: (H, W, 3) target unit normals in camera space, or (B, H, W, 3) for B views;
        mask: (H, W) or (B, H, W) bool target coverage; camera: one per view; faces: (F, 3) long on
        the normals' device; adjacency: ``MeshAdjacency.from_faces(faces)``, pass it to share it
        between objectives; region_faces: (F,) bool, the triangles whose pixels the normal term uses
        (all when None); one_sided, covering: the one-sided silhouette terms; visibility_every: calls
        per refresh of the visibility (1: every call); visibility_moved: pixels, refresh also in
        between once a vertex has moved this far since the last refresh (None: by the count alone)."""
        if isinstance(visibility_every, bool) or not isinstance(visibility_every, int) or visibility_every < 1:
            raise StatfitError(f"visibility_every must be a whole number of calls, 1 or more, got {visibility_every!r}")
        if visibility_moved is not None and not visibility_moved > 0:
            raise StatfitError(f"visibility_moved must be a number of pixels above 0, got {visibility_moved!r}")
        self.views = len(normals) if normals.dim() == 4 else None
        views = self.views or 1
        normals, mask = normals.view(views, *normals.shape[-3:]), mask.view(views, *mask.shape[-2:])
        self.mask = mask.to(normals.dtype)
        self.camera = camera
        self.faces = faces
        self.silhouette_weight = silhouette_weight
        self.one_sided, self.covering = one_sided, covering
        self.adjacency = adjacency if adjacency is not None else MeshAdjacency.from_faces(faces)
        counts = self.mask.sum(dim=(1, 2))                                                # (B,)
        self.count = float(counts.sum())
        self.region_faces = region_faces
        # The targets on the renderer's padded pixel grid (each image with one border pixel, stacked;
        # then a dump pixel and its neighbours): normals (3, E), mask (E,); region (BF+1,) per
        # triangle, 0 for "none"; with B views, each pixel's view (E,) (B: the dump) and the
        # silhouette's per-pixel weight (its view's 1 / count).
        height, width = mask.shape[1:]
        padded = normals.new_zeros(4, views, height + 2, width + 2)
        padded[:3, :, 1:-1, 1:-1] = normals.permute(3, 0, 1, 2)
        padded[3, :, 1:-1, 1:-1] = self.mask
        self._target = torch.nn.functional.pad(padded.view(4, -1), (0, width + 3))    # (4, E)
        self._region = torch.ones(views * len(faces) + 1, dtype=normals.dtype, device=normals.device)
        self._region[-1] = 0
        if region_faces is not None:
            self._region[:-1] = region_faces.to(normals.dtype).repeat(views)
        if self.views is not None:
            view_pixels = (height + 2) * (width + 2)
            self._view = torch.arange(views, device=normals.device).repeat_interleave(view_pixels)
            self._view = torch.nn.functional.pad(self._view, (0, width + 3), value=views)
            self._silhouette_scale = (silhouette_weight / counts.double()).repeat_interleave(view_pixels)
        self._renderer: SteadyRenderer | None = None
        self.visibility_every, self.visibility_moved = visibility_every, visibility_moved
        self._calls = 0

    @property
    def capturable(self) -> bool:
        """Whether a CUDA graph can capture a call (statfit.core.graphs): static shapes and no host
        reads, and every call the same program (the visibility refreshed every call)."""
        return self.visibility_every == 1

    def prepare(self, vertices: torch.Tensor, iteration: int) -> None:
        """Nothing to precompute: visibility is part of the calls (refreshed on their own count)."""

    def reset(self) -> None:
        """The next call refreshes the visibility (a new stage starts from a fresh view)."""
        self._calls = 0

    def replayed(self) -> bool:
        """After a replay of a captured call: whether the renderer's buffers were found too small
        (then the next call must run eagerly, to size them afresh)."""
        return self._renderer is not None and self._renderer.replayed()

    def __call__(self, vertices: torch.Tensor) -> dict[str, torch.Tensor]:
        """The terms (0-d) at ``vertices`` (N, 3), or (B, N, 3) for B views: the sums of the views'."""
        if self.views is None:
            return self._single(vertices)
        return {name: each.sum() for name, each in self._per_view(vertices).items()}

    def per_fit(self, vertices: torch.Tensor) -> list[dict[str, float]]:
        """Each view's terms and their total at ``vertices`` (B, N, 3), as its own objective gives them."""
        with torch.no_grad():
            terms = {name: each.tolist() for name, each in self._per_view(vertices, refresh=True).items()}
        views = [{name: values[b] for name, values in terms.items()} for b in range(self.views)]
        return [{**view, "total": sum(view.values())} for view in views]

    def _view_of(self, vertices: torch.Tensor, refresh: bool = False):
        """The renderer's view of ``vertices`` (made at the first call, for their dtype), its
        visibility refreshed where ``refresh`` or the count of calls says so."""
        if self._renderer is None or self._renderer.dtype != vertices.dtype:
            self._renderer = SteadyRenderer(self.faces, self.camera, self.adjacency, vertices.dtype,
                                            vertex_count=vertices.shape[-2])
            self._target = self._target.to(vertices.dtype)
            self._region = self._region.to(vertices.dtype)
            if self.views is not None:
                self._silhouette_scale = self._silhouette_scale.to(vertices.dtype)
        refresh = refresh or self._calls % self.visibility_every == 0
        self._calls += 1
        return self._renderer(vertices, refresh, self.visibility_moved)

    def _covered(self, view) -> tuple[torch.Tensor, torch.Tensor]:
        """The target's rows (4, M) at the view's covered pixels (before antialiasing), and whether
        the target covers them too and, with a region, they show one of its triangles (M,)."""
        with torch.no_grad():
            target = self._target.index_select(1, view.pixel)     # by columns: 2× faster on a CPU than by rows
            return target, target[3] * self._region.index_select(0, view.face)

    def _single(self, vertices: torch.Tensor) -> dict[str, torch.Tensor]:
        view = self._view_of(vertices)
        pixels = self._renderer.pixels
        target, both = self._covered(view)
        normals = view.blended_normals()                                                # (3, M)
        normal = ((normals - target[:3]).abs().sum(dim=0) * both).sum() / both.sum().clamp_min(1.0)
        terms = {"normal": normal}
        if self.silhouette_weight:
            coverage = view.blended_coverage(vertices.dtype)[:pixels]
            terms["silhouette"] = self._silhouette_difference(coverage - self._target[3, :pixels]).square().sum() \
                * (self.silhouette_weight / self.count)
        return terms

    def _per_view(self, vertices: torch.Tensor, refresh: bool = False) -> dict[str, torch.Tensor]:
        """Each view's terms (B,) at ``vertices`` (B, N, 3)."""
        view = self._view_of(vertices, refresh)
        pixels, views = self._renderer.pixels, self.views
        target, both = self._covered(view)
        with torch.no_grad():
            owner = self._view.index_select(0, view.pixel)                             # (M,) B: the dump
        error = (view.blended_normals() - target[:3]).abs().sum(dim=0) * both
        sums = per_view_sums(torch.stack([error, both]), owner, views + 1)
        terms = {"normal": sums[0, :views] / sums[1, :views].clamp_min(1.0)}
        if self.silhouette_weight:
            coverage = view.blended_coverage(vertices.dtype)[:pixels]
            squares = self._silhouette_difference(coverage - self._target[3, :pixels]).square()
            terms["silhouette"] = (squares * self._silhouette_scale).view(views, -1).sum(dim=1)
        return terms

    def _silhouette_difference(self, difference: torch.Tensor) -> torch.Tensor:
        """The coverage's difference from the mask as the silhouette term counts it (its sides)."""
        if self.one_sided:
            return difference.clamp_min(0.0)
        if self.covering:
            return difference.clamp_max(0.0)
        return difference


def per_view_sums(values: torch.Tensor, owner: torch.Tensor, owners: int, spread: int | None = None
                  ) -> torch.Tensor:
    """Σ values[:, i] over the lanes i of each owner: (C, owners), from values (C, L) and owner
    (L,), through ``spread`` partial sums per owner (default: ``SPREAD`` on a GPU, where CUDA's
    deterministic ``index_add`` adds each index's writes one after another, tens of thousands a
    view here; 1 on a CPU, which sums in lane order)."""
    spread = spread or (1 if owner.device.type == "cpu" else SPREAD)
    if spread == 1:
        return values.new_zeros(len(values), owners).index_add(1, owner, values)
    lane = owner * spread + torch.arange(len(owner), device=owner.device) % spread
    partial = values.new_zeros(len(values), owners * spread).index_add(1, lane, values)
    return partial.view(len(values), owners, spread).sum(dim=2)
