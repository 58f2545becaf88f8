"""Parametrisations of the vertices x (N, 3): differentiable maps from their parameters to x, so any
torch loss on x drives them through ``loss.backward()``.

- FilteredVertices:    x = x0 + F u          (F: identity, Laplacian, statistical, hybrid; u₀ = 0)
- PCACoefficients:     x = x̄ + B c,  B = U diag(std)
- RegularizedVertices: x free, prior β/N ‖(I − UUᵀ)(x − x̄)‖² (gradient in the vertices' backward)

``capturable``: whether a CUDA graph can capture ``vertices()`` (its filter's, for FilteredVertices).

Every map is linear, so each is one autograd function whose backward is one explicit product
(the filter again, F being symmetric; Bᵀ for the coefficients): no graph of the filter's inner
operations is kept. ``x = x0 + F u`` with u₀ = 0 follows the same trajectory as Nicolet et al.'s
``x = F u`` with u₀ = F⁻¹x0 (the map is linear and the optimiser sees only gradients), without
ever needing F⁻¹.
"""
from __future__ import annotations

from typing import Callable

import torch

from statfit.core.matvec import expand, project

Filter = Callable[[torch.Tensor], torch.Tensor]


class _LinearMap(torch.autograd.Function):
    """y = A(u) for a linear map given as ``forward`` and its adjoint ``adjoint`` (Aᵀ)."""

    @staticmethod
    def forward(ctx, u: torch.Tensor, forward: Filter, adjoint: Filter) -> torch.Tensor:
        ctx.adjoint = adjoint
        return forward(u)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        return ctx.adjoint(grad), None, None


def linear_map(u: torch.Tensor, forward: Filter, adjoint: Filter) -> torch.Tensor:
    """``forward(u)``, differentiable: the gradient w.r.t. ``u`` is ``adjoint(grad)``."""
    return _LinearMap.apply(u, forward, adjoint)


def filtered(u: torch.Tensor, filter: Filter) -> torch.Tensor:
    """F u for a symmetric filter F (any of :mod:`statfit.core.filters`), differentiable: ∂/∂u = F ∂/∂(Fu)."""
    return linear_map(u, filter, filter)


class _SubspacePrior(torch.autograd.Function):
    """Passes x through and reports w ‖(I − UUᵀ)(x − x̄)‖² (``basis_t`` = Uᵀ); the backward adds the
    prior's gradient 2w (I − UUᵀ)(x − x̄) to the loss's gradient once every use of x in the loss is
    summed (the explicit form, so the sum is the same whatever the loss's graph)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, mean: torch.Tensor, basis_t: torch.Tensor, weight: float):
        offset = (x - mean).reshape(-1)
        outside = expand(basis_t, project(basis_t, offset).neg_(), offset)
        ctx.save_for_backward(outside)
        ctx.weight = weight
        value = weight * outside.square().sum()
        ctx.mark_non_differentiable(value)
        return x.clone(), value

    @staticmethod
    def backward(ctx, grad: torch.Tensor, _):
        (outside,) = ctx.saved_tensors
        return grad + (2 * ctx.weight * outside).view_as(grad), None, None, None


class FilteredVertices:
    """x = x0 + F u."""

    def __init__(self, x0: torch.Tensor, filter: Filter):
        self.x0 = x0
        self.filter = filter
        self.u = torch.zeros_like(x0, requires_grad=True)
        self.capturable = bool(getattr(filter, "capturable", False))

    def parameters(self) -> list[torch.Tensor]:
        return [self.u]

    def vertices(self) -> torch.Tensor:
        return self.x0 + filtered(self.u, self.filter)

    def prior(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        return {}


class PCACoefficients:
    """x = x̄ + B c with ``basis_t`` = Bᵀ (K, 3N); c starts at ``coeffs`` (default 0); ``prior``
    w adds the term w · mean(c²) (c in standard deviations when B holds them)."""

    capturable = True

    def __init__(self, mean: torch.Tensor, basis_t: torch.Tensor, coeffs: torch.Tensor | None = None,
                 prior: float = 0.0):
        self.mean = mean
        self.basis_t = basis_t.contiguous()
        start = torch.zeros(basis_t.shape[0], dtype=mean.dtype, device=mean.device) if coeffs is None else coeffs
        self.coeffs = start.detach().clone().requires_grad_(True)
        self.prior_weight = prior

    def parameters(self) -> list[torch.Tensor]:
        return [self.coeffs]

    def vertices(self) -> torch.Tensor:
        return self.mean + linear_map(self.coeffs, self._shape, self._coefficients)

    def prior(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        return {"prior": self.prior_weight * self.coeffs.square().mean()} if self.prior_weight else {}

    def _shape(self, coeffs: torch.Tensor) -> torch.Tensor:
        return expand(self.basis_t, coeffs).view_as(self.mean)

    def _coefficients(self, grad_x: torch.Tensor) -> torch.Tensor:
        return project(self.basis_t, grad_x.reshape(-1))


class RegularizedVertices:
    """Free vertices with the prior β/N ‖(I − UUᵀ)(x − x̄)‖² (``basis_t`` = Uᵀ, (K, 3N)): the
    prior's gradient comes with the vertices' backward; ``prior`` reports its value."""

    capturable = True

    def __init__(self, x0: torch.Tensor, mean: torch.Tensor, basis_t: torch.Tensor, beta: float):
        self.x = x0.detach().clone().requires_grad_(True)
        self.mean = mean
        self.basis_t = basis_t.contiguous()
        self.weight = beta / x0.shape[0]
        self._prior = torch.zeros(())

    def parameters(self) -> list[torch.Tensor]:
        return [self.x]

    def vertices(self) -> torch.Tensor:
        x, self._prior = _SubspacePrior.apply(self.x, self.mean, self.basis_t, self.weight)
        return x

    def prior(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        """The prior's value at the last ``vertices()`` (no gradient: that is in the vertices')."""
        return {"prior": self._prior}
