"""Mesh Laplacians (positive semi-definite, scipy sparse CSC) and the smoothing matrix I + λL."""
from __future__ import annotations

from typing import Literal

import igl
import numpy as np
import scipy.sparse as sp

LaplacianKind = Literal["uniform", "cotangent"]


def laplacian(vertices: np.ndarray, faces: np.ndarray, kind: LaplacianKind = "uniform") -> sp.csc_matrix:
    """Graph Laplacian D - A (``uniform``, as in Nicolet et al.) or the cotangent Laplacian, (N, N)."""
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    if kind == "uniform":
        adjacency = igl.adjacency_matrix(faces).astype(np.float64).tocsr()
        adjacency.resize((len(vertices), len(vertices)))     # the vertices past the last one a face uses: none
        adjacency.data[:] = 1.0
        degree = np.asarray(adjacency.sum(axis=1)).ravel()
        return (sp.diags(degree) - adjacency).tocsc()
    if kind == "cotangent":
        return (-igl.cotmatrix(np.ascontiguousarray(vertices, dtype=np.float64), faces)).tocsc()
    raise ValueError(f"unknown Laplacian kind {kind!r}")


def smoothing_matrix(vertices: np.ndarray, faces: np.ndarray, lam: float,
                     kind: LaplacianKind = "uniform") -> sp.csc_matrix:
    """M = I + λL, symmetric positive definite for λ ≥ 0."""
    return identity_plus(laplacian(vertices, faces, kind), lam)


def identity_plus(laplacian: sp.spmatrix, lam: float) -> sp.csc_matrix:
    """I + λL for any Laplacian ``L`` (N, N): mesh or image grid."""
    return (sp.identity(laplacian.shape[0], format="csc") + lam * laplacian).tocsc()
