"""Gauss–Newton on the model's coefficients: the closed-form ``pca`` stage.

For an objective whose residuals are affine in the vertices between two refreshes (the scan's
point-to-plane residuals with their attachments held) and vertices ``x = x̄ + B c`` (B = U diag(std),
so c ~ N(0, I) under the model), each iteration solves the K × K system

    (JᵀJ / R + ρ I) δ = −(Jᵀ r / R + ρ c),    J = ∂r/∂c  (R residuals),

with ρ = σ² / R the Gaussian prior's weight for residual noise σ (fit-frame units): the MAP
coefficients given the current correspondences. The objective's ``refresh`` renews those
correspondences before every iteration (ICP-style alternation). σ follows a continuation path,
from strong to weak prior, so that the large modes settle before the small ones can explain what
they should not (docs/method.md, "Gauss–Newton pca"). Where asked, the path's last levels are
each tried as the end: the one whose prior predicts the scan's held-out edge best is kept
(:func:`held_out_error`; docs/studies.md §32). A model whose modes hold no rigid motion cannot move
the pose a fit was given; six small rigid motions among the coefficients
(:meth:`statfit.core.settings.FitSpace.closed_form_modes`) let the closed form settle it (docs/studies.md §47).
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
# The share of the scan points held out to choose a level: its edge that faces what it does not show
# (docs/studies.md §32; §20 held out the same quarter to choose a method).
EDGE_SHARE = 0.25


class LeastSquaresObjective(Protocol):
    """An objective with residuals affine in the vertices between two ``prepare`` calls."""

    def refresh(self, vertices: torch.Tensor) -> object: ...

    def __call__(self, vertices: torch.Tensor) -> dict[str, torch.Tensor]: ...

    def residuals(self, vertices: torch.Tensor) -> torch.Tensor:
        """(R,) residuals whose mean square the Gauss–Newton stage minimises."""

    def jacobian(self, directions: torch.Tensor) -> torch.Tensor:
        """∂residuals/∂c (R, K) for vertices moving along ``directions`` (N, 3, K)."""

    def residual_points(self) -> torch.Tensor:
        """(R, 3) the scan points of the residuals' rows (needed to choose a level only)."""


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


def edge_rows(points: torch.Tensor, start: torch.Tensor, share: float = EDGE_SHARE) -> torch.Tensor:
    """(R,) bool: the rows whose scan points (R, 3) are the ``share`` farthest along the direction
    from their centroid to the centroid of the ``start`` vertices (N, 3): the scan's edge that faces
    the part of the model it does not show."""
    points = points.double()
    if len(points) == 0:
        return torch.zeros(0, dtype=torch.bool, device=points.device)
    along = points @ (start.double().mean(dim=0) - points.mean(dim=0))
    return along >= torch.quantile(along, 1.0 - share)


def held_out_error(jac: torch.Tensor, r: torch.Tensor, coeffs: torch.Tensor, prior_weight: float,
                   held: torch.Tensor) -> float:
    """How well the rows not ``held`` (R,) bool predict the others at this prior: the mean squared
    residual of the held rows after the Gauss–Newton step from ``coeffs`` (K,) taken without them
    (their linear model: ``jac`` (R, K), ``r`` (R,), float64; the prior's weight per row as the fit's).
    Infinite where no row is held or none is left to predict them, or the solve fails."""
    if not bool(held.any()) or bool(held.all()):
        return math.inf
    kept_jac, kept_r = jac[~held], r[~held]
    count = len(kept_r)
    lhs = kept_jac.T @ kept_jac / count
    lhs = lhs + (prior_weight + SINGULAR_GUARD * float(lhs.diagonal().mean())) * torch.eye(
        len(coeffs), dtype=jac.dtype, device=jac.device)
    try:
        step = torch.linalg.solve(lhs, kept_jac.T @ kept_r / count + prior_weight * coeffs)
    except torch.linalg.LinAlgError:      # no prior (σ = 0) and fewer rows than modes
        return math.inf
    error = float((r[held] - jac[held] @ step).square().mean())
    return error if math.isfinite(error) else math.inf


def fit_coefficients(mean: torch.Tensor, basis_t: torch.Tensor, std: torch.Tensor, objective: LeastSquaresObjective,
                     x0: torch.Tensor, iterations: int, noise: float, levels: int = CONTINUATION_LEVELS,
                     choose_levels: int = 0, tolerance: float = TOLERANCE, first_iteration: int = 0,
                     on_record: Callable[[int, dict[str, float]], None] | None = None,
                     on_snapshot: Callable[[int, torch.Tensor], None] | None = None) -> CoefficientFit:
    """Gauss–Newton over coefficients c of ``x = mean + Σ_k c_k std_k U_k`` (``basis_t`` = Uᵀ,
    (K, 3N); ``mean`` (N, 3)), from the projection of ``x0`` (N, 3) on the model, at most
    ``iterations`` steps in all. The prior's noise σ falls from ``noise``·√10^(levels−1) to ``noise``
    by factors of √10; each level runs until the data term improves by less than ``tolerance``.

    ``choose_levels`` N > 0: each of the path's last N levels, once converged, is scored by
    :func:`held_out_error` on the scan's edge (:func:`edge_rows`, from the ``x0`` it starts at), and
    the fit returned is the level with the least error (its coefficients and terms; on a tie, the
    earlier), the last level where none could be scored; the objective then needs
    ``residual_points``. A path the ``iterations`` cut short ends where it stopped, as without."""
    started = time.perf_counter()
    directions = mode_directions(basis_t, std).contiguous()
    coeffs = (torch.mv(basis_t, (x0 - mean).reshape(-1)) / std).double()
    eye = torch.eye(len(std), dtype=torch.float64, device=mean.device)
    schedule = [noise * math.sqrt(10.0) ** level for level in reversed(range(max(1, levels)))]
    terms, done, level_start, previous = {}, 0, 0, math.inf
    tried: list[tuple[float, torch.Tensor, dict[str, float]]] = []       # (held-out error, coefficients, terms)
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
        jac = None
        if done - 1 > level_start and previous - data <= tolerance * previous:
            if len(schedule) <= choose_levels:      # one of the last levels: score it as an end
                jac = objective.jacobian(directions).double()
                held = edge_rows(objective.residual_points(), x0)
                tried.append((held_out_error(jac, r, coeffs, prior_weight, held), coeffs, terms))
            schedule.pop(0)       # this level has converged: the next, or the end
            if not schedule:
                best = min(tried, key=lambda each: each[0], default=(math.inf,))
                if math.isfinite(best[0]):
                    _, coeffs, terms = best
                break
            level_start, sigma, prior_weight = done - 1, schedule[0], schedule[0] ** 2 / count
        previous = data
        jac = objective.jacobian(directions).double() if jac is None else jac
        lhs = jac.T @ jac / count
        lhs = lhs + (prior_weight + SINGULAR_GUARD * float(lhs.diagonal().mean())) * eye
        rhs = jac.T @ r / count + prior_weight * coeffs
        coeffs = coeffs - torch.linalg.solve(lhs, rhs)
    x = mean + directions @ coeffs.to(mean.dtype)
    return CoefficientFit(x, coeffs, terms, done, time.perf_counter() - started)
