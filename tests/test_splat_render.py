"""The surfel renderer against a brute-force per-pixel reference, and its gradients against finite
differences (surfel parameters, and mesh vertices through the binding)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from statfit.structures.camera import Camera
from statfit.errors import StatfitError
from statfit.renderer import MeshSplats, Surfels, render_surfels


def _camera(width: int = 14, height: int = 11) -> Camera:
    return Camera.look_at([0.3, -0.2, 4.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0], 40.0, width, height)


def _random_surfels(rng: np.random.Generator, count: int, opacity_high: float = 1.0) -> Surfels:
    centres = rng.uniform(-0.6, 0.6, (count, 3))
    normals = rng.normal(size=(count, 3))
    normals[:, 2] = np.abs(normals[:, 2]) + 0.3          # mostly facing the camera at +z
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    helper = rng.normal(size=(count, 3))
    tangent_u = np.cross(normals, helper)
    tangent_u /= np.linalg.norm(tangent_u, axis=1, keepdims=True)
    tangent_v = np.cross(normals, tangent_u)
    return Surfels(*(torch.tensor(a) for a in (centres, tangent_u, tangent_v, rng.uniform(0.05, 0.35, (count, 2)),
                                              rng.uniform(0, 1, (count, 3)), rng.uniform(0.3, opacity_high, count))))


def _brute_force(surfels: Surfels, camera: Camera, background: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every pixel against every surfel, one at a time: the 2DGS formulas written out plainly
    (α clamped to 0.99, pairs below α 1/255 dropped, compositing stopped below 1e-4 light left)."""
    pose, K = camera.world_to_camera.numpy(), camera.K.numpy()
    c = surfels.centres.numpy() @ pose[:3, :3].T + pose[:3, 3]
    tu, tv = surfels.tangent_u.numpy() @ pose[:3, :3].T, surfels.tangent_v.numpy() @ pose[:3, :3].T
    scales, colours, opacity = surfels.scales.numpy(), surfels.colours.numpy(), surfels.opacity.numpy()
    image = np.zeros((camera.height, camera.width, 3))
    alpha_image = np.zeros((camera.height, camera.width))
    order = np.argsort(c[:, 2], kind="stable")
    for row in range(camera.height):
        for col in range(camera.width):
            ray = np.linalg.solve(K, [col + 0.5, row + 0.5, 1.0])
            light, colour = 1.0, np.zeros(3)
            for i in order:
                normal = np.cross(tu[i], tv[i])
                if c[i, 2] <= 1e-3 or normal @ c[i] >= 0:   # behind the camera, or seen from the back
                    continue
                t = (normal @ c[i]) / (normal @ ray)
                hit = t * ray - c[i]
                u, v = hit @ tu[i] / scales[i, 0], hit @ tv[i] / scales[i, 1]
                projected = (K @ c[i])[:2] / c[i, 2]
                lowpass = math.exp(-np.sum((np.array([col + 0.5, row + 0.5]) - projected) ** 2))
                alpha = min(0.99, opacity[i] * max(math.exp(-0.5 * (u * u + v * v)) if t > 0 else 0.0, lowpass))
                if alpha < 1 / 255 or light < 1e-4:
                    continue
                colour += light * alpha * colours[i]
                light *= 1 - alpha
            alpha_image[row, col] = 1 - light
            image[row, col] = colour + light * background
    return image, alpha_image


def _stack(count: int = 5) -> Surfels:
    """``count`` wide surfels one behind the other (opacity 0.95): the light left behind the
    fourth is 1.25e-4, behind the fifth 6e-6, below the compositing cut-off."""
    depth = torch.linspace(0.0, -0.4, count, dtype=torch.float64)
    centres = torch.stack([torch.zeros(count, dtype=torch.float64), torch.zeros(count, dtype=torch.float64), depth], 1)
    axis = lambda i: torch.eye(3, dtype=torch.float64)[i].expand(count, 3)  # noqa: E731
    colours = torch.tensor(np.random.default_rng(2).uniform(size=(count, 3)))
    return Surfels(centres, axis(0), axis(1), torch.full((count, 2), 0.5, dtype=torch.float64), colours,
                   torch.full((count,), 0.95, dtype=torch.float64))


@pytest.mark.parametrize("scene", ["random", "stacked"])
def test_the_renderer_matches_a_per_pixel_reference(scene):
    rng = np.random.default_rng(3)
    surfels = _random_surfels(rng, 12) if scene == "random" else _stack()
    camera = _camera()
    background = np.array([0.2, 0.4, 0.1])
    image = render_surfels(surfels, camera, torch.tensor(background))
    expected, expected_alpha = _brute_force(surfels, camera, background)
    assert image.pairs > 0 and expected_alpha.max() > 0.5    # a real scene: surfels overlap and cover pixels
    np.testing.assert_allclose(image.colour.numpy(), expected, atol=1e-9)
    np.testing.assert_allclose(image.alpha.numpy(), expected_alpha, atol=1e-9)


def test_a_surfel_seen_from_behind_is_culled_unless_asked():
    surfels = _random_surfels(np.random.default_rng(0), 1)
    flipped = Surfels(surfels.centres, surfels.tangent_v, surfels.tangent_u, surfels.scales.flip(1), surfels.colours,
                      surfels.opacity)
    assert float(render_surfels(surfels, _camera()).alpha.sum()) > 0
    assert float(render_surfels(flipped, _camera()).alpha.sum()) == 0
    both = render_surfels(flipped, _camera(), cull_backfaces=False).alpha
    np.testing.assert_allclose(both.numpy(), render_surfels(surfels, _camera()).alpha.numpy(), atol=1e-12)


def test_too_many_pairs_is_a_clear_error():
    with pytest.raises(StatfitError, match="pairs"):
        render_surfels(_random_surfels(np.random.default_rng(1), 12), _camera(), max_pairs=10)


def _directional_check(loss, tensors: list[torch.Tensor], rng: np.random.Generator, step: float = 1e-6) -> None:
    """∇loss · d against (loss(x + h d) − loss(x − h d)) / 2h for a random direction d per tensor."""
    for tensor in tensors:
        value = loss()
        (grad,) = torch.autograd.grad(value, [tensor])
        direction = torch.tensor(rng.normal(size=tuple(tensor.shape)))
        with torch.no_grad():
            tensor += step * direction
            ahead = float(loss())
            tensor -= 2 * step * direction
            behind = float(loss())
            tensor += step * direction
        numeric = (ahead - behind) / (2 * step)
        analytic = float((grad * direction).sum())
        assert analytic == pytest.approx(numeric, rel=1e-4, abs=1e-7), tensor.shape


def test_gradients_of_surfel_parameters_match_finite_differences():
    rng = np.random.default_rng(5)
    base = _random_surfels(rng, 8, opacity_high=0.9)   # α stays below its clamp
    leaves = [t.clone().requires_grad_(True) for t in (base.centres, base.scales, base.colours, base.opacity)]
    weights = torch.tensor(rng.uniform(size=(11, 14, 3)))
    camera = _camera()

    def loss():
        surfels = Surfels(leaves[0], base.tangent_u, base.tangent_v, leaves[1], leaves[2], leaves[3])
        image = render_surfels(surfels, camera, torch.tensor([0.3, 0.3, 0.3]))
        return (image.colour * weights).sum() + image.alpha.square().sum()

    _directional_check(loss, leaves, rng)


def _tetrahedron() -> tuple[torch.Tensor, torch.Tensor]:
    vertices = torch.tensor([[0.0, 0.0, 0.9], [0.8, -0.4, -0.2], [-0.7, -0.5, -0.1], [0.0, 0.8, -0.3]],
                            dtype=torch.float64)
    faces = torch.tensor([[0, 1, 3], [0, 3, 2], [0, 2, 1], [1, 2, 3]])
    return vertices, faces


def test_gradients_reach_the_vertices_through_the_binding():
    rng = np.random.default_rng(7)
    vertices, faces = _tetrahedron()
    vertices.requires_grad_(True)
    splats = MeshSplats.on(faces, 4, dtype=torch.float64)
    with torch.no_grad():
        splats.colour_logit.copy_(torch.tensor(rng.normal(size=splats.colour_logit.shape)))
        splats.angle.copy_(torch.tensor(rng.uniform(-1, 1, len(splats))))
        splats.opacity_logit.fill_(0.5)
    camera = _camera(16, 16)
    weights = torch.tensor(rng.uniform(size=(16, 16, 3)))

    def loss():
        return (render_surfels(splats.surfels(vertices), camera).colour * weights).sum()

    assert float(render_surfels(splats.surfels(vertices), camera).alpha.detach().max()) > 0.3
    _directional_check(loss, [vertices, splats.angle, splats.log_scale, splats.colour_logit], rng)


def test_moving_the_mesh_moves_its_splats():
    vertices, faces = _tetrahedron()
    splats = MeshSplats.on(faces, 3, dtype=torch.float64)
    before = splats.surfels(vertices)
    rotation = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    after = splats.surfels(2.0 * vertices @ rotation.T + torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64))
    torch.testing.assert_close(after.centres, 2.0 * before.centres @ rotation.T + torch.tensor([1.0, 2.0, 3.0],
                                                                                               dtype=torch.float64))
    torch.testing.assert_close(after.tangent_u, before.tangent_u @ rotation.T)
    torch.testing.assert_close(after.scales, 2.0 * before.scales)
    normal = torch.linalg.cross(after.tangent_u, after.tangent_v, dim=1)
    face_normal = torch.linalg.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]],
                                     vertices[faces[:, 2]] - vertices[faces[:, 0]], dim=1) @ rotation.T
    face_normal = face_normal / face_normal.norm(dim=1, keepdim=True)
    torch.testing.assert_close(normal, face_normal.repeat_interleave(3, dim=0))


def test_a_zero_area_triangle_changes_nothing_and_spreads_no_nan():
    """A model with a collapsed triangle (all three corners one vertex; found by a fuzz of odd models,
    where every `statfit splat` fit of it ended "diverged at iteration 1"): its splat has no axes, so
    it is never drawn, and its 0/0 must not reach the gradient. The image and the vertices' gradient
    are those of the mesh without it."""
    vertices, faces = _tetrahedron()
    collapsed = torch.cat([faces, faces[:1, :1].repeat(1, 3)])
    camera = _camera(16, 16)
    weights = torch.tensor(np.random.default_rng(3).uniform(size=(16, 16, 3)))
    results = []
    for mesh_faces in (faces, collapsed):
        corners = vertices.clone().requires_grad_(True)
        splats = MeshSplats.on(mesh_faces, 3, dtype=torch.float64)
        image = render_surfels(splats.surfels(corners), camera)
        (image.colour * weights).sum().backward()
        results.append((image.colour.detach(), corners.grad))
    (clean_image, clean_grad), (image, grad) = results
    assert torch.isfinite(grad).all()
    torch.testing.assert_close(image, clean_image, rtol=0, atol=1e-12)
    torch.testing.assert_close(grad, clean_grad, rtol=1e-9, atol=1e-12)
