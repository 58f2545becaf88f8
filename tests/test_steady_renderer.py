"""The fitting loop's renderer (:class:`statfit.renderer.steady.SteadyRenderer`) against the general
functions it re-lays out (``rasterize`` → ``fragment_normals`` → ``silhouette_crossings(...).blend``):
the same covered pixels, the same antialiased normals and coverage, the same gradients, in float64.
The general path is the independent expectation: it is built from other code (per-triangle
barycentric planes, its own pair enumeration and walk)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from statfit.renderer import MeshAdjacency, render_normals
from statfit.renderer.steady import SteadyRenderer
from statfit.synth.sample import camera_for_view

SIZE = 96


@pytest.fixture(scope="module", params=[(20.0, 5.0), (75.0, -20.0)], ids=["front", "side"])
def scene(embedded_model, request):
    yaw, pitch = request.param
    shape = embedded_model.sample(np.random.default_rng(11), 1.0)
    camera = camera_for_view(shape, yaw, pitch, SIZE)
    faces = torch.as_tensor(embedded_model.faces, dtype=torch.long)
    return torch.as_tensor(shape, dtype=torch.float64), faces, camera


def _steady(vertices, faces, camera):
    """Blended normals (H, W, 3) at the covered pixels (zero elsewhere), coverage (H, W), covered (H, W)."""
    renderer = SteadyRenderer(faces, camera, MeshAdjacency.from_faces(faces), torch.float64)
    view = renderer(vertices)
    real = view.pixel < renderer.pixels
    row = view.pixel[real] // renderer.stride - 1
    col = view.pixel[real] % renderer.stride - 1
    normals = vertices.new_zeros(camera.height, camera.width, 3)
    normals = normals.index_put((row, col), view.blended_normals()[:, real].T)
    coverage = view.blended_coverage(torch.float64)[:renderer.pixels]
    coverage = coverage.view(camera.height + 2, camera.width + 2)[1:-1, 1:-1]
    covered = torch.zeros(camera.height, camera.width, dtype=torch.bool)
    covered[row, col] = True
    return normals, coverage, covered


def test_the_same_pixels_normals_and_coverage(scene):
    vertices, faces, camera = scene
    normals, coverage = render_normals(vertices, faces, camera)
    steady_normals, steady_coverage, covered = _steady(vertices, faces, camera)
    assert covered.sum() > 0.1 * SIZE * SIZE
    # The general path blends the background side of an outline too; the loop's only the covered side.
    np.testing.assert_allclose(steady_normals[covered].numpy(), normals[covered].numpy(), atol=1e-10)
    np.testing.assert_allclose(steady_coverage.numpy(), coverage.numpy(), atol=1e-10)


def test_the_same_gradients(scene):
    vertices, faces, camera = scene
    generator = torch.Generator().manual_seed(0)
    weight_n = torch.randn(SIZE, SIZE, 3, generator=generator, dtype=torch.float64)
    weight_c = torch.randn(SIZE, SIZE, generator=generator, dtype=torch.float64)

    def gradients(render):
        x = vertices.clone().requires_grad_()
        normals, coverage, covered = render(x)
        ((normals * weight_n)[covered].sum() + (coverage * weight_c).sum()).backward()
        return x.grad

    covered = _steady(vertices, faces, camera)[2]
    general = gradients(lambda x: (*render_normals(x, faces, camera), covered))
    steady = gradients(lambda x: _steady(x, faces, camera))
    assert general.abs().max() > 1.0
    np.testing.assert_allclose(steady.numpy(), general.numpy(), atol=1e-8 * float(general.abs().max()))


def test_the_products_over_corners_are_the_bits_of_the_whole_product_summed():
    """The pixel normals' set-up and backward sum three products in order instead of making the
    whole broadcast product and summing it: float32 results must be the same to the bit, so fits
    on a CPU stay bit-identical (docs/benchmarks.md §12, session 21)."""
    from statfit.renderer.steady_parts import _corner_sum

    generator = torch.Generator().manual_seed(5)
    terms, w = (torch.randn(3, 3, 1001, generator=generator) for _ in range(2))
    assert torch.equal(_corner_sum(terms[:, None], w[None], 2), (w[None] * terms[:, None]).sum(dim=2))
    planes = torch.randn(3, 3, 1001, generator=generator)
    assert torch.equal(_corner_sum(planes[:, :, None], terms[:, None], dim=0),
                       (planes[:, :, None] * terms[:, None]).sum(dim=0))
    assert torch.equal(_corner_sum(planes[:, :, None], w[None]), (planes[:, :, None] * w[None]).sum(dim=1))
