"""Point-to-surface registration term with periodically refreshed correspondences.

Each scan point is attached to its closest point on the current surface (a triangle and
barycentric coordinates); the residual is ``p − Σ bᵢ x_{tᵢ}``. At a refresh this is exactly the
point-to-surface distance and its gradient (envelope theorem); between refreshes the attachment
is held.

Robustness against what a real scan holds beyond the template (neck, shoulders, hair, background):
at a refresh a point counts only where its closest point is not on the template's open boundary (a
point beyond the border clamps there); with ``clutter``, also only where its normal agrees with the
surface's up to sign (within 60°) and its distance is within OUTLIER_SIGMAS robust standard
deviations (1.4826 × the median distance of the points left, at least FLOOR). Then the ``1 − trim``
quantile of the farthest is left out too, until the next refresh. The clutter rules cost a fit of a
clean scan with a large expression (the expression's points are far at first, like clutter: +23% on
the ICT jaw-open case), so they are for scans that hold clutter (:mod:`statfit.registration`). With a region (a mask over triangles), points are still attached
to the closest point of the whole surface, and only those that land on a region triangle count:
scan points of other parts (hair, shoulders) neither pull the region nor the rest.
"""
from __future__ import annotations

import torch

from statfit.geometry.closest import ClosestPointQuery, SurfacePoints


# A point farther than this many robust standard deviations of the distances is not on the template.
OUTLIER_SIGMAS = 3.0
# ... unless it is closer than this (fit-frame units: template RMS radii), so a near-perfect fit keeps its points.
FLOOR = 0.01
# |cos| between a point's normal and the surface's below which the point is not on the template (60°).
NORMAL_COSINE = 0.5
# A barycentric coordinate below this puts the closest point on the opposite edge.
ON_EDGE = 1e-6


class ScanObjective:
    """Mean squared point-to-surface distance of a scan (M, 3) to the mesh, in the fit frame;
    ``normals`` (M, 3) the scan's unit normals (any sign), if known; ``clutter`` turns on the rules
    for points that are not on the template (module docstring)."""

    def __init__(self, points: torch.Tensor, query: ClosestPointQuery, refresh_every: int = 10,
                 trim: float = 0.05, region_faces: torch.Tensor | None = None,
                 normals: torch.Tensor | None = None, clutter: bool = False):
        self.points = points
        self.scan_normals = normals
        self.clutter = clutter
        self.query = query
        self.refresh_every = max(1, refresh_every)
        self.trim = trim
        self.faces = query.faces
        self.region_faces = region_faces  # (F,) bool: triangles whose points count, or None for all
        self.attachment: SurfacePoints | None = None
        self._keep: torch.Tensor | None = None
        self._corner_ids: torch.Tensor | None = None
        self._normals: torch.Tensor | None = None

    def refresh(self, vertices: torch.Tensor) -> SurfacePoints:
        """Re-attach every scan point to its closest surface point."""
        self.attachment = self.query(vertices.detach(), self.points)
        self._corner_ids = self.faces[self.attachment.triangle].reshape(-1)
        dist = self.attachment.distance
        self._keep = torch.ones_like(dist, dtype=torch.bool)
        if self.region_faces is not None:
            self._keep = self.region_faces[self.attachment.triangle]
        a, b, c = vertices.detach().index_select(0, self._corner_ids).view(-1, 3, 3).unbind(dim=1)
        normals = torch.nn.functional.normalize(torch.linalg.cross(b - a, c - a), dim=-1)   # (M, 3)
        on_border = self.query.open_edges[self.attachment.triangle] & (self.attachment.barycentric < ON_EDGE)
        self._keep &= ~on_border.any(dim=1)
        if self.clutter:
            if self.scan_normals is not None:
                self._keep &= (normals * self.scan_normals).sum(dim=-1).abs() >= NORMAL_COSINE
            if self._keep.any():
                self._keep &= dist <= max(OUTLIER_SIGMAS * 1.4826 * float(dist[self._keep].median()), FLOOR)
        if self.trim > 0 and self._keep.any():
            self._keep &= dist <= torch.quantile(dist[self._keep], 1.0 - self.trim)
        self._normals = normals[self._keep]                                                  # (M', 3)
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

    def _attached(self, vertices: torch.Tensor) -> torch.Tensor:
        """The attached surface points (..., M, 3) of ``vertices`` (..., N, 3)."""
        # index_select's backward (index_add) is deterministic on the CPU; advanced indexing's is not.
        corners = vertices.index_select(-2, self._corner_ids).view(*vertices.shape[:-2], -1, 3, 3)
        return (corners * self.attachment.barycentric[..., None]).sum(dim=-2)

    def __call__(self, vertices: torch.Tensor) -> dict[str, torch.Tensor]:
        residual = (self.points - self._attached(vertices))[self._keep]
        return {"data": residual.square().sum(dim=1).mean()}

    def residuals(self, vertices: torch.Tensor) -> torch.Tensor:
        """Point-to-plane residuals (M',) of the M' points kept: nᵢ·(pᵢ − sᵢ), with the attached
        triangle's normal nᵢ held from the refresh; affine in ``vertices`` (N, 3) between refreshes.
        The first-order model of the point-to-surface distance, for Gauss–Newton: unlike
        point-to-point residuals it lets the surface slide, so alternation converges in a few steps."""
        offset = (self.points - self._attached(vertices))[self._keep]
        return (offset * self._normals).sum(dim=-1)

    def jacobian(self, directions: torch.Tensor) -> torch.Tensor:
        """∂residuals/∂c (M', K) for vertices moving along K ``directions`` stored vertex-major,
        (N, 3, K)."""
        ids = self._corner_ids.view(-1, 3)[self._keep].reshape(-1)
        rows = directions.index_select(0, ids).view(-1, 9, directions.shape[-1])       # (M', 3 corners × xyz, K)
        # residual i moves by −Σ_corners b_c n·Δx_c: one weight per (corner, axis), b_c n_axis
        weights = self.attachment.barycentric[self._keep][:, :, None] * self._normals[:, None, :]
        return -torch.bmm(weights.reshape(-1, 1, 9), rows).squeeze(1)

    def pose_jacobian(self, centre: torch.Tensor) -> torch.Tensor:
        """∂residuals/∂(ω, t, σ) (M', 7) for the kept scan points moved by a small similarity about
        ``centre`` (3,): p ↦ p + ω × (p − centre) + t + σ (p − centre), the surface held."""
        offset = self.points[self._keep] - centre
        return torch.cat([torch.linalg.cross(offset, self._normals), self._normals,
                          (offset * self._normals).sum(dim=-1, keepdim=True)], dim=-1)
