"""Gradient filters: symmetric linear maps F applied to (N, 3) tensors, ``F(g)``, or to (B, N, 3):
B independent fits of one mesh filtered at once (each fit's (N, 3) block by F; the model's basis is
streamed once for all B, and the Laplacian solves 3B columns in one call).

- identity:     F = I
- laplacian:    F = (I + λL)⁻¹                              (Nicolet et al. 2021)
- statistical:  F = α UUᵀ + (1 − α) I,  α = β / (1 + β)      = (I + β(I − UUᵀ))⁻¹
- hybrid:       F = α UUᵀ + (1 − α)(I + λL)⁻¹

``capturable``: whether a CUDA graph can capture the filter (all but a Laplacian solved by a
solver whose kernels leave torch's stream).

The statistical filter is applied as ``e⊥ g + Uᵀᵀ((e − e⊥) ⊙ (Uᵀ g))`` with the basis stored
transposed, (K, 3N) contiguous, so each mat-vec streams it once (on every thread:
:mod:`statfit.core.matvec`). ``mode_gain`` generalises the eigenvalue 1 on the model subspace to one gain
per mode (e.g. proportional to the modes' standard deviations, so low-variance modes move slower).
"""
from __future__ import annotations

import collections
import hashlib
import threading

import numpy as np
import scipy.sparse as sp
import torch

from statfit.core.laplacian import LaplacianKind, identity_plus, smoothing_matrix
from statfit.core.matvec import expand, project
from statfit.core.solvers import make_solver


def beta_with_power(beta: float, power: float) -> float:
    """β' such that the filter with β' equals the filter with β raised to ``power``."""
    return (1.0 + beta) ** power - 1.0


class IdentityFilter:
    """F = I."""

    capturable = True

    def __call__(self, g: torch.Tensor) -> torch.Tensor:
        return g


# Factorisations kept per thread, the latest few: a pipeline's stages with one λ (render's default:
# three) and a batch's fits of one model factorise once (a solver is not shared between threads).
KEPT_FACTORISATIONS = 2
_kept = threading.local()


def _kept_solver(key: tuple, factorise):
    """This thread's solver for ``key``, made by ``factorise()`` unless one of the last
    :data:`KEPT_FACTORISATIONS` has that key."""
    if not hasattr(_kept, "solvers"):
        _kept.solvers = collections.OrderedDict()
    kept = _kept.solvers
    if key not in kept:
        kept[key] = factorise()
        while len(kept) > KEPT_FACTORISATIONS:
            kept.popitem(last=False)
    kept.move_to_end(key)
    return kept[key]


class LaplacianFilter:
    """F = (I + λL)⁻¹, factorised at construction, or taken from the last :data:`KEPT_FACTORISATIONS`
    of this thread when one was made of the same mesh (the faces; the vertices too for a cotangent
    Laplacian), λ, solver, dtype and device."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, lam: float, kind: LaplacianKind = "uniform",
                 solver: str = "auto", dtype: torch.dtype = torch.float32, device: str | torch.device = "cpu"):
        self.lam = lam
        digest = hashlib.blake2b(np.ascontiguousarray(faces, dtype=np.int64).tobytes(), digest_size=16)
        if kind != "uniform":
            digest.update(np.ascontiguousarray(vertices, dtype=np.float64).tobytes())
        key = (digest.hexdigest(), len(vertices), float(lam), kind, solver, dtype, str(torch.device(device)))
        self._solver = _kept_solver(key, lambda: make_solver(smoothing_matrix(vertices, faces, lam, kind), solver,
                                                             dtype, device))

    @classmethod
    def from_laplacian(cls, laplacian: sp.spmatrix, lam: float, solver: str = "auto",
                       dtype: torch.dtype = torch.float32, device: str | torch.device = "cpu") -> "LaplacianFilter":
        """The filter for a ready Laplacian ``L`` (N, N), e.g. an image grid's."""
        filt = cls.__new__(cls)
        filt.lam = lam
        filt._solver = make_solver(identity_plus(laplacian, lam), solver, dtype, device)
        return filt

    @property
    def capturable(self) -> bool:
        """Whether a CUDA graph can capture the solve (the ``dense`` solver's product)."""
        return self._solver.capturable

    def __call__(self, g: torch.Tensor) -> torch.Tensor:
        if g.dim() == 2:
            return self._solver.solve(g)
        fits, n, c = g.shape                                   # the fits' columns side by side: (N, 3B)
        columns = g.permute(1, 0, 2).reshape(n, fits * c)
        return self._solver.solve(columns).view(n, fits, c).permute(1, 0, 2)


class StatisticalFilter:
    """F = U diag(e) Uᵀ + e⊥ (I − UUᵀ), with e = mode_gain (default 1) and e⊥ = 1 / (1 + β').

    ``basis_t``: (K, 3N) orthonormal rows. β' = (1 + β)^power − 1. With the default gains this is
    exactly α UUᵀ + (1 − α) I = (I + β'(I − UUᵀ))⁻¹.
    """

    capturable = True

    def __init__(self, basis_t: torch.Tensor, beta: float, power: float = 1.0,
                 mode_gain: torch.Tensor | None = None):
        self.basis_t = basis_t.contiguous()
        self._basis = self.basis_t.t()
        self.beta = beta_with_power(beta, power)
        self.off_gain = 1.0 / (1.0 + self.beta)
        gain = torch.ones(basis_t.shape[0], dtype=basis_t.dtype, device=basis_t.device) \
            if mode_gain is None else mode_gain.to(basis_t)
        self._gain_minus_off = gain - self.off_gain

    def __call__(self, g: torch.Tensor) -> torch.Tensor:
        if g.dim() == 3:
            flat = g.reshape(len(g), -1)                                                     # (B, 3N)
            coeff = flat.mm(self._basis).mul_(self._gain_minus_off)                          # (B, K)
            return torch.addmm(flat, coeff, self.basis_t, beta=self.off_gain).view_as(g)
        flat = g.reshape(-1)
        coeff = project(self.basis_t, flat).mul_(self._gain_minus_off)
        return expand(self.basis_t, coeff, flat, self.off_gain, self._basis).view_as(g)


class HybridFilter:
    """F = U diag(e) Uᵀ + e⊥ (I + λL)⁻¹ with e⊥ = 1 − α; by default e = α (the paper's form)."""

    def __init__(self, basis_t: torch.Tensor, beta: float, laplacian_filter: LaplacianFilter,
                 power: float = 1.0, mode_gain: torch.Tensor | None = None):
        self.basis_t = basis_t.contiguous()
        self._basis = self.basis_t.t()
        self.beta = beta_with_power(beta, power)
        alpha = self.beta / (1.0 + self.beta)
        self.off_gain = 1.0 - alpha
        self._gain = (torch.full((basis_t.shape[0],), alpha, dtype=basis_t.dtype, device=basis_t.device)
                      if mode_gain is None else alpha * mode_gain.to(basis_t))
        self._smooth = laplacian_filter
        self.capturable = laplacian_filter.capturable

    def __call__(self, g: torch.Tensor) -> torch.Tensor:
        if g.dim() == 3:
            flat = g.reshape(len(g), -1)                                                     # (B, 3N)
            coeff = flat.mm(self._basis).mul_(self._gain)                                    # (B, K)
            smooth = self._smooth(g).reshape(len(g), -1)
            return torch.addmm(smooth, coeff, self.basis_t, beta=self.off_gain).view_as(g)
        flat = g.reshape(-1)
        coeff = project(self.basis_t, flat).mul_(self._gain)
        smooth = self._smooth(g).reshape(-1)
        return expand(self.basis_t, coeff, smooth, self.off_gain, self._basis).view_as(g)
