"""Differentiable rasteriser (statfit.renderer): camera, visibility against a ray caster,
perspective-correct interpolation, antialiasing, and gradients against finite differences."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import trimesh

from conftest import ICT_DIR
from statfit.errors import StatfitError
from statfit.renderer import (Camera, EdgeCrossings, MeshAdjacency, interpolate, normal_image, rasterize, render_normals,
                            silhouette_crossings, vertex_normals)

ICT_PATH = ICT_DIR / "ict_face_identity.npz"


@pytest.fixture(autouse=True)
def _threads():
    """Overrides conftest's: one thread (small tensors; OpenMP spin-waits suffer on a shared CPU)."""
    torch.set_num_threads(1)


@pytest.fixture(scope="module")
def head() -> tuple[np.ndarray, np.ndarray]:
    """ICT head: vertices (11248, 3) float64 in cm (+y up, +z out of the face), faces (22288, 3) int64."""
    if not ICT_PATH.is_file():
        pytest.skip(f"ICT data not found at {ICT_PATH}")
    with np.load(ICT_PATH) as data:
        return data["v_template"].astype(np.float64), data["faces"].astype(np.int64)


@pytest.fixture(scope="module")
def head_torch(head) -> tuple[torch.Tensor, torch.Tensor, MeshAdjacency]:
    faces = torch.as_tensor(head[1])
    return torch.as_tensor(head[0]), faces, MeshAdjacency.from_faces(faces)


def frontal(center: tuple[float, float], fov_deg: float, size: int, distance: float = 60.0) -> Camera:
    """Camera on +z looking along −z at (x, y, 0), image up = +y."""
    x, y = center
    return Camera.look_at([x, y, distance], [x, y, 0.0], [0.0, 1.0, 0.0], fov_deg, size, size)


def outline(covered: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels whose 3×3 neighbourhood mixes covered and uncovered pixels."""
    padded = np.pad(covered, 1, mode="edge")
    windows = np.lib.stride_tricks.sliding_window_view(padded, (3, 3))
    return windows.any(axis=(2, 3)) & ~windows.all(axis=(2, 3))


# --- camera -----------------------------------------------------------------------------------

def test_camera_projection_follows_opencv_convention():
    camera = Camera.look_at([0.0, 0.0, 10.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0], 90.0, 200, 100)
    np.testing.assert_allclose(camera.K.numpy(), [[50, 0, 100], [0, 50, 50], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(camera.center.numpy(), [0, 0, 10], atol=1e-12)
    points = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 5.0]], dtype=torch.float64)
    pixels, depth = camera.project(points)
    # centre → principal point; world +x → right (larger column); world up → top (smaller row)
    np.testing.assert_allclose(pixels.numpy(), [[100, 50], [105, 50], [100, 45], [100, 50]], atol=1e-12)
    np.testing.assert_allclose(depth.numpy(), [10, 10, 10, 5], atol=1e-12)
    origin, directions = camera.pixel_rays()
    assert directions.shape == (100, 200, 3)
    hits = origin + 7.0 * directions[[0, 99, 40], [0, 199, 120]]          # pixel centres (col + .5, row + .5)
    np.testing.assert_allclose(camera.project(hits)[0].numpy(), [[0.5, 0.5], [199.5, 99.5], [120.5, 40.5]],
                               atol=1e-9)


def test_camera_json_round_trip():
    camera = Camera.look_at([3.0, -2.0, 40.0], [0.5, 1.0, 0.0], [0.1, 1.0, 0.0], 35.0, 320, 240)
    data = json.loads(json.dumps(camera.to_dict()))
    assert data["convention"] == "opencv" and (data["width"], data["height"]) == (320, 240)
    restored = Camera.from_dict(data)
    assert (restored.width, restored.height) == (320, 240)
    torch.testing.assert_close(restored.K, camera.K)
    torch.testing.assert_close(restored.world_to_camera, camera.world_to_camera)
    assert restored.to_dict() == camera.to_dict()


@pytest.mark.parametrize("change, message", [
    ({"K": [[500.0, 0.0, 32.0], [0.0, 0.0, 32.0], [0.0, 0.0, 1.0]]}, "singular"),
    ({"K": [[1.0, 2.0, 3.0], [2.0, 4.0, 6.0], [0.0, 0.0, 1.0]]}, "singular"),
    ({"K": [[500.0, 0.0, 32.0], [0.0, 500.0, 32.0], [0.0, 1.0, 1.0]]}, "bottom row"),
    ({"K": [[500.0, 0.0], [0.0, 500.0]]}, "shape"),
    ({"width": 0}, "width"),
    ({"height": -3}, "height"),
    ({"width": 64.5}, "width"),
    ({"world_to_camera": np.diag([2.0, 2.0, 2.0, 1.0])}, "rigid"),
    ({"world_to_camera": np.diag([1.0, 1.0, -1.0, 1.0])}, "rigid"),
    ({"world_to_camera": np.full((4, 4), np.nan)}, "non-finite"),
])
def test_bad_camera_raises(change, message):
    fields = {"width": 64, "height": 64, "K": [[500.0, 0.0, 32.0], [0.0, 500.0, 32.0], [0.0, 0.0, 1.0]],
              "world_to_camera": np.eye(4)} | change
    with pytest.raises(StatfitError, match=message):
        Camera(**fields)


def test_bad_camera_description_raises():
    good = Camera.look_at([0.0, 0.0, 5.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0], 40.0, 32, 32).to_dict()
    with pytest.raises(StatfitError, match="convention"):
        Camera.from_dict(good | {"convention": "directx"})
    with pytest.raises(StatfitError, match="lacks K"):
        Camera.from_dict({key: value for key, value in good.items() if key != "K"})
    with pytest.raises(StatfitError, match="coincide"):
        Camera.look_at([1.0, 2.0, 3.0], [1.0, 2.0, 3.0], [0.0, 1.0, 0.0], 40.0, 32, 32)
    with pytest.raises(StatfitError, match="parallel"):
        Camera.look_at([0.0, 5.0, 0.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0], 40.0, 32, 32)


# --- visibility -------------------------------------------------------------------------------

def test_rasterize_matches_ray_caster(head):
    """Triangle ids and depths against trimesh/embree rays through the pixel centres, in an oblique
    view with self-occlusion (nose over cheek, ear over head)."""
    vertices, faces = head
    direction = np.array([np.sin(np.radians(40)), 0.25, np.cos(np.radians(40))])
    camera = Camera.look_at(55 * direction / np.linalg.norm(direction) + [0, -2, 0], [0.0, -2.0, 0.0],
                            [0.0, 1.0, 0.0], 40.0, 256, 256)
    fragments = rasterize(torch.as_tensor(vertices, dtype=torch.float32), torch.as_tensor(faces), camera)
    ids = fragments.triangle.numpy().reshape(-1)

    origin, directions = camera.pixel_rays()
    rays = directions.reshape(-1, 3).numpy()
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    locations, ray_index, hit_tri = mesh.ray.intersects_location(np.broadcast_to(origin.numpy(), rays.shape), rays,
                                                                 multiple_hits=False)
    reference = np.full(len(rays), -1)
    reference[ray_index] = hit_tri
    both = (ids >= 0) & (reference >= 0)
    assert both.sum() > 20000
    assert np.mean(ids[both] == reference[both]) >= 0.995
    differ = (ids >= 0) != (reference >= 0)
    assert not (differ & ~outline((ids >= 0).reshape(256, 256)).reshape(-1)).any()

    same = ids[ray_index] == hit_tri
    ray_depth = camera.to_camera(torch.as_tensor(locations[same]))[:, 2].numpy()
    np.testing.assert_allclose(fragments.depth.numpy().reshape(-1)[ray_index[same]], ray_depth, rtol=1e-5)
    assert np.isinf(fragments.depth.numpy().reshape(-1)[ids < 0]).all()


def test_chunked_rasterization_is_identical(head_torch):
    vertices, faces, _ = head_torch
    camera = frontal((0.0, -2.0), 40.0, 128)
    whole = rasterize(vertices, faces, camera)
    chunked = rasterize(vertices, faces, camera, max_candidates=1000)
    assert torch.equal(whole.triangle, chunked.triangle)
    assert torch.equal(whole.depth, chunked.depth)


def test_screen_filling_triangles_with_a_small_budget():
    """Two triangles far larger than the image, rasterised with a budget much smaller than W·H."""
    camera = Camera(48, 32, np.eye(3), np.eye(4))                     # pixel = (x / z, y / z)
    vertices = torch.tensor([[-100.0, -100.0, 2.0], [100.0, -100.0, 2.0], [100.0, 100.0, 2.0],
                             [-100.0, 100.0, 2.0]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    fragments = rasterize(vertices, faces, camera, max_candidates=100)
    rows, cols = np.mgrid[0:32, 0:48]
    triangle = fragments.triangle.numpy()
    assert (triangle[cols > rows] == 0).all() and (triangle[cols < rows] == 1).all()
    assert np.isin(triangle[cols == rows], [0, 1]).all()              # centres on the shared edge: either
    np.testing.assert_allclose(fragments.depth.numpy(), 2.0)


def test_triangles_behind_the_near_plane_are_culled(head_torch):
    """A camera inside the head: triangles with a vertex behind it are not drawn, and neither
    the images nor their gradients contain non-finite values."""
    vertices, faces, adjacency = head_torch
    camera = frontal((0.0, 0.0), 100.0, 48, distance=5.0)
    behind = camera.project(vertices)[1] <= 1e-3
    assert behind.any()
    fragments = rasterize(vertices, faces, camera)
    drawn = fragments.triangle[fragments.triangle >= 0].unique()
    assert not behind[faces[drawn]].any()
    moving = vertices.clone().requires_grad_()
    normals, mask = render_normals(moving, faces, camera, adjacency=adjacency)
    (normals.sum() + mask.sum()).backward()
    assert torch.isfinite(normals).all() and torch.isfinite(mask).all() and torch.isfinite(moving.grad).all()


def test_empty_view_and_bad_meshes(head_torch):
    vertices, faces, adjacency = head_torch
    away = Camera.look_at([0.0, 0.0, 60.0], [0.0, 0.0, 120.0], [0.0, 1.0, 0.0], 30.0, 32, 32)
    moving = vertices.clone().requires_grad_()
    normals, mask = render_normals(moving, faces, away, adjacency=adjacency)
    assert (normals == 0).all() and (mask == 0).all()
    (normals.sum() + mask.sum()).backward()
    assert (moving.grad == 0).all()
    with pytest.raises(StatfitError, match="faces"):
        rasterize(vertices, faces.int(), away)
    with pytest.raises(StatfitError, match="vertices"):
        rasterize(vertices[:, :2], faces, away)


def test_mesh_adjacency():
    tetrahedron = torch.tensor([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
    adjacency = MeshAdjacency.from_faces(tetrahedron)
    # edge i of triangle t runs from corner i+1 to i+2; across it lies the tetrahedron's 4th vertex
    expected = [[({0, 1, 2, 3} - set(tetrahedron[t].tolist())).pop()] * 3 for t in range(4)]
    assert adjacency.opposite.tolist() == expected
    for t in range(4):
        for i in range(3):
            other = adjacency.neighbor[t, i]
            edge = {int(tetrahedron[t, (i + 1) % 3]), int(tetrahedron[t, (i + 2) % 3])}
            assert other != t and edge <= set(tetrahedron[other].tolist())
    single = MeshAdjacency.from_faces(torch.tensor([[4, 5, 6]]))
    assert single.opposite.tolist() == [[4, 5, 6]] and single.neighbor.tolist() == [[-1, -1, -1]]


# --- interpolation and normals ----------------------------------------------------------------

def test_interpolation_is_perspective_correct(head_torch):
    """Interpolated camera-space positions lie on the pixel-centre rays at the z-buffer depth."""
    vertices, faces, _ = head_torch
    camera = frontal((0.0, -2.0), 30.0, 96, distance=35.0)
    fragments = rasterize(vertices, faces, camera)
    points = interpolate(camera.to_camera(vertices), faces, fragments)[fragments.triangle >= 0]   # (M, 3)
    pixel = fragments.pixel
    centres = torch.stack([pixel % 96, pixel // 96], dim=1).double() + 0.5
    torch.testing.assert_close(camera.camera_to_pixels(points), centres, atol=1e-8, rtol=0)
    torch.testing.assert_close(points[:, 2], fragments.depth.view(-1)[pixel], rtol=1e-6, atol=0)
    corners = camera.to_camera(vertices)[faces[fragments.face]]                                  # (M, 3, 3)
    torch.testing.assert_close((fragments.barycentric.T[..., None] * corners).sum(dim=1), points)
    torch.testing.assert_close(fragments.barycentric.sum(dim=0), torch.ones(len(pixel), dtype=torch.float64))


def test_vertex_normals(head):
    vertices, faces = head
    corners = vertices[faces]
    face_normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    expected = np.zeros_like(vertices)
    for corner in range(3):
        np.add.at(expected, faces[:, corner], face_normals)
    expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    normals = vertex_normals(torch.as_tensor(vertices), torch.as_tensor(faces)).numpy()
    np.testing.assert_allclose(normals, expected, atol=1e-12)
    assert normals[np.argmax(vertices[:, 2]), 2] > 0.95                # outward at the nose tip
    tetrahedron = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.1, 0.0], [0.2, 1.0, 0.1], [0.3, 0.2, 1.0]],
                               dtype=torch.float64, requires_grad=True)
    tet_faces = torch.tensor([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
    assert torch.autograd.gradcheck(lambda v: vertex_normals(v, tet_faces), (tetrahedron,))


def test_render_normals(head_torch):
    vertices, faces, adjacency = head_torch
    camera = frontal((0.0, -2.0), 40.0, 64)
    normals, mask = render_normals(vertices, faces, camera, adjacency=adjacency)
    world, _ = render_normals(vertices, faces, camera, adjacency=adjacency, space="world")
    assert normals.shape == (64, 64, 3) and mask.shape == (64, 64)
    assert float(mask.min()) >= 0.0 and float(mask.max()) <= 1.0
    assert 0 < float(((mask > 0) & (mask < 1)).sum()) < 0.5 * float((mask == 1).sum())   # a blended outline
    fragments = rasterize(vertices, faces, camera)
    sharp = normal_image(vertices, faces, fragments, camera)
    covered = fragments.triangle >= 0
    torch.testing.assert_close(sharp[covered].norm(dim=1), torch.ones(int(covered.sum()), dtype=torch.float64))
    assert (sharp[~covered] == 0).all() and (normals[mask == 0] == 0).all()
    assert float(normals.norm(dim=2).max()) <= 1 + 1e-12
    rotation = camera.rotation
    torch.testing.assert_close(world @ rotation.T, normals)
    assert normals[32, 32, 2] < -0.8                                   # the face looks at the camera (−z)
    with pytest.raises(StatfitError, match="space"):
        render_normals(vertices, faces, camera, space="tangent")


# --- antialiasing -----------------------------------------------------------------------------

@pytest.mark.parametrize("axis", [0, 1])
@pytest.mark.parametrize("side", ["before", "after"])
def test_antialiased_straight_edge_is_exact(axis, side):
    """A quad whose only visible edge is straight and axis-aligned at 10.3 px, the quad before or
    after it: every antialiased row (or column) of the mask sums to exactly the covered length,
    and moving the edge by δ changes the mask sum by ±32·δ (one unit per row it crosses)."""
    camera = Camera(32, 32, np.eye(3), np.eye(4))                     # pixel = (x / z, y / z)
    low, high = (-5.0, 10.3) if side == "before" else (10.3, 40.0)
    corners = np.array([[low, -5.0], [high, -5.0], [high, 40.0], [low, 40.0]])
    edge = [1, 2] if side == "before" else [0, 3]                     # the corners on the 10.3 edge
    if axis == 1:
        corners = corners[:, ::-1].copy()
    vertices = torch.tensor(np.c_[corners, np.ones(4)], requires_grad=True)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    _, mask = render_normals(vertices, faces, camera)
    length = 10.3 if side == "before" else 32 - 10.3
    torch.testing.assert_close(mask.sum(dim=1 - axis), torch.full((32,), length, dtype=torch.float64))
    mask.sum().backward()
    moved = vertices.grad[edge, axis].sum()
    torch.testing.assert_close(moved, torch.tensor(32.0 if side == "before" else -32.0, dtype=torch.float64))


def test_blend_gradients():
    crossings = EdgeCrossings(target=torch.tensor([5, 6, 5, 9]), source=torch.tensor([4, 10, 1, 8]),
                              weight=torch.tensor([0.1, 0.4, 0.3, 0.25], dtype=torch.float64, requires_grad=True))
    color = torch.rand(3, 4, 2, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda c, w: EdgeCrossings(crossings.target, crossings.source, w).blend(c),
                                    (color, crossings.weight))


def test_blending_the_covered_pixels_only_equals_blending_the_image(head_torch):
    """EdgeCrossings.blend_covered (values at the covered pixels, background 0) against blend on
    the whole image, at those pixels: values and gradients (the ICT head from the side, where the
    nose hides the cheek: outlines inside the mask and against the background); and no covered pixel."""
    vertices, faces, adjacency = head_torch
    camera = frontal((0.0, -1.0), 30.0, 48, distance=45.0)
    turned = vertices @ torch.as_tensor(trimesh.transformations.rotation_matrix(1.0, [0, 1, 0])[:3, :3]).T
    fragments = rasterize(turned, faces, camera)
    crossings = silhouette_crossings(fragments, faces, adjacency)
    covered_target = torch.isin(crossings.target, fragments.pixel)
    covered_source = torch.isin(crossings.source, fragments.pixel)
    assert (covered_target & covered_source).sum() > 10      # outlines inside the mask
    assert (covered_target & ~covered_source).sum() > 10     # ... and against the background
    values = torch.rand(len(fragments.pixel), 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    values.requires_grad_()
    image = torch.zeros(48 * 48, 3, dtype=torch.float64).index_copy(0, fragments.pixel, values)
    whole = crossings.blend(image.view(48, 48, 3)).view(-1, 3).index_select(0, fragments.pixel)
    covered = crossings.blend_covered(values, fragments.pixel)
    torch.testing.assert_close(covered, whole)
    weights = torch.randn_like(covered)
    torch.testing.assert_close(torch.autograd.grad((covered * weights).sum(), values)[0],
                               torch.autograd.grad((whole * weights).sum(), values)[0])
    empty = crossings.blend_covered(values[:0], fragments.pixel[:0])
    assert empty.shape == (0, 3)


# --- gradients against finite differences -----------------------------------------------------

def test_normal_gradients_match_finite_differences(head_torch):
    """d/dv of Σ (normal map · W) for interior vertices of a view filled by the face (float64)."""
    vertices, faces, adjacency = head_torch
    camera = frontal((0.0, -1.0), 12.0, 96, distance=45.0)
    weights = torch.randn(96, 96, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)

    def loss(v: torch.Tensor) -> torch.Tensor:
        return (render_normals(v, faces, camera, adjacency=adjacency)[0] * weights).sum()

    moving = vertices.clone().requires_grad_()
    loss(moving).backward()
    screen = camera.project(vertices)[0]
    interior = ((screen > 20) & (screen < 76)).all(dim=1)
    chosen = (moving.grad.norm(dim=1) * interior).argsort(descending=True)[:4]
    directions = torch.randn(4, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    for vertex, direction in zip(chosen.tolist(), directions / directions.norm(dim=1, keepdim=True)):
        step = torch.zeros_like(vertices)
        step[vertex] = 1e-5 * direction
        numeric = (loss(vertices + step) - loss(vertices - step)) / 2e-5
        analytic = moving.grad[vertex] @ direction
        assert abs(float(analytic - numeric)) <= 1e-3 * abs(float(numeric)), (vertex, analytic, numeric)


@pytest.mark.parametrize("vertex, axis", [(7852, 0), (7472, 0), (7847, 1)])
def test_silhouette_gradient_matches_finite_differences(head_torch, vertex, axis):
    """d/dv of the antialiased mask's sum for an outline vertex moved along a camera axis (in the
    screen plane), against central differences whose steps (¼, ½ and 1 pixel) move the outline
    across pixel centres. Plain rasterisation gives this gradient as zero. The vertices are among
    those this sum depends on most in this view (chosen once, where the differences are stable:
    a silhouette edge turning through 45° or a sliver triangle folding over makes the sum jump)."""
    vertices, faces, adjacency = head_torch
    camera = frontal((-7.3, -2.0), 3.0, 64)                           # zoom on the left cheek's outline

    def loss(v: torch.Tensor) -> torch.Tensor:
        return render_normals(v, faces, camera, adjacency=adjacency)[1].sum()

    screen, depth = camera.project(vertices)
    col, row = screen[vertex].floor().long().tolist()
    assert 16 <= col < 48 and 16 <= row < 48
    covered = rasterize(vertices, faces, camera).triangle.numpy() >= 0
    assert outline(covered)[row - 1:row + 2, col - 1:col + 2].any()   # it is on the outline
    moving = vertices.clone().requires_grad_()
    loss(moving).backward()
    direction = camera.rotation[axis]                                 # camera x or y axis in world coordinates
    analytic = float(moving.grad[vertex] @ direction)
    pixel = float(depth[vertex] / camera.K[0, 0])                      # world length of one pixel there
    numeric = []
    for fraction in (0.25, 0.5, 1.0):
        step = torch.zeros_like(vertices)
        step[vertex] = fraction * pixel * direction
        numeric.append(float(loss(vertices + step) - loss(vertices - step)) / (2 * fraction * pixel))
    numeric = float(np.mean(numeric))
    assert abs(numeric) > 10.0                                          # the outline really moves
    assert np.sign(analytic) == np.sign(numeric)
    assert abs(analytic - numeric) <= 0.05 * abs(numeric), (analytic, numeric)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu(head):
    vertices, faces = (torch.as_tensor(a) for a in head)
    camera = frontal((0.0, -2.0), 40.0, 128)
    results = []
    for device in ("cpu", "cuda"):
        moving = vertices.float().to(device).requires_grad_()
        normals, mask = render_normals(moving, faces.to(device), camera)
        (normals.sum() + mask.sum()).backward()
        results.append((normals.detach().cpu(), mask.detach().cpu(), moving.grad.cpu()))
    (n_cpu, m_cpu, g_cpu), (n_gpu, m_gpu, g_gpu) = results
    assert torch.mean((m_cpu - m_gpu).abs()) < 1e-3
    assert torch.mean((n_cpu - n_gpu).abs()) < 1e-3
    assert torch.nn.functional.cosine_similarity(g_cpu.flatten(), g_gpu.flatten(), dim=0) > 0.99
