"""Point-to-surface registration term with periodically refreshed correspondences.

Each scan point is attached to its closest point on the current surface (a triangle and
barycentric coordinates); the residual is ``p − Σ bᵢ x_{tᵢ}``. At a refresh this is exactly the
point-to-surface distance and its gradient (envelope theorem); between refreshes the attachment
is held. Robustness: the points whose distance lies above the ``1 − trim`` quantile at a refresh
are left out until the next one. With a region (a mask over triangles), points are still attached
to the closest point of the whole surface, and only those that land on a region triangle count:
scan points of other parts (hair, shoulders) neither pull the region nor the rest.
"""
from __future__ import annotations

import torch

from statfit.closest import ClosestPointQuery, SurfacePoints


class ScanObjective:
    """Mean squared point-to-surface distance of a scan (M, 3) to the mesh, in the fit frame."""

    def __init__(self, points: torch.Tensor, query: ClosestPointQuery, refresh_every: int = 10,
                 trim: float = 0.05, region_faces: torch.Tensor | None = None):
        self.points = points
        self.query = query
        self.refresh_every = max(1, refresh_every)
        self.trim = trim
        self.faces = query.faces
        self.region_faces = region_faces  # (F,) bool: triangles whose points count, or None for all
        self.attachment: SurfacePoints | None = None
        self._keep: torch.Tensor | None = None
        self._corner_ids: torch.Tensor | None = None

    def refresh(self, vertices: torch.Tensor) -> SurfacePoints:
        """Re-attach every scan point to its closest surface point."""
        self.attachment = self.query(vertices.detach(), self.points)
        self._corner_ids = self.faces[self.attachment.triangle].reshape(-1)
        dist = self.attachment.distance
        self._keep = torch.ones_like(dist, dtype=torch.bool)
        if self.region_faces is not None:
            self._keep = self.region_faces[self.attachment.triangle]
        if self.trim > 0 and self._keep.any():
            self._keep &= dist <= torch.quantile(dist[self._keep], 1.0 - self.trim)
        return self.attachment

    @property
    def kept(self) -> int:
        """How many scan points the data term uses since the last refresh."""
        return int(self._keep.sum())

    def reset(self) -> None:
        """Drop the attachments, so the next ``prepare`` recomputes them."""
        self.attachment = None

    def prepare(self, vertices: torch.Tensor, iteration: int) -> None:
        if self.attachment is None or iteration % self.refresh_every == 0:
            self.refresh(vertices)

    def __call__(self, vertices: torch.Tensor) -> dict[str, torch.Tensor]:
        # index_select's backward (index_add) is deterministic on the CPU; advanced indexing's is not.
        corners = vertices.index_select(0, self._corner_ids).view(-1, 3, 3)      # (M, 3, 3)
        surface = (corners * self.attachment.barycentric[..., None]).sum(dim=1)
        residual = (self.points - surface)[self._keep]
        return {"data": residual.square().sum(dim=1).mean()}
