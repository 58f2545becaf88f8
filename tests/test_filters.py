"""Filters against their dense closed forms (float64)."""
from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from statfit.core.filters import HybridFilter, LaplacianFilter, StatisticalFilter, beta_with_power
from statfit.core.laplacian import laplacian, smoothing_matrix
from statfit.core.solvers import SOLVERS


def random_basis(rng, n3: int, k: int) -> np.ndarray:
    q, _ = np.linalg.qr(rng.standard_normal((n3, k)))
    return q


@pytest.fixture
def sphere():
    mesh = trimesh.creation.icosphere(subdivisions=2)
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


def apply(filter_, g: np.ndarray) -> np.ndarray:
    return filter_(torch.as_tensor(g.reshape(-1, 3))).reshape(-1).numpy()


@pytest.mark.parametrize("beta", [0.5, 30.0, 300.0])
def test_statistical_filter_is_the_inverse_of_i_plus_beta_projector(rng, beta):
    u = random_basis(rng, 60, 7)
    g = rng.standard_normal(60)
    dense = np.linalg.solve(np.eye(60) + beta * (np.eye(60) - u @ u.T), g)
    got = apply(StatisticalFilter(torch.as_tensor(u.T), beta), g)
    np.testing.assert_allclose(got, dense, rtol=1e-12, atol=1e-12)
    alpha = beta / (1 + beta)
    np.testing.assert_allclose(got, alpha * u @ (u.T @ g) + (1 - alpha) * g, rtol=1e-12)


@pytest.mark.parametrize("power", [0.5, 2.0, 3.0])
def test_power_of_filter_equals_filter_with_adjusted_beta(rng, power):
    u = random_basis(rng, 45, 5)
    beta, g = 30.0, rng.standard_normal(45)
    p = np.linalg.inv(np.eye(45) + beta * (np.eye(45) - u @ u.T))
    w, v = np.linalg.eigh(p)
    p_power = (v * w**power) @ v.T
    got = apply(StatisticalFilter(torch.as_tensor(u.T), beta, power=power), g)
    np.testing.assert_allclose(got, p_power @ g, rtol=1e-10, atol=1e-12)
    same = apply(StatisticalFilter(torch.as_tensor(u.T), beta_with_power(beta, power)), g)
    np.testing.assert_allclose(got, same, rtol=1e-12)


@pytest.mark.parametrize("a,b", [(1.0, 30.0), (0.2, -0.1), (3.0, 0.5)])
def test_inverse_of_a_identity_plus_b_projector_has_the_same_form(rng, a, b):
    u = random_basis(rng, 30, 4)
    p = u @ u.T  # idempotent
    mu, nu = 1 / a, -b / (a * (a + b))
    np.testing.assert_allclose(np.linalg.inv(a * np.eye(30) + b * p), mu * np.eye(30) + nu * p, atol=1e-12)


def test_mode_gain_scales_each_mode(rng):
    u = random_basis(rng, 36, 6)
    gain = np.linspace(1.0, 0.2, 6)
    beta, g = 30.0, rng.standard_normal(36)
    off = 1 / (1 + beta)
    dense = u @ np.diag(gain) @ u.T + off * (np.eye(36) - u @ u.T)
    got = apply(StatisticalFilter(torch.as_tensor(u.T), beta, mode_gain=torch.as_tensor(gain)), g)
    np.testing.assert_allclose(got, dense @ g, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("solver", SOLVERS)
@pytest.mark.parametrize("kind", ["uniform", "cotangent"])
def test_laplacian_filter_equals_dense_solve(sphere, rng, solver, kind):
    v, f = sphere
    g = rng.standard_normal((len(v), 3))
    dense = np.linalg.solve(smoothing_matrix(v, f, 19.0, kind).toarray(), g)
    got = LaplacianFilter(v, f, 19.0, kind, solver, dtype=torch.float64)(torch.as_tensor(g)).numpy()
    np.testing.assert_allclose(got, dense, rtol=1e-9, atol=1e-10)


def test_laplacians_are_positive_semidefinite_with_constant_kernel(sphere):
    v, f = sphere
    for kind in ("uniform", "cotangent"):
        lap = laplacian(v, f, kind).toarray()
        np.testing.assert_allclose(lap, lap.T, atol=1e-12)
        np.testing.assert_allclose(lap @ np.ones(len(v)), 0, atol=1e-10)
        assert np.linalg.eigvalsh(lap).min() > -1e-9


def test_hybrid_filter_equals_dense_formula(sphere, rng):
    v, f = sphere
    n3 = 3 * len(v)
    u = random_basis(rng, n3, 8)
    beta, lam = 30.0, 19.0
    alpha = beta / (1 + beta)
    m_inv = np.linalg.inv(smoothing_matrix(v, f, lam).toarray())
    smooth = np.kron(m_inv, np.eye(3))  # vertex-major flattening: the Laplacian acts per channel
    dense = alpha * u @ u.T + (1 - alpha) * smooth
    g = rng.standard_normal(n3)
    lap = LaplacianFilter(v, f, lam, dtype=torch.float64)
    got = apply(HybridFilter(torch.as_tensor(u.T), beta, lap), g)
    np.testing.assert_allclose(got, dense @ g, rtol=1e-9, atol=1e-10)


def test_filters_are_symmetric(sphere, rng):
    v, f = sphere
    n3 = 3 * len(v)
    u = torch.as_tensor(random_basis(rng, n3, 5).T)
    lap = LaplacianFilter(v, f, 5.0, dtype=torch.float64)
    for filt in (StatisticalFilter(u, 10.0), lap, HybridFilter(u, 10.0, lap)):
        a, b = rng.standard_normal(n3), rng.standard_normal(n3)
        assert apply(filt, a) @ b == pytest.approx(a @ apply(filt, b), rel=1e-10)


def test_a_factorisation_is_reused_for_the_same_mesh_and_lambda_only():
    """Stages and fits of one mesh and λ share a factorisation (the same solver, the same solves);
    another λ, another mesh or another thread factorises afresh."""
    import threading

    from statfit.core.filters import KEPT_FACTORISATIONS, LaplacianFilter

    mesh = trimesh.creation.icosphere(subdivisions=1)
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    first = LaplacianFilter(vertices, faces, 19.0)
    again = LaplacianFilter(vertices.copy(), faces.copy(), 19.0)
    assert again._solver is first._solver
    assert LaplacianFilter(vertices, faces, 5.0)._solver is not first._solver
    other = trimesh.creation.icosphere(subdivisions=2)
    assert LaplacianFilter(np.asarray(other.vertices), np.asarray(other.faces), 19.0)._solver is not first._solver
    assert KEPT_FACTORISATIONS == 2   # the two above pushed the first one out
    assert LaplacianFilter(vertices, faces, 19.0)._solver is not first._solver
    elsewhere = []
    thread = threading.Thread(target=lambda: elsewhere.append(LaplacianFilter(vertices, faces, 19.0)._solver))
    thread.start()
    thread.join()
    assert elsewhere[0] is not LaplacianFilter(vertices, faces, 19.0)._solver
    g = torch.randn(len(vertices), 3)
    torch.testing.assert_close(again(g), LaplacianFilter(vertices, faces, 19.0)(g))
