"""Gauss–Newton on the model's coefficients: the closed-form ``pca`` stage.

For an objective whose residuals are affine in the vertices between two refreshes (the scan's
point-to-plane residuals with their attachments held) and vertices ``x = x̄ + B c`` (B = U diag(std),
so c ~ N(0, I) under the model), each iteration solves the K × K system

    (JᵀJ / R + ρ I) δ = −(Jᵀ r / R + ρ c),    J = ∂r/∂c  (R residuals),

with ρ = σ² / R the Gaussian prior's weight for residual noise σ (fit-frame units): the MAP
coefficients given the current correspondences. The objective's ``refresh`` renews those
correspondences before every iteration (ICP-style alternation). σ follows a continuation path,
from strong to weak prior, so that the large modes settle before the small ones can explain what
they should not (docs/method.md, "Gauss–Newton pca").
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable, Protocol

import torch

from statfit.errors import DivergenceError

# Relative ridge on the normal equations: keeps a noise-free fit to too few points solvable.
SINGULAR_GUARD = 1e-12
# Continuation: the prior starts 10² times stronger (σ × √10⁴) and relaxes in 5 levels to σ; a level
# ends when the data term improves by less than 0.1% (docs/studies.md §9: without it, large
# expressions are explained by low-variance modes, e.g. cheek-puff 0.276 vs 0.178 cm).
CONTINUATION_LEVELS = 5
TOLERANCE = 1e-3


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


def mode_directions(basis_t: torch.Tensor, std: torch.Tensor) -> torch.Tensor:
    """The modes (``basis_t`` = Uᵀ, (K, 3N)) times their standard deviations ``std`` (K,), vertex-major:
    (N, 3, K), the layout :meth:`LeastSquaresObjective.jacobian` takes."""
    return (basis_t * std[:, None]).T.reshape(-1, 3, len(std))


def fit_coefficients(mean: torch.Tensor, basis_t: torch.Tensor, std: torch.Tensor, objective: LeastSquaresObjective,
                     x0: torch.Tensor, iterations: int, noise: float, levels: int = CONTINUATION_LEVELS,
                     tolerance: float = TOLERANCE, first_iteration: int = 0,
                     on_record: Callable[[int, dict[str, float]], None] | None = None,
                     on_snapshot: Callable[[int, torch.Tensor], None] | None = None) -> CoefficientFit:
    """Gauss–Newton over coefficients c of ``x = mean + Σ_k c_k std_k U_k`` (``basis_t`` = Uᵀ,
    (K, 3N); ``mean`` (N, 3)), from the projection of ``x0`` (N, 3) on the model, at most
    ``iterations`` steps in all. The prior's noise σ falls from ``noise``·√10^(levels−1) to ``noise``
    by factors of √10; each level runs until the data term improves by less than ``tolerance``."""
    started = time.perf_counter()
    directions = mode_directions(basis_t, std).contiguous()
    coeffs = (torch.mv(basis_t, (x0 - mean).reshape(-1)) / std).double()
    eye = torch.eye(len(std), dtype=torch.float64, device=mean.device)
    schedule = [noise * math.sqrt(10.0) ** level for level in reversed(range(max(1, levels)))]
    terms, done, level_start, previous = {}, 0, 0, math.inf
    while done < iterations:
        sigma = schedule[0]
        x = mean + directions @ coeffs.to(mean.dtype)
        objective.refresh(x)
        r = objective.residuals(x).double()
        count = max(r.numel(), 1)
        prior_weight = sigma**2 / count
        data = float(objective(x)["data"])
        terms = {"data": data, "prior": prior_weight * float(coeffs.square().sum())}
        terms["total"] = terms["data"] + terms["prior"]
        if not math.isfinite(terms["total"]):
            raise DivergenceError(f"the fit diverged at iteration {first_iteration + done}: "
                                  f"the loss is {terms['total']}")
        if on_record:
            on_record(first_iteration + done, terms)
        if on_snapshot:
            on_snapshot(first_iteration + done, x)
        done += 1
        if done - 1 > level_start and previous - data <= tolerance * previous:
            schedule.pop(0)       # this level has converged: the next, or the end
            if not schedule:
                break
            level_start, sigma, prior_weight = done - 1, schedule[0], schedule[0] ** 2 / count
        previous = data
        jac = objective.jacobian(directions).double()
        lhs = jac.T @ jac / count
        lhs = lhs + (prior_weight + SINGULAR_GUARD * float(lhs.diagonal().mean())) * eye
        rhs = jac.T @ r / count + prior_weight * coeffs
        coeffs = coeffs - torch.linalg.solve(lhs, rhs)
    x = mean + directions @ coeffs.to(mean.dtype)
    return CoefficientFit(x, coeffs, terms, done, time.perf_counter() - started)
