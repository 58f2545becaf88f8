"""Landmarks as a fit term: the model's landmark vertices pulled to the scan's landmarks for the
whole fit, robustly, so that one misplaced landmark cannot drag the face.

The term is ``weight · mean_i ρ(‖x_{vᵢ} − tᵢ‖²)`` with the Geman–McClure ρ(d²) = s²d² / (s² + d²):
quadratic for landmarks within ``s`` of their target, bounded (gradient → 0) beyond, so a landmark
several ``s`` away is in effect ignored. ``s`` is in fit-frame units (the model's RMS radius is 1):
the default 0.05 is about 5 mm on a head.

For the Gauss–Newton stage, :class:`WithLandmarks` stacks the scan's point-to-plane residuals and
the landmarks' point-to-point residuals, the latter reweighted at each refresh (iteratively
reweighted least squares on ρ) and scaled by the scan's point count, so that both pull as in the
gradient-based loss (mean over scan points + weight × mean over landmarks).
"""
from __future__ import annotations

import torch

ROBUST_SCALE = 0.05


class LandmarkObjective:
    """Robust squared distance of the landmark vertices ``indices`` (L,) to ``targets`` (L, 3)."""

    def __init__(self, indices: torch.Tensor, targets: torch.Tensor, weight: float, scale: float = ROBUST_SCALE):
        self.indices = indices
        self.targets = targets
        self.weight = weight
        self.scale = scale
        self._irls: torch.Tensor | None = None  # (L,) ρ'(d²) at the last refresh

    def squared_distances(self, vertices: torch.Tensor) -> torch.Tensor:
        """(L,) squared distance of each landmark vertex to its target."""
        return (vertices.index_select(0, self.indices) - self.targets).square().sum(dim=-1)

    def __call__(self, vertices: torch.Tensor) -> dict[str, torch.Tensor]:
        d2 = self.squared_distances(vertices)
        s2 = self.scale**2
        return {"landmarks": self.weight * (s2 * d2 / (s2 + d2)).mean()}

    def refresh(self, vertices: torch.Tensor) -> None:
        """Hold the robust weights ρ'(d²) = s⁴ / (s² + d²)² of the current distances (for Gauss–Newton)."""
        s2 = self.scale**2
        self._irls = s2**2 / (s2 + self.squared_distances(vertices.detach())).square()

    def residuals(self, vertices: torch.Tensor, per: float) -> torch.Tensor:
        """(3L,) residuals weighted by ρ' at the last refresh: there, the gradient of their sum of
        squares is that of ``per`` × the term (iteratively reweighted least squares)."""
        factor = (self.weight * per / len(self.indices) * self._irls).sqrt()[:, None]
        return (factor * (self.targets - vertices.index_select(0, self.indices))).reshape(-1)

    def jacobian(self, directions: torch.Tensor, per: float) -> torch.Tensor:
        """∂residuals/∂c (3L, K) for vertices moving along ``directions`` (N, 3, K)."""
        factor = (self.weight * per / len(self.indices) * self._irls).sqrt()[:, None, None]
        return -(factor * directions.index_select(0, self.indices)).reshape(-1, directions.shape[-1])


class WithLandmarks:
    """A scan objective plus a landmark term: one objective for the fitting loop and for
    Gauss–Newton (the scan's residuals first, then the landmarks', weighted per scan point)."""

    def __init__(self, scan, landmarks: LandmarkObjective):
        self.scan = scan
        self.landmarks = landmarks

    def prepare(self, vertices: torch.Tensor, iteration: int) -> None:
        self.scan.prepare(vertices, iteration)

    def reset(self) -> None:
        self.scan.reset()

    def __call__(self, vertices: torch.Tensor) -> dict[str, torch.Tensor]:
        return self.scan(vertices) | self.landmarks(vertices)

    def refresh(self, vertices: torch.Tensor):
        self.landmarks.refresh(vertices)
        return self.scan.refresh(vertices)

    def residuals(self, vertices: torch.Tensor) -> torch.Tensor:
        return torch.cat([self.scan.residuals(vertices), self.landmarks.residuals(vertices, self.scan.kept)])

    def jacobian(self, directions: torch.Tensor) -> torch.Tensor:
        return torch.cat([self.scan.jacobian(directions), self.landmarks.jacobian(directions, self.scan.kept)])
