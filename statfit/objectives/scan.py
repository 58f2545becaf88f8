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


def masked_quantile(values: torch.Tensor, mask: torch.Tensor, q: float | torch.Tensor) -> torch.Tensor:
    """``torch.quantile(values[mask], q)`` (linear interpolation) bit for bit, as a (1,) tensor, without
    compacting: static shapes, no host wait (NaN when no value is masked in). ``values`` and ``mask``
    (..., M): one quantile per row, (..., 1)."""
    ordered = values.masked_fill(~mask, torch.inf).sort().values        # the masked-out last
    if not isinstance(q, torch.Tensor):   # (a tensor kept by the caller: no copy to the device each time)
        q = torch.tensor(q, dtype=values.dtype, device=values.device)
    ranks = q * (mask.sum(dim=-1, keepdim=True) - 1)                     # > −1: truncates to ≥ 0
    low = ranks.long()
    below, above = ordered.gather(-1, torch.cat([low, ranks.ceil().long()], dim=-1)).chunk(2, dim=-1)
    return below.lerp(above, ranks - low)


def masked_median(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``values[mask].median()`` (the lower of the two middle values) as a (1,) tensor, without
    compacting (+inf when no value is masked in). ``values`` and ``mask`` (..., M): one per row, (..., 1)."""
    ordered = values.masked_fill(~mask, torch.inf).sort().values
    middle = (mask.sum(dim=-1, keepdim=True) - 1).div(2, rounding_mode="floor").clamp_min_(0)
    return ordered.gather(-1, middle)


def attached_normals(vertices: torch.Tensor, corner_ids: torch.Tensor) -> torch.Tensor:
    """(M, 3) unit normals of the triangles whose corners ``corner_ids`` (3M,) are rows of ``vertices``."""
    a, b, c = vertices.index_select(0, corner_ids).view(-1, 3, 3).unbind(dim=1)
    return torch.nn.functional.normalize(torch.linalg.cross(b - a, c - a), dim=-1)


def counted(keep: torch.Tensor, dist: torch.Tensor, clutter: bool | torch.Tensor, agree: torch.Tensor | None,
            quantile: torch.Tensor | float | None) -> torch.Tensor:
    """Which attached points the data term counts, (..., M) bool, from those ``keep`` (..., M) leaves
    (off the open border, on the region) and their distances ``dist`` (..., M), per row: with
    ``clutter`` (a bool, or (..., 1) per row), only those whose normals ``agree`` (None: no normals)
    and within OUTLIER_SIGMAS robust deviations of the median; then, for a ``quantile`` (None: no
    trim), those within that quantile of the distances."""
    if clutter is not False:
        cluttered = keep if agree is None else keep & agree
        median = masked_median(dist, cluttered).double()
        cluttered = cluttered & (dist <= (OUTLIER_SIGMAS * 1.4826 * median).clamp_min(FLOOR))
        keep = cluttered if clutter is True else torch.where(clutter, cluttered, keep)
    if quantile is not None:
        keep = keep & (dist <= masked_quantile(dist, keep, quantile))
    return keep


def data_weights(keep: torch.Tensor, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """The data term's weights (M·, 1, 1) of the points ``keep`` (..., M) counts: 1/M' per counted
    point of its row for the value, 2/M' for the gradient (M' = 0: NaN, as the mean of nothing)."""
    share = keep.sum(dim=-1, keepdim=True).to(dtype).reciprocal()
    weights = keep.to(dtype)
    return (weights * share).view(-1, 1, 1), (weights * (2 * share)).view(-1, 1, 1)


class _PointToSurface(torch.autograd.Function):
    """The data term Σᵢ wᵢ ‖pᵢ − Σ_c b_ic x_{t_ic}‖² (wᵢ = 1/M' for the M' points kept, else 0) with
    its gradient written out: the same values as autograd's for the mean over the kept points, in a
    few whole-scan ops (static shapes: no boolean compaction, so no host wait on a GPU)."""

    @staticmethod
    def forward(ctx, vertices: torch.Tensor, objective: "ScanObjective") -> torch.Tensor:
        corners = vertices[objective._corner_rows]                                    # (M, 3, 3)
        attached = (corners * objective._bary_columns).sum(dim=1, keepdim=True)     # (M, 1, 3)
        residual = objective._points_rows - attached                                 # (M, 1, 3)
        ctx.residual, ctx.state = residual, objective._gradient_state()
        return (residual.square() * objective._mean_weights).sum()

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        corner_ids, neg_bary, grad_weights, zeros = ctx.state
        # 2 rᵢ / M' (the mean's and the square's factors, one rounding as autograd's), then −b_ic per corner
        scaled = ctx.residual * (grad_weights * grad)                                # (M, 1, 3)
        per_corner = (scaled * neg_bary).view(-1, 3)                                 # (3M, 3)
        return torch.index_add(zeros, 0, corner_ids, per_corner), None


class ScanObjective:
    """Mean squared point-to-surface distance of a scan (M, 3) to the mesh, in the fit frame;
    ``normals`` (M, 3) the scan's unit normals (any sign), if known; ``clutter`` turns on the rules
    for points that are not on the template (module docstring).

    A refresh decides which points count as a mask (no compaction), and the data term weighs them
    by it: every tensor keeps its shape from one refresh to the next, and neither the refresh nor an
    iteration waits for the device. The loss's gradient is bit for bit autograd's mean over the kept
    points; its value sums in another order (the last bits may differ)."""

    # The fitting loop may check for divergence at its record steps only: a refresh refuses
    # non-finite vertices itself (DivergenceError), and nothing else is hurt by them.
    deferred_checks = True

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
        self._refreshed_at: torch.Tensor | None = None
        self._zeros: torch.Tensor | None = None      # (N, 3), where the gradient is summed into
        self._normals: torch.Tensor | None = None
        self._points_rows = points.view(-1, 1, 3)
        self._host_points = points.detach().cpu().double().numpy()
        self._quantile = torch.tensor(1.0 - trim, dtype=points.dtype, device=points.device)

    def refresh(self, vertices: torch.Tensor) -> SurfacePoints:
        """Re-attach every scan point to its closest surface point."""
        vertices = vertices.detach() if vertices.requires_grad else vertices
        self.attachment = self.query(vertices, self.points, self._host_points)
        triangle, bary, dist = self.attachment.triangle, self.attachment.barycentric, self.attachment.distance
        self._corner_rows = self.faces.index_select(0, triangle)                     # (M, 3)
        self._corner_ids = self._corner_rows.view(-1)
        if self._zeros is None or self._zeros.shape != vertices.shape or self._zeros.dtype != vertices.dtype:
            self._zeros = vertices.new_zeros(vertices.shape)
        self._refreshed_at, self._normals = vertices, None
        on_border = (self.query.open_edges.index_select(0, triangle) & (bary < ON_EDGE)).any(dim=1)
        keep = ~on_border
        if self.region_faces is not None:
            keep &= self.region_faces.index_select(0, triangle)
        agree = None if not self.clutter or self.scan_normals is None else \
            (self.normals * self.scan_normals).sum(dim=-1).abs() >= NORMAL_COSINE
        q = self._quantile if self._quantile.dtype == dist.dtype else 1.0 - self.trim
        self._keep = keep = counted(keep, dist, self.clutter, agree, q if self.trim > 0 else None)
        self._mean_weights, self._grad_weights = data_weights(keep, dist.dtype)
        self._bary_columns = bary[:, :, None]
        self._neg_bary = bary.neg()[:, :, None]
        return self.attachment

    @property
    def normals(self) -> torch.Tensor:
        """(M, 3) unit normals of the triangles the points are attached to, at the last refresh."""
        if self._normals is None:
            self._normals = attached_normals(self._refreshed_at, self._corner_ids)
        return self._normals

    def _gradient_state(self) -> tuple[torch.Tensor, ...]:
        return self._corner_ids, self._neg_bary, self._grad_weights, self._zeros

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
        if vertices.requires_grad and torch.is_grad_enabled():
            return {"data": _PointToSurface.apply(vertices, self)}
        # a value only (Gauss–Newton's convergence test): the mean over the kept points, as ever
        residual = (self.points - self._attached(vertices))[self._keep]
        return {"data": residual.square().sum(dim=1).mean()}

    def residuals(self, vertices: torch.Tensor) -> torch.Tensor:
        """Point-to-plane residuals (M',) of the M' points kept: nᵢ·(pᵢ − sᵢ), with the attached
        triangle's normal nᵢ held from the refresh; affine in ``vertices`` (N, 3) between refreshes.
        The first-order model of the point-to-surface distance, for Gauss–Newton: unlike
        point-to-point residuals it lets the surface slide, so alternation converges in a few steps."""
        offset = (self.points - self._attached(vertices))[self._keep]
        return (offset * self.normals[self._keep]).sum(dim=-1)

    def residual_points(self) -> torch.Tensor:
        """(M', 3) the scan points of :meth:`residuals`' rows (those kept at the last refresh)."""
        return self.points[self._keep]

    def jacobian(self, directions: torch.Tensor) -> torch.Tensor:
        """∂residuals/∂c (M', K) for vertices moving along K ``directions`` stored vertex-major,
        (N, 3, K)."""
        ids = self._corner_ids.view(-1, 3)[self._keep].reshape(-1)
        rows = directions.index_select(0, ids).view(-1, 9, directions.shape[-1])       # (M', 3 corners × xyz, K)
        # residual i moves by −Σ_corners b_c n·Δx_c: one weight per (corner, axis), b_c n_axis
        weights = self.attachment.barycentric[self._keep][:, :, None] * self.normals[self._keep][:, None, :]
        return -torch.bmm(weights.reshape(-1, 1, 9), rows).squeeze(1)

    def pose_jacobian(self, centre: torch.Tensor) -> torch.Tensor:
        """∂residuals/∂(ω, t, σ) (M', 7) for the kept scan points moved by a small similarity about
        ``centre`` (3,): p ↦ p + ω × (p − centre) + t + σ (p − centre), the surface held."""
        offset = self.points[self._keep] - centre
        normals = self.normals[self._keep]
        return torch.cat([torch.linalg.cross(offset, normals), normals,
                          (offset * normals).sum(dim=-1, keepdim=True)], dim=-1)
