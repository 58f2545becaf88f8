"""Fitting methods: settings, presets, and construction of (parametrisation, optimiser).

A *pipeline* is a sequence of stages; each stage's result starts the next. The paper-faithful
methods are one stage each; ``default`` is the pipeline chosen by the study in docs/studies.md.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np
import scipy.sparse as sp
import torch

from statfit.errors import StatfitError
from statfit.filters import HybridFilter, IdentityFilter, LaplacianFilter, StatisticalFilter
from statfit.optim import UniformAdam
from statfit.parametrize import FilteredVertices, PCACoefficients, RegularizedVertices

METHODS = ("statistical", "laplacian", "hybrid", "pca", "regularized", "none")


@dataclass(frozen=True)
class Settings:
    """One optimisation stage. ``beta`` is the filter's β (statistical, hybrid) or the
    regulariser's weight (regularized); ``mode_gain`` γ sets the filter's gain on mode j to
    (std_j / std_1)^γ (0: the paper's filter, gain 1 on every mode). ``optimizer`` is "adam"
    (Adam, or UniformAdam for filtered methods) or "gauss-newton" (pca only: the closed-form
    coefficient solve, ``iterations`` an upper bound, ``noise`` σ the residual noise that weighs
    the Gaussian prior, in fit-frame units, reached through ``levels`` continuation levels)."""

    method: str
    iterations: int
    lr: float
    beta: float = 30.0
    power: float = 1.0
    lam: float = 19.0
    laplacian: str = "uniform"
    solver: str = "cholespy"
    mode_gain: float = 0.0
    betas: tuple[float, float] = (0.9, 0.999)
    optimizer: str = "adam"
    noise: float = 0.003
    levels: int = 5

    def describe(self) -> dict[str, Any]:
        """The settings as a plain dict (for logs)."""
        return asdict(self)


JOBS = ("register", "render")
# The paper's iteration counts per job: 500 for scan registration, 3000 for inverse rendering.
PAPER_ITERATIONS = {"register": 500, "render": 3000}

# The paper's settings (Nicolet-style UniformAdam, lr 0.01; β 30 filter / 10 regulariser; λ 19).
PAPER: dict[str, Settings] = {
    "statistical": Settings("statistical", 500, 0.01, beta=30.0),
    "laplacian": Settings("laplacian", 500, 0.01, lam=19.0),
    "hybrid": Settings("hybrid", 500, 0.01, beta=30.0, lam=19.0),
    "regularized": Settings("regularized", 500, 0.01, beta=10.0),
    "pca": Settings("pca", 500, 5.0),
    "none": Settings("none", 500, 0.01),
}

# The Gauss–Newton pca stage stops by itself (31–50 iterations on the study's cases, docs/studies.md
# §9); this only bounds it.
GAUSS_NEWTON_ITERATIONS = 200

# Our defaults: each method's best settings in the registration study (docs/studies.md),
# measured on ICT partial scans with expressions outside the model. ``statistical`` here uses
# mode gains (γ = 1); ``--preset paper`` (or ``mode_gain=0``) gives the paper's filter.
TUNED: dict[str, Settings] = {
    "statistical": Settings("statistical", 1000, 0.05, beta=1000.0, mode_gain=1.0),
    "laplacian": Settings("laplacian", 1000, 0.1, lam=300.0),
    "hybrid": Settings("hybrid", 1000, 0.03, beta=30.0, lam=19.0),
    "regularized": Settings("regularized", 1000, 0.1, beta=30.0),
    "pca": Settings("pca", GAUSS_NEWTON_ITERATIONS, 0.0, optimizer="gauss-newton", noise=0.003),
    "none": Settings("none", 1000, 0.003),
}

# Two stages of the statistical filter with β = 1000: gains ∝ std (γ = 1) find the shape in the
# model's span, then a smaller step with gains ∝ sqrt(std) (γ = 0.5) lets low-variance modes and
# off-model detail (expressions) in. Chosen by the study and its follow-up (docs/studies.md).
PIPELINES: dict[str, tuple[Settings, ...]] = {
    "default": (Settings("statistical", 4000, 0.03, beta=1000.0, mode_gain=1.0),
                Settings("statistical", 1333, 0.01, beta=1000.0, mode_gain=0.5)),
}


# Inverse rendering (one normal map): each method's best settings in the rendering study
# (docs/studies.md §5), 3000 iterations each as in the paper. The default is the hybrid filter
# with mode gains ∝ std (γ = 1): the lowest error over all vertices of everything tried.
RENDER_TUNED: dict[str, Settings] = {
    "statistical": Settings("statistical", 3000, 0.01, beta=1000.0, mode_gain=1.0),
    "laplacian": Settings("laplacian", 3000, 0.003, lam=19.0),
    "hybrid": Settings("hybrid", 3000, 0.01, beta=30.0, lam=19.0, mode_gain=1.0),
    "regularized": Settings("regularized", 3000, 0.01, beta=10.0),
    "pca": Settings("pca", 3000, 0.05),
    "none": Settings("none", 3000, 0.001),
}
RENDER_PIPELINES: dict[str, tuple[Settings, ...]] = {"default": (RENDER_TUNED["hybrid"],)}


@dataclass(frozen=True)
class FitSpace:
    """The model in the fit frame, as tensors: mean (N, c), basis_t = Uᵀ (K, cN), std (K,); the
    Laplacian comes from the mesh ``faces``, or is given ready (``laplacian``, e.g. an image grid's)."""

    mean: torch.Tensor
    basis_t: torch.Tensor
    std: torch.Tensor
    faces: np.ndarray | None
    laplacian: sp.spmatrix | None = None


def resolve(method: str, preset: str = "tuned", job: str = "register", **overrides: Any) -> tuple[Settings, ...]:
    """The stages for ``method`` under ``preset`` ('tuned' or 'paper') for ``job`` ('register'
    or 'render'), with ``overrides`` (non-None values) applied to every stage."""
    if preset not in ("tuned", "paper"):
        raise StatfitError(f"unknown preset {preset!r}; choose 'tuned' or 'paper'")
    if job not in JOBS:
        raise StatfitError(f"unknown job {job!r}; choose one of {', '.join(JOBS)}")
    pipelines = PIPELINES if job == "register" else RENDER_PIPELINES
    if method in pipelines:
        if preset == "paper":
            raise StatfitError(f"the {method!r} pipeline is ours, not the paper's; use --method statistical --preset paper")
        stages = pipelines[method]
    elif method in METHODS:
        if preset == "paper":
            stages = (replace(PAPER[method], iterations=PAPER_ITERATIONS[job]),)
        else:
            stages = ((TUNED if job == "register" else RENDER_TUNED)[method],)
    else:
        raise StatfitError(f"unknown method {method!r}; choose one of {', '.join((*pipelines, *METHODS))}")
    changes = {k: v for k, v in overrides.items() if v is not None}
    if changes.get("iterations", 1) < 1:
        raise StatfitError("--iterations must be at least 1")
    if len(stages) > 1 and "iterations" in changes:
        last = stages[-1]
        total = sum(s.iterations for s in stages)
        stages = tuple(replace(s, iterations=max(1, round(s.iterations * changes["iterations"] / total)))
                       for s in stages[:-1]) + (last,)
        spent = sum(s.iterations for s in stages[:-1])
        stages = stages[:-1] + (replace(last, iterations=max(1, changes["iterations"] - spent)),)
        changes.pop("iterations")
    return tuple(replace(s, **changes) for s in stages)


def build(settings: Settings, space: FitSpace, x0: torch.Tensor):
    """Parametrisation and optimiser for one stage, starting from vertices ``x0`` (N, 3)."""
    if settings.method == "pca":
        scaled = space.basis_t * space.std[:, None]
        start = torch.mv(space.basis_t, (x0 - space.mean).reshape(-1)) / space.std
        param = PCACoefficients(space.mean, scaled, start)
        return param, torch.optim.Adam(param.parameters(), lr=settings.lr, betas=settings.betas)
    if settings.method == "regularized":
        param = RegularizedVertices(x0, space.mean, space.basis_t, settings.beta)
        return param, UniformAdam(param.parameters(), lr=settings.lr, betas=settings.betas)
    if settings.method == "none":
        param = FilteredVertices(x0, IdentityFilter())
        return param, torch.optim.Adam(param.parameters(), lr=settings.lr, betas=settings.betas)
    param = FilteredVertices(x0, make_filter(settings, space, x0))
    return param, UniformAdam(param.parameters(), lr=settings.lr, betas=settings.betas)


def make_filter(settings: Settings, space: FitSpace, x0: torch.Tensor):
    """The gradient filter of a filtered method."""
    gain = (space.std / space.std[0]) ** settings.mode_gain if settings.mode_gain else None
    if settings.method == "statistical":
        return StatisticalFilter(space.basis_t, settings.beta, settings.power, gain)
    if space.laplacian is not None:
        smooth = LaplacianFilter.from_laplacian(space.laplacian, settings.lam, settings.solver, x0.dtype, x0.device)
    else:
        smooth = LaplacianFilter(x0.detach().cpu().double().numpy(), space.faces, settings.lam, settings.laplacian,
                                 settings.solver, x0.dtype, x0.device)
    if settings.method == "laplacian":
        return smooth
    if settings.method == "hybrid":
        return HybridFilter(space.basis_t, settings.beta, smooth, settings.power, gain)
    raise StatfitError(f"method {settings.method!r} has no filter")
