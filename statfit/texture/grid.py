"""The 4-neighbour graph Laplacian of an H × W pixel grid, optionally restricted to UV charts.

Pixels are numbered row-major (``i * W + j``), the order of ``image.reshape(H * W, C)``. The
unrestricted Laplacian is ``L = I_H ⊗ L_W + L_H ⊗ I_W`` with ``L_n`` the path graph's Laplacian.

**Charts.** A texture atlas packs several UV charts into one image; pixels that touch in the image
but lie in different charts are far apart on the surface, and pixels outside every chart (the
gutter) carry no surface at all. With ``charts`` (H, W) integer labels (0 = outside every chart),
an edge is kept only when both its pixels carry the same non-zero label. Colour then diffuses inside
each chart and never across a chart border; a gutter pixel has no edges (its row of L is zero, so
``(I + λL)⁻¹`` leaves it alone).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from statfit.errors import StatfitError


def path_laplacian(n: int) -> sp.csr_matrix:
    """Laplacian D − A of the path graph 0 – 1 – … – n−1, (n, n)."""
    adjacency = sp.diags([np.ones(n - 1), np.ones(n - 1)], [-1, 1], shape=(n, n), format="csr")
    return (sp.diags(np.asarray(adjacency.sum(axis=1)).ravel()) - adjacency).tocsr()


def grid_laplacian(height: int, width: int, charts: np.ndarray | None = None) -> sp.csc_matrix:
    """The grid Laplacian (H·W, H·W), positive semi-definite, rows summing to zero; with
    ``charts`` (H, W) labels, only edges inside one chart (module docstring)."""
    if height < 1 or width < 1:
        raise StatfitError(f"an image grid needs a positive size, got {height}×{width}")
    laplacian = (sp.kron(sp.identity(height), path_laplacian(width))
                 + sp.kron(path_laplacian(height), sp.identity(width)))
    if charts is None:
        return laplacian.tocsc()
    charts = np.asarray(charts)
    if charts.shape != (height, width):
        raise StatfitError(f"the chart image is {charts.shape[1]}×{charts.shape[0]} but the texture is "
                           f"{width}×{height}")
    labels = charts.reshape(-1)
    adjacency = sp.coo_matrix(sp.diags(laplacian.diagonal()) - laplacian)
    keep = (labels[adjacency.row] == labels[adjacency.col]) & (labels[adjacency.row] != 0)
    adjacency = sp.coo_matrix((adjacency.data[keep], (adjacency.row[keep], adjacency.col[keep])), shape=laplacian.shape)
    degree = np.asarray(adjacency.sum(axis=1)).ravel()
    return (sp.diags(degree) - adjacency).tocsc()
