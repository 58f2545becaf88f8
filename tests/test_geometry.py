"""Closest points, the scan term's gradient, parametrisation pull-backs and pre-alignment."""
from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial.transform import Rotation

from statfit.geometry.align import Similarity, icp, umeyama
from statfit.geometry.closest import ClosestPointQuery, closest_on_triangles
from statfit.objectives.scan import ScanObjective
from statfit.core.filters import StatisticalFilter
from statfit.core.parametrize import FilteredVertices, PCACoefficients, RegularizedVertices


def test_closest_points_match_brute_force(embedded_model, rng):
    """Against trimesh's per-triangle closest point evaluated on every triangle (exact)."""
    mesh = trimesh.Trimesh(embedded_model.template, embedded_model.faces, process=False)
    points = mesh.sample(150, seed=5) + rng.normal(scale=0.01, size=(150, 3))
    triangles = np.tile(mesh.triangles, (len(points), 1, 1))
    nearest = trimesh.triangles.closest_point(triangles, np.repeat(points, len(mesh.faces), axis=0))
    expected = np.linalg.norm(nearest - np.repeat(points, len(mesh.faces), axis=0), axis=1)
    expected = expected.reshape(len(points), -1).min(axis=1)
    hit = ClosestPointQuery(embedded_model.faces, len(mesh.vertices), k=12)(
        torch.as_tensor(mesh.vertices), torch.as_tensor(points))
    np.testing.assert_allclose(hit.distance.numpy(), expected, atol=1e-9)
    surface = (mesh.vertices[mesh.faces[hit.triangle.numpy()]] * hit.barycentric.numpy()[..., None]).sum(axis=1)
    np.testing.assert_allclose(np.linalg.norm(surface - points, axis=1), expected, atol=1e-9)
    assert (hit.barycentric.numpy() >= -1e-12).all()
    fast = ClosestPointQuery(embedded_model.faces, len(mesh.vertices), k=2)(
        torch.as_tensor(mesh.vertices), torch.as_tensor(points))
    assert np.mean(np.abs(fast.distance.numpy() - expected) < 1e-9) > 0.95  # the fit's cheaper candidate set


def test_closest_points_with_a_vertex_of_no_triangle_and_a_tie():
    """A vertex of no triangle lists triangle 0, so a point nearest it still has candidates; a point
    equally near two triangles gets the one listed first around its nearest vertex (argmin's rule)."""
    vertices = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [5, 5, 0]], dtype=torch.float64)
    faces = np.array([[0, 1, 2], [1, 3, 2]])                     # vertex 4: in no triangle
    points = torch.tensor([[5.0, 5.0, 0.1], [0.3, 0.7, 1.0]], dtype=torch.float64)
    hit = ClosestPointQuery(faces, len(vertices), k=2)(vertices, points)
    # the first point's candidates: triangle 0 (vertex 4's stand-in) and triangle 1 (vertex 3's)
    assert hit.triangle.tolist() == [1, 0]
    torch.testing.assert_close(hit.distance, torch.tensor([32.01 ** 0.5, 1.0], dtype=torch.float64))
    torch.testing.assert_close(hit.barycentric[0], torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))


def test_closest_point_regions_of_one_triangle():
    a, b, c = (torch.tensor(v, dtype=torch.float64) for v in ([0, 0, 0], [1, 0, 0], [0, 1, 0]))
    points = torch.tensor([[0.2, 0.2, 1.0], [-1, -1, 0], [2, -1, 0], [0.5, -1, 0], [1, 1, 0]], dtype=torch.float64)
    bary, sq = closest_on_triangles(points, a, b, c)
    expected = torch.tensor([[0.6, 0.2, 0.2], [1, 0, 0], [0, 1, 0], [0.5, 0.5, 0], [0, 0.5, 0.5]], dtype=torch.float64)
    torch.testing.assert_close(bary, expected)
    torch.testing.assert_close(sq, torch.tensor([1.0, 2.0, 2.0, 1.0, 0.5], dtype=torch.float64))


def test_scan_term_gradient_matches_central_differences(embedded_model, rng):
    verts = torch.as_tensor(embedded_model.template)
    mesh = trimesh.Trimesh(embedded_model.template, embedded_model.faces, process=False)
    points = torch.as_tensor(mesh.sample(300, seed=2) + rng.normal(scale=0.003, size=(300, 3)))
    objective = ScanObjective(points, ClosestPointQuery(embedded_model.faces, len(verts)), trim=0.0)
    objective.prepare(verts, 0)
    x = verts.clone().requires_grad_(True)
    objective(x)["data"].backward()
    touched = torch.nonzero(x.grad.abs().sum(dim=1)).ravel()[:20]
    h = 1e-6
    for v in touched.tolist():
        for axis in range(3):
            plus, minus = verts.clone(), verts.clone()
            plus[v, axis] += h
            minus[v, axis] -= h
            numeric = (float(objective(plus)["data"]) - float(objective(minus)["data"])) / (2 * h)
            assert x.grad[v, axis].item() == pytest.approx(numeric, rel=1e-5, abs=1e-9)


def test_exact_point_to_surface_gradient_at_refresh(embedded_model, rng):
    """At a refresh the held attachment gives the gradient of the true point-to-surface distance."""
    verts = torch.as_tensor(embedded_model.template)
    query = ClosestPointQuery(embedded_model.faces, len(verts), k=6)
    mesh = trimesh.Trimesh(embedded_model.template, embedded_model.faces, process=False)
    points = torch.as_tensor(mesh.sample(200, seed=4) + rng.normal(scale=0.004, size=(200, 3)))
    objective = ScanObjective(points, query, trim=0.0)
    objective.prepare(verts, 0)
    x = verts.clone().requires_grad_(True)
    objective(x)["data"].backward()
    true_loss = lambda v: float(query(v, points).distance.square().mean())
    direction = torch.as_tensor(rng.standard_normal(verts.shape)) * (x.grad.abs().sum(1, keepdim=True) > 0)
    h = 1e-7
    numeric = (true_loss(verts + h * direction) - true_loss(verts - h * direction)) / (2 * h)
    assert float((x.grad * direction).sum()) == pytest.approx(numeric, rel=1e-3)


def test_pull_backs_match_autograd(embedded_model, rng):
    """Each parametrisation's explicit backward equals autograd through its formula."""
    mean = torch.as_tensor(embedded_model.template)
    basis_t = torch.as_tensor(embedded_model.basis.T)
    weights = torch.as_tensor(rng.standard_normal(mean.shape))
    loss = lambda x: (weights * x).sum() + x.square().sum()

    pca = PCACoefficients(mean, basis_t * 0.01, torch.as_tensor(rng.standard_normal(basis_t.shape[0])))
    loss(pca.vertices()).backward()
    c = pca.coeffs.detach().clone().requires_grad_(True)
    loss(mean + (basis_t.t() * 0.01 @ c).view_as(mean)).backward()
    torch.testing.assert_close(pca.coeffs.grad, c.grad)

    start = mean + 0.01 * torch.as_tensor(rng.standard_normal(mean.shape))
    reg = RegularizedVertices(start, mean, basis_t, beta=10.0)
    x = reg.vertices()
    prior = reg.prior(x)["prior"]
    loss(x).backward()  # the prior's gradient comes with the vertices
    y = start.clone().requires_grad_(True)
    off = (y - mean).reshape(-1)
    outside = off - basis_t.t() @ (basis_t @ off)
    total = loss(y) + 10.0 / len(mean) * outside.square().sum()
    total.backward()
    torch.testing.assert_close(reg.x.grad, y.grad)
    assert float(prior) == pytest.approx(float(10.0 / len(mean) * outside.detach().square().sum()))

    filtered_x = FilteredVertices(mean, StatisticalFilter(basis_t, 30.0))
    x = filtered_x.vertices()
    loss(x).backward()
    g = (weights + 2 * x.detach()).reshape(-1)  # ∂loss/∂x in closed form; ∂/∂u = α UUᵀ g + (1 − α) g
    expected = 30.0 / 31.0 * basis_t.t() @ (basis_t @ g) + g / 31.0
    torch.testing.assert_close(filtered_x.u.grad.reshape(-1), expected)


@pytest.mark.parametrize("with_scale", [False, True])
def test_icp_recovers_a_known_pose(embedded_model, rng, with_scale):
    rotation = Rotation.from_euler("xyz", [8, -15, 5], degrees=True).as_matrix()
    truth = Similarity(1.7 if with_scale else 1.0, rotation, np.array([0.02, -0.01, 0.03]))
    mesh = trimesh.Trimesh(embedded_model.template, embedded_model.faces, process=False)
    points = truth.apply(mesh.sample(3000, seed=9))
    found = icp(embedded_model.template, embedded_model.faces, points, with_scale,
                start=Similarity(1.6 if with_scale else 1.0, np.eye(3), np.zeros(3)))
    moved = np.abs(found.apply(embedded_model.template) - truth.apply(embedded_model.template)).max()
    assert moved < 1e-3 * truth.scale


def test_umeyama_exact(rng):
    src = rng.standard_normal((50, 3))
    truth = Similarity(2.5, Rotation.random(random_state=3).as_matrix(), rng.standard_normal(3))
    got = umeyama(src, truth.apply(src), with_scale=True)
    np.testing.assert_allclose(got.apply(src), truth.apply(src), atol=1e-10)


def test_kd_trees_build_while_the_thread_flushes_subnormals():
    """A fit's thread flushes subnormals to zero; SciPy's balanced KD-tree build then recursed
    without end on many coordinates tied at zero and the process died of a segmentation fault. Run in a child process, so a crash is a failed test, not a lost worker;
    the tree must be the one built without flushing, and the thread's mode restored."""
    import subprocess
    import sys

    child = """
import numpy as np, torch
from statfit.structures.kdtree import flushes_subnormals, kd_tree
points = np.random.default_rng(0).normal(size=(1000, 3))
points[:300, 0] = 0.0                              # 300 points on the plane x = 0
plain = kd_tree(points)
torch.set_flush_denormal(True)
assert flushes_subnormals()
tree = kd_tree(points)
assert flushes_subnormals()
query = np.random.default_rng(1).normal(size=(200, 3))
assert all((a == b).all() for a, b in zip(tree.query(query, k=3), plain.query(query, k=3)))
torch.set_flush_denormal(False)
assert not flushes_subnormals()
print("built")
"""
    done = subprocess.run([sys.executable, "-c", child], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout.strip() == "built", (done.returncode, done.stderr[-2000:])
