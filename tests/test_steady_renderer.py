"""The fitting loop's renderer (:class:`statfit.renderer.steady.SteadyRenderer`) against the general
functions it re-lays out (``rasterize`` → ``fragment_normals`` → ``silhouette_crossings(...).blend``):
the same covered pixels, the same antialiased normals and coverage, the same gradients, in float64.
The general path is the independent expectation: it is built from other code (per-triangle
barycentric planes, its own pair enumeration and walk)."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

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


def _reused_loss(renderer, x, weights, refresh):
    """A weighted sum of the view's blended normals and coverage over the image's pixels (not the dump
    slots, which no term reads): smooth in ``x`` while the visibility is held."""
    view = renderer(x, refresh=refresh)
    weight_n, weight_c = weights
    real = view.pixel < renderer.pixels
    coverage = view.blended_coverage(torch.float64)[:renderer.pixels]
    return (view.blended_normals() * weight_n[:, :len(real)] * real).sum() + (coverage * weight_c[:len(coverage)]).sum()


def test_reused_visibility_at_the_same_vertices_is_the_refreshed_view_to_the_bit(scene):
    """Visibility is a function of the vertices: reused at the vertices it was found at, the view and its
    gradient are the refreshed call's, bit for bit."""
    vertices, faces, camera = scene
    renderer = SteadyRenderer(faces, camera, MeshAdjacency.from_faces(faces), torch.float64)
    generator = torch.Generator().manual_seed(3)
    weights = (torch.randn(3, 200_000, generator=generator, dtype=torch.float64),
               torch.randn(200_000, generator=generator, dtype=torch.float64))
    outcomes = []
    for refresh in (True, False):
        x = vertices.clone().requires_grad_()
        loss = _reused_loss(renderer, x, weights, refresh)
        loss.backward()
        outcomes.append((loss.detach(), x.grad))
    assert torch.equal(outcomes[0][0], outcomes[1][0]) and torch.equal(outcomes[0][1], outcomes[1][1])


def test_reused_visibility_keeps_the_pixels_and_moves_the_normals_with_exact_gradients(scene):
    """Moved vertices drawn with the last refresh's visibility: the same pixels and triangles as that
    refresh, normals and crossings that follow the vertices, and a gradient that finite differences
    of the reused view confirm (float64)."""
    vertices, faces, camera = scene
    renderer = SteadyRenderer(faces, camera, MeshAdjacency.from_faces(faces), torch.float64)
    fresh = renderer(vertices)
    generator = torch.Generator().manual_seed(4)
    moved = vertices + 2e-3 * torch.randn(vertices.shape, generator=generator, dtype=torch.float64)
    reused = renderer(moved, refresh=False)
    assert torch.equal(reused.pixel, fresh.pixel) and torch.equal(reused.face, fresh.face)
    assert not torch.allclose(reused.normals, fresh.normals, atol=1e-9)
    real = reused.pixel < renderer.pixels
    np.testing.assert_allclose(reused.normals[:, real].norm(dim=0).numpy(), 1.0, atol=1e-12)
    weights = (torch.randn(3, 200_000, generator=generator, dtype=torch.float64),
               torch.randn(200_000, generator=generator, dtype=torch.float64))
    x = moved.clone().requires_grad_()
    _reused_loss(renderer, x, weights, refresh=False).backward()
    direction = torch.randn(vertices.shape, generator=generator, dtype=torch.float64)
    step = 1e-8          # the crossings curve fast: at 1e-6 central differences are off by ~1e-4
    with torch.no_grad():
        ahead = _reused_loss(renderer, moved + step * direction, weights, refresh=False)
        behind = _reused_loss(renderer, moved - step * direction, weights, refresh=False)
    numeric = float((ahead - behind) / (2 * step))
    analytic = float((x.grad * direction).sum())
    assert abs(analytic) > 1.0
    assert abs(numeric - analytic) < 1e-5 * abs(analytic)


def test_the_objective_refreshes_every_k_calls_and_after_a_reset(scene):
    from statfit.objectives.normals import NormalMapObjective
    from statfit.renderer import render_normals

    vertices, faces, camera = scene
    normals, coverage = render_normals(vertices, faces, camera)
    objective = NormalMapObjective(normals.detach(), coverage.detach() > 0.5, camera, faces, visibility_every=3)
    assert not objective.capturable and NormalMapObjective(normals, coverage > 0.5, camera, faces).capturable
    refreshes = []
    objective(vertices)
    original = objective._renderer._visibility
    objective._renderer._visibility = lambda *args: refreshes.append(len(calls)) or original(*args)
    calls = []
    for _ in range(7):
        calls.append(objective(vertices))
    objective.reset()
    calls.append(objective(vertices))
    assert refreshes == [2, 5, 7]          # calls 3 and 6 since the first, then the first after the reset
    assert all(torch.equal(each["normal"], calls[0]["normal"]) for each in calls)


@pytest.mark.parametrize("every", [0, -4, 2.0, True, None])
def test_a_refresh_count_that_is_not_a_whole_number_of_calls_is_refused(scene, every):
    from statfit.errors import StatfitError
    from statfit.objectives.normals import NormalMapObjective

    vertices, faces, camera = scene
    normals, mask = torch.zeros(camera.height, camera.width, 3), torch.ones(camera.height, camera.width, dtype=torch.bool)
    with pytest.raises(StatfitError, match="visibility_every must be a whole number"):
        NormalMapObjective(normals, mask, camera, faces, visibility_every=every)


def test_the_gpu_lookups_give_the_cpu_view_and_gradient_to_the_bit(scene):
    """``lookups`` (a GPU's: slots looked up by ``searchsorted`` instead of scattered) on a CPU: the
    same pixels, triangles, blends, loss and gradient as the scatters, bit for bit."""
    vertices, faces, camera = scene
    generator = torch.Generator().manual_seed(5)
    weights = (torch.randn(3, 200_000, generator=generator, dtype=torch.float64),
               torch.randn(200_000, generator=generator, dtype=torch.float64))
    outcomes = []
    for lookups in (False, True):
        renderer = SteadyRenderer(faces, camera, MeshAdjacency.from_faces(faces), torch.float64)
        renderer.lookups = lookups
        x = vertices.clone().requires_grad_()
        view = renderer(x)
        loss = _reused_loss(renderer, x, weights, refresh=False)
        loss.backward()
        outcomes.append((view.pixel, view.face, view.target, view.source, view.weight.detach(), loss.detach(), x.grad))
    assert all(torch.equal(a, b) for a, b in zip(*outcomes))


class _Scatters(TorchDispatchMode):
    """The most writes any one index takes in each accumulating scatter (index_add, scatter_add,
    scatter_reduce, index_put with accumulate), by op."""

    def __init__(self):
        super().__init__()
        self.most: list[tuple[str, int]] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = func.__name__.split(".")[0]
        index = None
        if name in ("index_add", "index_add_", "scatter_add", "scatter_add_", "scatter_reduce", "scatter_reduce_"):
            index = args[2]
        elif name in ("index_put", "index_put_", "_index_put_impl_") and (args[3] if len(args) > 3 else False):
            index = next(i for i in args[1] if i is not None)
        if index is not None and index.numel():
            self.most.append((name, int(torch.unique(index.reshape(-1), return_counts=True)[1].max())))
        return func(*args, **(kwargs or {}))


def test_no_index_takes_the_masked_lanes_writes(embedded_model):
    """CUDA's deterministic scatters add each index's writes one after another, so one index that
    every masked lane writes costs milliseconds a call on a card (the H100 profile, 2026-11-27). A
    render iteration's scatters (the objective and its backward, GPU lookups, 256²) take at most a
    few dozen writes at one index (17, 2026-11-27); with one dump slot they took thousands (6,747)."""
    shape = embedded_model.sample(np.random.default_rng(11), 1.0)
    camera = camera_for_view(shape, 20.0, 5.0, 256)
    faces = torch.as_tensor(embedded_model.faces, dtype=torch.long)
    renderer = SteadyRenderer(faces, camera, MeshAdjacency.from_faces(faces), torch.float32)
    renderer.lookups = True
    vertices = torch.as_tensor(shape, dtype=torch.float32)
    generator = torch.Generator().manual_seed(6)
    weights = (torch.randn(3, 200_000, generator=generator), torch.randn(200_000, generator=generator))
    renderer(vertices)                                       # the buffers sized (host reads)
    spy = _Scatters()
    x = vertices.clone().requires_grad_()
    with spy:
        view = renderer(x)
        real = view.pixel < renderer.pixels
        coverage = view.blended_coverage(torch.float32)[:renderer.pixels]
        loss = (view.blended_normals() * weights[0][:, :len(real)] * real).sum() + (coverage * weights[1][:len(coverage)]).sum()
        loss.backward()
    covered = int(real.sum())
    assert len(spy.most) >= 6
    assert max(most for _, most in spy.most) < covered / 100, (covered, spy.most)


@pytest.mark.parametrize("lookups", [False, True], ids=["scatters", "lookups"])
def test_a_view_that_outgrows_its_buffers_draws_what_fits(scene, monkeypatch, lookups):
    """Buffers sized without margin, then the mesh turned a quarter about its z axis (more
    silhouette, at 96² more pixels near it than the buffer holds): the call drops what does not fit
    (until the next check resizes), indexing only inside its buffers; every pixel it keeps is one a
    fresh renderer covers (dropped candidates only uncover pixels, or leave a farther triangle)."""
    from statfit.renderer import steady_buffers
    monkeypatch.setattr(steady_buffers, "MARGIN", 1.0)
    monkeypatch.setattr(steady_buffers, "FLOOR", 0)
    vertices, faces, camera = scene
    adjacency = MeshAdjacency.from_faces(faces)
    renderer = SteadyRenderer(faces, camera, adjacency, torch.float64)
    renderer.lookups = lookups
    renderer(vertices)
    centre = vertices.mean(dim=0)
    quarter = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    turned = centre + (vertices - centre) @ quarter.T
    view = renderer(turned)
    sizes = torch.tensor([renderer._sizes[name] for name in steady_buffers.BUFFERS])
    assert renderer._need[steady_buffers.BUFFERS.index("edges")] > sizes[steady_buffers.BUFFERS.index("edges")]
    fresh = SteadyRenderer(faces, camera, adjacency, torch.float64)(turned)
    kept = view.pixel < renderer.pixels
    assert kept.sum() > 0 and torch.isin(view.pixel[kept], fresh.pixel[fresh.pixel < renderer.pixels]).all()


def test_a_reused_visibility_is_refreshed_once_a_vertex_has_moved_too_far(scene):
    """``moved``: a call that would reuse the visibility keeps it while no vertex has moved that many
    pixels since the last refresh, and refreshes it (a fresh renderer's pixels) once one has."""
    vertices, faces, camera = scene
    adjacency = MeshAdjacency.from_faces(faces)
    renderer = SteadyRenderer(faces, camera, adjacency, torch.float64)
    renderer(vertices)
    found = renderer._visible
    generator = torch.Generator().manual_seed(8)
    moved = vertices + 1e-3 * torch.randn(vertices.shape, generator=generator, dtype=torch.float64)
    pixels = float((renderer._project(moved)[2] - found.screen).abs().amax())
    assert pixels > 0.01
    kept = renderer(moved, refresh=False, moved=2 * pixels)
    assert renderer._visible is found and torch.equal(kept.pixel, found.pixel)
    refreshed = renderer(moved, refresh=False, moved=pixels / 2)
    fresh = SteadyRenderer(faces, camera, adjacency, torch.float64)(moved)
    assert renderer._visible is not found
    mine, theirs = refreshed.pixel < renderer.pixels, fresh.pixel < renderer.pixels        # buffers sized apart
    assert torch.equal(refreshed.pixel[mine], fresh.pixel[theirs]) and torch.equal(refreshed.face[mine], fresh.face[theirs])


@pytest.mark.parametrize("moved", [0.0, -1.0, float("nan")])
def test_a_movement_limit_that_is_not_above_zero_pixels_is_refused(scene, moved):
    from statfit.errors import StatfitError
    from statfit.objectives.normals import NormalMapObjective

    vertices, faces, camera = scene
    normals, mask = torch.zeros(camera.height, camera.width, 3), torch.ones(camera.height, camera.width, dtype=torch.bool)
    with pytest.raises(StatfitError, match="visibility_moved must be a number of pixels above 0"):
        NormalMapObjective(normals, mask, camera, faces, visibility_every=4, visibility_moved=moved)
