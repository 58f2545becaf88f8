"""Settings of one optimisation stage, validated when made, and the model as the fit sees it."""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp
import torch

from statfit.errors import StatfitError
from statfit.core.filters import beta_with_power
from statfit.structures.frame import Frame
from statfit.model.cut import rigid_motion_basis
from statfit.model.statmodel import StatModel
from statfit.core.solvers import SOLVERS

OPTIMIZERS = ("adam", "gauss-newton")
LAPLACIANS = ("uniform", "cotangent")
MAX_ITERATIONS = 10_000_000
# The built-in methods that step with Adam, not UniformAdam (statfit.core.methods): no settle.
ADAM_METHODS = ("pca", "none")
MAX_LEVELS = 20
# Upper bounds: far beyond any useful value (β 1000, λ 300, γ 1, σ 0.003 are the largest tuned ones),
# below what breaks the arithmetic (λ 10³⁰ makes I + λL numerically indefinite; β^p overflows).
LIMITS = {"beta": 1e9, "lam": 1e9, "mode_gain": 100.0, "noise": 1e3, "power": 100.0, "prior": 1e9}


@dataclass(frozen=True)
class Settings:
    """One optimisation stage of ``method`` (a name in :data:`statfit.core.methods.METHODS`).

    ``beta``: the filter's β (statistical, hybrid) or the regulariser's weight (regularized);
    ``power`` p turns β into β' = (1+β)^p − 1; ``lam``: λ of the Laplacian (``laplacian``: its kind,
    ``solver``: how (I + λL) is factorised; ``auto``: cholespy, or on CUDA the dense inverse where it
    fits, :func:`statfit.core.solvers.auto_solver`); ``mode_gain`` γ sets the filter's gain on mode j to
    (std_j / std_1)^γ (0: the paper's filter, gain 1 on every mode). ``optimizer`` is "adam"
    (Adam, or UniformAdam for filtered methods; ``lr``, ``adam_betas``) or "gauss-newton" (pca on a scan:
    the closed-form coefficient solve, ``iterations`` an upper bound, ``noise`` σ the residual noise
    that weighs the Gaussian prior, in fit-frame units, reached through ``levels`` continuation
    levels; ``choose_levels`` N > 0: of the last N levels, the one whose prior best predicts the
    scan's held-out edge, :func:`statfit.core.gauss_newton.fit_coefficients`). ``prior``: with Adam
    on pca's coefficients c (in standard deviations), the weight w of a Gaussian prior term
    w · mean(c²) (0: none). ``landmarks`` False: the stage does not fit a
    landmark term (the landmarks, if given, still place the start and the other stages).
    ``settle``: with UniformAdam, the share of the stage's last iterations over which the step size
    falls linearly to 0 (0: constant, the paper's), so the fit comes to rest instead of ending
    wherever its last step took it (docs/studies.md §30).
    Out-of-range values raise StatfitError naming the setting.
    """

    method: str
    iterations: int
    lr: float
    beta: float = 30.0
    power: float = 1.0
    lam: float = 19.0
    laplacian: str = "uniform"
    solver: str = "auto"
    mode_gain: float = 0.0
    adam_betas: tuple[float, float] = (0.9, 0.999)
    optimizer: str = "adam"
    noise: float = 0.003
    levels: int = 5
    choose_levels: int = 0
    prior: float = 0.0
    landmarks: bool = True
    settle: float = 0.0

    def __post_init__(self) -> None:
        check_int("iterations", self.iterations, 1, MAX_ITERATIONS)
        check_int("levels", self.levels, 1, MAX_LEVELS)
        check_int("choose_levels", self.choose_levels, 0, self.levels)
        if self.optimizer not in OPTIMIZERS:
            raise StatfitError(f"unknown optimizer {self.optimizer!r}; choose one of {', '.join(OPTIMIZERS)}")
        if self.choose_levels and self.optimizer != "gauss-newton":
            raise StatfitError("choose_levels chooses among the Gauss–Newton stage's prior levels; "
                               f"the {self.optimizer!r} stage has none")
        if self.optimizer == "adam":
            _check_number("lr (the step size)", self.lr, positive=True)
        elif self.method != "pca":
            raise StatfitError(f"the Gauss–Newton optimizer fits the model's coefficients: method 'pca', not "
                               f"{self.method!r}")
        for name, high in LIMITS.items():
            _check_number(name, getattr(self, name), high=high, positive=name == "power")
        try:
            beta_with_power(self.beta, self.power)  # the filters' β'
        except OverflowError:
            raise StatfitError(f"(1 + beta)^power overflows: beta {self.beta}, power {self.power}") from None
        if self.prior and (self.method != "pca" or self.optimizer != "adam"):
            hint = " (its prior is noise)" if self.optimizer == "gauss-newton" else ""
            raise StatfitError(f"prior weighs pca's coefficients under Adam, not {self.method!r} with "
                               f"{self.optimizer!r}{hint}")
        if self.laplacian not in LAPLACIANS:
            raise StatfitError(f"unknown Laplacian {self.laplacian!r}; choose one of {', '.join(LAPLACIANS)}")
        if self.solver not in SOLVERS:
            raise StatfitError(f"unknown solver {self.solver!r}; choose one of {', '.join(SOLVERS)}")
        _check_number("settle", self.settle, high=1.0)
        if self.settle and self.optimizer != "adam":
            raise StatfitError("settle brings an Adam stage's step size down; the Gauss–Newton stage has none")
        if self.settle and self.method in ADAM_METHODS:
            raise StatfitError(f"settle brings UniformAdam's step size down; {self.method!r} steps with Adam")
        if len(self.adam_betas) != 2 or not all(0 <= b < 1 for b in self.adam_betas):
            raise StatfitError(f"adam_betas must be two numbers in [0, 1), got {self.adam_betas}")

    def describe(self) -> dict[str, Any]:
        """The settings as a plain dict (for logs)."""
        return asdict(self)


def _check_number(name: str, value: float, positive: bool = False, high: float = math.inf) -> None:
    """A finite number, ≥ 0 (or > 0 with ``positive``), at most ``high``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise StatfitError(f"{name} must be a finite number, got {value!r}")
    if value < 0 or (positive and value == 0):
        raise StatfitError(f"{name} must be {'positive' if positive else 'at least 0'}, got {value!r}")
    if value > high:
        raise StatfitError(f"{name} must be at most {high:g}, got {value!r}")


def check_int(name: str, value: int, low: int, high: int) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not low <= value <= high:
        raise StatfitError(f"{name} must be a whole number from {low} to {high:,}, got {value!r}")


@dataclass(frozen=True)
class FitSpace:
    """The model in the fit frame, as tensors: mean (N, c), basis_t = Uᵀ (K, cN), std (K,); the
    Laplacian comes from the mesh ``faces``, or is given ready (``laplacian_matrix``, e.g. an image grid's).
    ``pose_std``: the closed-form stage's own small rigid motion, RMS vertex motion per standard deviation
    (fit-frame units; :meth:`closed_form_modes`), 0 for none."""

    mean: torch.Tensor
    basis_t: torch.Tensor
    std: torch.Tensor
    faces: np.ndarray | None
    laplacian_matrix: sp.spmatrix | None = None
    pose_std: float = 0.0

    @classmethod
    def of(cls, model: StatModel, frame: Frame | None = None, device: str | torch.device = "cpu",
           dtype: torch.dtype = torch.float32, pose_std: float = 0.0) -> "FitSpace":
        """``model``'s mean, basis and std-devs in ``frame`` (default: the template's unit frame,
        :class:`statfit.structures.frame.Frame`), as tensors on ``device``."""
        frame = frame or model.frame

        def as_tensor(array: np.ndarray) -> torch.Tensor:
            return torch.as_tensor(np.ascontiguousarray(array), dtype=dtype, device=device)

        return cls(as_tensor(frame.to_unit(model.template)), as_tensor(model.basis.T),
                   as_tensor(model.std / frame.scale), model.faces, pose_std=pose_std)

    def closed_form_modes(self) -> tuple[torch.Tensor, torch.Tensor]:
        """What the closed-form stage fits: Uᵀ (K, 3N) and std (K,), and with ``pose_std`` > 0 six more
        rows after them: the mean's small rigid motions (:func:`statfit.model.cut.rigid_motion_basis`:
        shifts and turns about its centroid, orthonormal), each moving the vertices by ``pose_std`` RMS
        per standard deviation: (K + 6, 3N), (K + 6,). A turn is a rotation to first order: by a degree,
        the lengths grow by 0.015%."""
        if self.pose_std <= 0:
            return self.basis_t, self.std
        rigid = rigid_motion_basis(self.mean.detach().cpu().double().numpy())
        rigid_t = torch.as_tensor(rigid.T, dtype=self.basis_t.dtype, device=self.basis_t.device)
        rigid_std = torch.full((6,), self.pose_std * math.sqrt(len(self.mean)), dtype=self.std.dtype,
                               device=self.std.device)
        return torch.cat([self.basis_t, rigid_t]), torch.cat([self.std, rigid_std])

    def shape(self, coefficients: np.ndarray | torch.Tensor) -> torch.Tensor:
        """The mean plus Σ c_k std_k U_k for ``coefficients`` (K,) in standard deviations: (N, c)."""
        c = torch.as_tensor(coefficients, dtype=self.mean.dtype, device=self.mean.device)
        return self.mean + ((c * self.std) @ self.basis_t).view_as(self.mean)
