"""Parametrisations of the vertices x (N, 3): each maps its parameters to x and pulls ∂loss/∂x
back onto them. All maps are linear, so the pull-back is one explicit product, no autograd graph.

- FilteredVertices:    x = x0 + F u          (F: identity, Laplacian, statistical, hybrid; u₀ = 0)
- PCACoefficients:     x = x̄ + B c,  B = U diag(std)
- RegularizedVertices: x free, prior β/N ‖(I − UUᵀ)(x − x̄)‖²

``x = x0 + F u`` with u₀ = 0 follows the same trajectory as Nicolet et al.'s ``x = F u`` with
u₀ = F⁻¹x0 (the map is linear and the optimiser sees only gradients), without ever needing F⁻¹.
"""
from __future__ import annotations

from typing import Callable

import torch

Filter = Callable[[torch.Tensor], torch.Tensor]


class FilteredVertices:
    """x = x0 + F u; ∂/∂u = F ∂/∂x (F symmetric)."""

    def __init__(self, x0: torch.Tensor, filter: Filter):
        self.x0 = x0
        self.filter = filter
        self.u = torch.zeros_like(x0, requires_grad=True)

    def parameters(self) -> list[torch.Tensor]:
        return [self.u]

    def vertices(self) -> torch.Tensor:
        with torch.no_grad():
            return self.x0 + self.filter(self.u)

    def pull_gradient(self, grad_x: torch.Tensor, x: torch.Tensor) -> dict[str, float]:
        self.u.grad = self.filter(grad_x)
        return {}


class PCACoefficients:
    """x = x̄ + B c with ``basis_t`` = Bᵀ (K, 3N); c starts at ``coeffs`` (default 0)."""

    def __init__(self, mean: torch.Tensor, basis_t: torch.Tensor, coeffs: torch.Tensor | None = None):
        self.mean = mean
        self.basis_t = basis_t.contiguous()
        start = torch.zeros(basis_t.shape[0], dtype=mean.dtype, device=mean.device) if coeffs is None else coeffs
        self.coeffs = start.detach().clone().requires_grad_(True)

    def parameters(self) -> list[torch.Tensor]:
        return [self.coeffs]

    def vertices(self) -> torch.Tensor:
        with torch.no_grad():
            return self.mean + torch.mv(self.basis_t.t(), self.coeffs).view_as(self.mean)

    def pull_gradient(self, grad_x: torch.Tensor, x: torch.Tensor) -> dict[str, float]:
        self.coeffs.grad = torch.mv(self.basis_t, grad_x.reshape(-1))
        return {}


class RegularizedVertices:
    """Free vertices with the prior β/N ‖(I − UUᵀ)(x − x̄)‖² (``basis_t`` = Uᵀ, (K, 3N))."""

    def __init__(self, x0: torch.Tensor, mean: torch.Tensor, basis_t: torch.Tensor, beta: float):
        self.x = x0.detach().clone().requires_grad_(True)
        self.mean = mean
        self.basis_t = basis_t.contiguous()
        self.weight = beta / x0.shape[0]

    def parameters(self) -> list[torch.Tensor]:
        return [self.x]

    def vertices(self) -> torch.Tensor:
        return self.x.detach()

    def pull_gradient(self, grad_x: torch.Tensor, x: torch.Tensor) -> dict[str, float]:
        offset = (x.detach() - self.mean).reshape(-1)
        outside = offset - torch.mv(self.basis_t.t(), torch.mv(self.basis_t, offset))
        self.x.grad = grad_x + (2 * self.weight * outside).view_as(grad_x)
        return {"prior": float(self.weight * outside.square().sum())}
