"""Prefactored sparse SPD solvers: factorise once, then each call only solves.

All take and return torch tensors of shape (n, c) on the solver's device. Measured choice of the
default: see docs/studies.md (``cholespy``, the solver largesteps uses, was fastest). ``dense`` keeps
the inverse as a matrix: on a GPU one product a solve, which a CUDA graph can capture (cholespy's
kernels run on CUDA's legacy stream, outside any capture); ``auto`` picks it there for meshes that
fit (:func:`auto_solver`).
"""
from __future__ import annotations

import igl
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

from statfit.errors import StatfitError

SOLVERS: tuple[str, ...] = ("cholespy", "scipy-lu", "igl", "dense", "auto")
# The dense inverse holds n² numbers: 1 GB in float32 at this size.
DENSE_LIMIT = 16_384


# cholespy's CUDA solve takes at most this many right-hand sides in one call (its docstring).
CHOLESPY_CUDA_COLUMNS = 128


class CholespySolver:
    """Sparse Cholesky (CHOLMOD on CPU, cuSolver-free kernels on CUDA) from the cholespy package.
    Not capturable in a CUDA graph: its kernels run on CUDA's legacy default stream. On CUDA a
    solve of more than :data:`CHOLESPY_CUDA_COLUMNS` columns (many fits at once) runs in blocks of
    that many (``max_columns``; None: one call)."""

    capturable = False

    def __init__(self, matrix: sp.spmatrix, dtype: torch.dtype, device: torch.device):
        import cholespy

        coo = sp.coo_matrix(matrix)
        cls = cholespy.CholeskySolverF if dtype == torch.float32 else cholespy.CholeskySolverD
        self.dtype, self.device = dtype, device
        self.max_columns = CHOLESPY_CUDA_COLUMNS if torch.device(device).type == "cuda" else None
        ii = torch.as_tensor(coo.row.astype(np.int32), device=device)
        jj = torch.as_tensor(coo.col.astype(np.int32), device=device)
        vals = torch.as_tensor(coo.data.astype(np.float64), device=device)
        self._solver = cls(coo.shape[0], ii, jj, vals, cholespy.MatrixType.COO)

    def solve(self, rhs: torch.Tensor) -> torch.Tensor:
        rhs = rhs.to(self.dtype).contiguous()
        out = torch.empty_like(rhs)
        if self.max_columns is None or rhs.dim() == 1 or rhs.shape[1] <= self.max_columns:
            self._solver.solve(rhs, out)
            return out
        for first in range(0, rhs.shape[1], self.max_columns):
            block = rhs[:, first:first + self.max_columns].contiguous()
            solved = torch.empty_like(block)
            self._solver.solve(block, solved)
            out[:, first:first + self.max_columns] = solved
        return out


class ScipyLUSolver:
    """scipy's SuperLU factorisation (``splu``); solves on the CPU."""

    capturable = False

    def __init__(self, matrix: sp.spmatrix, dtype: torch.dtype, device: torch.device):
        self.dtype, self.device = dtype, device
        self._lu = spla.splu(sp.csc_matrix(matrix, dtype=np.float64))

    def solve(self, rhs: torch.Tensor) -> torch.Tensor:
        out = self._lu.solve(rhs.detach().cpu().double().numpy())
        return torch.as_tensor(out, dtype=self.dtype, device=self.device)


class IglSolver:
    """libigl's ``min_quad_with_fixed`` (Eigen sparse LLT); solves on the CPU in float64."""

    capturable = False

    def __init__(self, matrix: sp.spmatrix, dtype: torch.dtype, device: torch.device):
        self.dtype, self.device = dtype, device
        self._data = igl.min_quad_with_fixed_data()
        empty = sp.csc_matrix((0, matrix.shape[0]))
        igl.min_quad_with_fixed_precompute(sp.csc_matrix(matrix, dtype=np.float64),
                                           np.zeros(0, dtype=np.int64), empty, True, self._data)

    def solve(self, rhs: torch.Tensor) -> torch.Tensor:
        # min ½ xᵀ M x + xᵀ B is solved by M x = -B.
        b = -rhs.detach().cpu().double().numpy()
        out = igl.min_quad_with_fixed_solve(self._data, b, np.zeros((0, b.shape[1])), np.zeros((0, b.shape[1])))
        return torch.as_tensor(out, dtype=self.dtype, device=self.device)


class DenseSolver:
    """The inverse as a dense (n, n) matrix, from a Cholesky factorisation in float64 on the device;
    each solve is one matrix product (one kernel, capturable in a CUDA graph). For meshes of at most
    :data:`DENSE_LIMIT` vertices (the inverse takes n² numbers)."""

    capturable = True

    def __init__(self, matrix: sp.spmatrix, dtype: torch.dtype, device: torch.device):
        n = matrix.shape[0]
        if n > DENSE_LIMIT:
            raise StatfitError(f"the dense solver takes meshes of at most {DENSE_LIMIT:,} vertices, not {n:,}; "
                               "use the cholespy solver")
        self.dtype, self.device = dtype, device
        coo = sp.coo_matrix(matrix)
        rows, cols = (torch.as_tensor(each.astype(np.int64), device=device) for each in (coo.row, coo.col))
        values = torch.as_tensor(coo.data.astype(np.float64), device=device)
        full = torch.zeros(n, n, dtype=torch.float64, device=device).index_put_((rows, cols), values, accumulate=True)
        self._inverse = torch.cholesky_inverse(torch.linalg.cholesky(full)).to(dtype)

    def solve(self, rhs: torch.Tensor) -> torch.Tensor:
        return self._inverse @ rhs.to(self.dtype)


def auto_solver(n: int, device: torch.device) -> str:
    """``dense`` on CUDA for at most :data:`DENSE_LIMIT` unknowns (one product a solve, which a CUDA
    graph captures), else ``cholespy``."""
    return "dense" if device.type == "cuda" and n <= DENSE_LIMIT else "cholespy"


def make_solver(matrix: sp.spmatrix, name: str = "cholespy", dtype: torch.dtype = torch.float32,
                device: torch.device | str = "cpu"):
    """Factorise the SPD ``matrix`` with the named solver; ``auto``: :func:`auto_solver`'s choice."""
    device = torch.device(device)
    if name == "auto":
        name = auto_solver(matrix.shape[0], device)
    classes = {"cholespy": CholespySolver, "scipy-lu": ScipyLUSolver, "igl": IglSolver, "dense": DenseSolver}
    if name not in classes:
        raise ValueError(f"unknown solver {name!r}; choose one of {', '.join(SOLVERS)}")
    return classes[name](matrix, dtype, device)
