"""Gauss–Newton on the model's coefficients: the closed-form ``pca`` stage.

For an objective whose data term is a mean of squared residuals, ``mean ‖r(x)‖²`` (e.g. the scan's
point-to-surface term with its attachments held), and vertices ``x = x̄ + B c`` (B = U diag(std), so
c ~ N(0, I) under the model), each iteration solves the K × K system

    (JᵀJ / R + ρ I) δ = −(Jᵀ r / R + ρ c),    J = ∂r/∂c  (R residual entries),

with ρ = σ² / R the Gaussian prior's weight for residual noise σ (fit-frame units): the MAP
coefficients given the current correspondences. The objective's ``refresh`` renews those
correspondences before every iteration (ICP-style alternation), and the loop stops when the data
term improves by less than ``tolerance`` (relative) from one iteration to the next.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable, Protocol

import torch

from statfit.errors import DivergenceError


class LeastSquaresObjective(Protocol):
    """An objective with residuals affine in the vertices between two ``prepare`` calls."""

    def refresh(self, vertices: torch.Tensor) -> object: ...

    def __call__(self, vertices: torch.Tensor) -> dict[str, torch.Tensor]: ...

    def residuals(self, vertices: torch.Tensor) -> torch.Tensor:
        """(R,) residuals whose mean square the Gauss–Newton stage minimises."""

    def jacobian(self, directions: torch.Tensor) -> torch.Tensor:
        """∂residuals/∂c (R, K) for vertices moving along ``directions`` (N, 3, K)."""


@dataclass
class CoefficientFit:
    """vertices (N, 3), coefficients (K,) in standard-deviation units, final terms, iterations run."""

    vertices: torch.Tensor
    coefficients: torch.Tensor
    loss: dict[str, float]
    iterations: int
    seconds: float


def fit_coefficients(mean: torch.Tensor, basis_t: torch.Tensor, std: torch.Tensor, objective: LeastSquaresObjective,
                     x0: torch.Tensor, iterations: int, noise: float, tolerance: float = 1e-4, prior_power: float = 0.0,
                     first_iteration: int = 0, on_record: Callable[[int, dict[str, float]], None] | None = None,
                     on_snapshot: Callable[[int, torch.Tensor], None] | None = None) -> CoefficientFit:
    """Gauss–Newton over coefficients c of ``x = mean + Σ_k c_k std_k U_k`` (``basis_t`` = Uᵀ,
    (K, 3N); ``mean`` (N, 3)), starting from the projection of ``x0`` (N, 3) on the model, for at
    most ``iterations`` steps; ``noise`` σ sets the prior's weight (see the module docstring)."""
    started = time.perf_counter()
    directions = (basis_t * std[:, None]).T.reshape(*mean.shape, len(std)).contiguous()   # (N, 3, K)
    coeffs = (torch.mv(basis_t, (x0 - mean).reshape(-1)) / std).double()
    eye = torch.diag((std[0] / std).double() ** prior_power)
    previous, terms, done = math.inf, {}, 0
    for step in range(iterations):
        x = mean + directions @ coeffs.to(mean.dtype)
        objective.refresh(x)
        r = objective.residuals(x).double()
        count = max(r.numel(), 1)
        prior_weight = noise**2 / count
        data = float(objective(x)["data"])
        terms = {"data": data, "prior": prior_weight * float(coeffs @ eye @ coeffs)}
        terms["total"] = terms["data"] + terms["prior"]
        if not math.isfinite(terms["total"]):
            raise DivergenceError(f"the fit diverged at iteration {first_iteration + step}: the loss is {terms['total']}")
        if on_record:
            on_record(first_iteration + step, terms)
        if on_snapshot:
            on_snapshot(first_iteration + step, x)
        done = step + 1
        if previous - data < tolerance * previous:
            break
        previous = data
        jac = objective.jacobian(directions).double()
        lhs = jac.T @ jac / count + prior_weight * eye
        rhs = jac.T @ r.double() / count + prior_weight * (eye @ coeffs)
        coeffs = coeffs - torch.linalg.solve(lhs, rhs)
    x = mean + directions @ coeffs.to(mean.dtype)
    return CoefficientFit(x, coeffs, terms, done, time.perf_counter() - started)
