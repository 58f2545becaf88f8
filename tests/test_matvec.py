"""The basis mat-vecs on every thread count agree with a plain product (float64, numpy)."""
import numpy as np
import pytest
import torch

from statfit.core.matvec import expand, project
from statfit.core.threads import intra_op_threads


@pytest.mark.parametrize("threads", [1, 2, 3])
@pytest.mark.parametrize("columns", [2, 30, 3 * 1001])
def test_blocked_products_match_numpy(threads, columns):
    rng = np.random.default_rng(columns)
    basis_t, twice, coeff = rng.normal(size=(7, columns)), rng.normal(size=2 * columns), rng.normal(size=7)
    v = twice[::2]                       # a strided vector, as a view of another tensor can be
    t = torch.from_numpy
    with intra_op_threads(threads):
        projected = project(t(basis_t), t(twice)[::2]).numpy()
        expanded = expand(t(basis_t), t(coeff)).numpy()
        added = expand(t(basis_t), t(coeff), t(twice)[::2], 0.25).numpy()
    np.testing.assert_allclose(projected, basis_t @ v, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(expanded, basis_t.T @ coeff, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(added, 0.25 * v + basis_t.T @ coeff, rtol=1e-12, atol=1e-12)
