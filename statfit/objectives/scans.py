"""Many scans of one model as one data term: B registrations stepped together, one op for all B.

:class:`ScanBatch` is the sum over B fits of each fit's :class:`statfit.objectives.scan.ScanObjective`
term (and its :class:`statfit.objectives.landmarks.LandmarkObjective` term, where it has one), for
vertices (B, N, 3) of one topology. Each fit's points count as they would alone: attached to the
closest point of that fit's own surface, left out by the same rules (open border, region, clutter,
trim) with that fit's own median and quantile, weighed 1/M'_b over its own M'_b kept points. As
the fits' losses are summed and no parameter is shared, each fit's gradient is its own term's.

The scans' points are padded to the longest (B, M): a padded slot repeats its scan's first point
and never counts. A refresh reads the vertices from the device once for all B, builds one KD-tree
per fit on the host, and solves every fit's candidate triangles together
(:meth:`statfit.geometry.closest.ClosestPointQuery.many`); the rest is a few ops over (B, M).
"""
from __future__ import annotations

from typing import Sequence

import torch

from statfit.errors import StatfitError
from statfit.objectives.landmarks import LandmarkObjective
from statfit.objectives.scan import (NORMAL_COSINE, ON_EDGE, ScanObjective, _PointToSurface, attached_normals, counted,
                                     data_weights)


class ScanBatch:
    """The data terms of ``scans`` (B ScanObjectives of one query: one model topology, one
    ``trim`` and ``refresh_every``), and of their landmark terms (``landmarks``: one per scan, or
    None), as one objective of vertices (B, N, 3). ``with_landmarks(False)``: the same terms
    without the landmarks (a stage that fits the scan alone)."""

    deferred_checks = True

    def __init__(self, scans: Sequence[ScanObjective], landmarks: Sequence[LandmarkObjective | None] | None = None):
        first = scans[0]
        if any(s.query is not first.query or s.trim != first.trim or s.refresh_every != first.refresh_every
               for s in scans):
            raise StatfitError("the fits of one batch share the model's query, trim and refresh schedule")
        self.query, self.trim, self.refresh_every = first.query, first.trim, first.refresh_every
        self.fits = fits = len(scans)
        count = max(len(s.points) for s in scans)
        device, dtype = first.points.device, first.points.dtype

        def padded(rows: torch.Tensor) -> torch.Tensor:
            return torch.cat([rows, rows[:1].expand(count - len(rows), -1)])

        self.points = torch.stack([padded(s.points) for s in scans])                            # (B, M, 3)
        self._host_points = self.points.cpu().double().numpy()
        self._points_rows = self.points.view(-1, 1, 3)
        self._valid = (torch.arange(count, device=device)[None] <
                       torch.tensor([len(s.points) for s in scans], device=device)[:, None])    # (B, M)
        self._scan_normals = torch.stack([padded(s.scan_normals) if s.scan_normals is not None else
                                          torch.zeros(count, 3, dtype=dtype, device=device) for s in scans])
        self._no_normals = torch.tensor([[s.scan_normals is None] for s in scans], device=device)    # (B, 1)
        self._clutter = torch.tensor([[s.clutter] for s in scans], device=device)                 # (B, 1)
        self._any_clutter = any(s.clutter for s in scans)
        triangles = len(self.query.faces)
        self._open_edges = self.query.open_edges.repeat(fits, 1)                                  # (B·F, 3)
        self._region = None if all(s.region_faces is None for s in scans) else torch.cat(
            [s.region_faces if s.region_faces is not None else torch.ones(triangles, dtype=torch.bool, device=device)
             for s in scans])                                                                    # (B·F,)
        self._quantile = torch.tensor(1.0 - self.trim, dtype=dtype, device=device)
        self._landmarks = _StackedLandmarks.of(landmarks, self.query.num_vertices) \
            if landmarks is not None and any(each is not None for each in landmarks) else None
        self._use_landmarks = self._landmarks is not None
        self._faces = self.query.stacked_faces(fits)                                             # (B·F, 3)
        self.attachment = None
        self._keep: torch.Tensor | None = None
        self._zeros: torch.Tensor | None = None

    def with_landmarks(self, on: bool) -> ScanBatch:
        """This objective (the same correspondences) with or without its landmark terms."""
        self._use_landmarks = on and self._landmarks is not None
        return self

    def refresh(self, vertices: torch.Tensor) -> None:
        """Re-attach every fit's scan points to the closest point of that fit's surface
        (``vertices`` (B, N, 3)) and decide again which count."""
        vertices = vertices.detach() if vertices.requires_grad else vertices
        fits, count = self._valid.shape
        self.attachment = self.query.many(vertices, self.points, self._host_points)
        triangle, bary, dist = self.attachment.triangle, self.attachment.barycentric, self.attachment.distance
        self._corner_rows = self._faces.index_select(0, triangle)                                # (B·M, 3)
        self._corner_ids = self._corner_rows.view(-1)
        flat = vertices.reshape(-1, 3)
        if self._zeros is None or self._zeros.shape != flat.shape or self._zeros.dtype != flat.dtype:
            self._zeros = flat.new_zeros(flat.shape)
        on_border = (self._open_edges.index_select(0, triangle) & (bary < ON_EDGE)).any(dim=1)
        keep = self._valid & ~on_border.view(fits, count)
        if self._region is not None:
            keep &= self._region.index_select(0, triangle).view(fits, count)
        dist = dist.view(fits, count)
        agree = None
        if self._any_clutter:   # the clutter rules, on the fits that have them
            normals = attached_normals(flat, self._corner_ids).view(fits, count, 3)
            agree = ((normals * self._scan_normals).sum(dim=-1).abs() >= NORMAL_COSINE) | self._no_normals
        self._keep = keep = counted(keep, dist, self._clutter if self._any_clutter else False, agree,
                                    self._quantile if self.trim > 0 else None)
        self._mean_weights, self._grad_weights = data_weights(keep, dist.dtype)
        self._bary_columns = bary[:, :, None]
        self._neg_bary = bary.neg()[:, :, None]

    def _gradient_state(self) -> tuple[torch.Tensor, ...]:
        return self._corner_ids, self._neg_bary, self._grad_weights, self._zeros

    def kept(self) -> torch.Tensor:
        """(B,) how many of each fit's scan points count since the last refresh."""
        return self._keep.sum(dim=1)

    def reset(self) -> None:
        """Drop the attachments, so the next ``prepare`` recomputes them."""
        self.attachment = None

    def prepare(self, vertices: torch.Tensor, iteration: int) -> None:
        if self.attachment is None or iteration % self.refresh_every == 0:
            self.refresh(vertices)

    def per_fit(self, vertices: torch.Tensor) -> list[dict[str, float]]:
        """Each fit's terms at ``vertices`` (B, N, 3) with the last refresh's attachments, and their
        total (one host read)."""
        with torch.no_grad():
            flat = vertices.reshape(-1, 3)
            attached = (flat[self._corner_rows] * self._bary_columns).sum(dim=1, keepdim=True)
            data = ((self._points_rows - attached).square() * self._mean_weights).view(self.fits, -1).sum(dim=1)
            rows = [data]
            if self._use_landmarks:
                rows.append(self._landmarks.per_fit(flat, self.fits))
            values = torch.stack(rows, dim=1).tolist()
        has = [] if not self._use_landmarks else self._landmarks.present
        terms = [{"data": row[0], **({"landmarks": row[1]} if b in has else {})} for b, row in enumerate(values)]
        return [{**each, "total": sum(each.values())} for each in terms]

    def __call__(self, vertices: torch.Tensor) -> dict[str, torch.Tensor]:
        """The terms summed over the fits, of ``vertices`` (B, N, 3)."""
        flat = vertices.reshape(-1, 3)
        terms = {"data": _PointToSurface.apply(flat, self)}
        if self._use_landmarks:
            terms["landmarks"] = self._landmarks(flat)
        return terms


class _StackedLandmarks:
    """The landmark terms of several fits as one: Σ_b w_b mean_i ρ(‖x_{b,vᵢ} − t_{b,i}‖²)."""

    def __init__(self, indices: torch.Tensor, targets: torch.Tensor, weights: torch.Tensor, scale: float,
                 fit: torch.Tensor):
        self.indices, self.targets, self.weights, self.scale, self.fit = indices, targets, weights, scale, fit
        self.present = set(fit.tolist())

    @classmethod
    def of(cls, terms: Sequence[LandmarkObjective | None], vertices: int) -> _StackedLandmarks:
        """``terms`` (one per fit, None: none), on the fits' vertices stacked (B·N, 3), N = ``vertices``."""
        present = [(b, term) for b, term in enumerate(terms) if term is not None]
        scales = {term.scale for _, term in present}
        if len(scales) != 1:
            raise StatfitError("the landmark terms of one batch share their robust scale")
        indices = torch.cat([term.indices + b * int(vertices) for b, term in present])
        targets = torch.cat([term.targets for _, term in present])
        weights = torch.cat([torch.full((len(term.indices),), term.weight / len(term.indices),
                                        dtype=term.targets.dtype, device=term.targets.device) for _, term in present])
        fit = torch.cat([torch.full((len(term.indices),), b, device=term.indices.device) for b, term in present])
        return cls(indices, targets, weights, scales.pop(), fit)

    def _weighted(self, flat: torch.Tensor) -> torch.Tensor:
        d2 = (flat.index_select(0, self.indices) - self.targets).square().sum(dim=-1)
        s2 = self.scale**2
        return self.weights * (s2 * d2 / (s2 + d2))

    def __call__(self, flat: torch.Tensor) -> torch.Tensor:
        return self._weighted(flat).sum()

    def per_fit(self, flat: torch.Tensor, fits: int) -> torch.Tensor:
        """(B,) each fit's term (0 for a fit without landmarks)."""
        weighted = self._weighted(flat)
        return weighted.new_zeros(fits).index_add_(0, self.fit, weighted)

