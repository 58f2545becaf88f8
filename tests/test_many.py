"""Many registrations in one program (issue 38, part 3): each piece that takes B fits at once
against the same piece run on each fit alone, and ``register_many`` against ``register``."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from statfit.core.filters import HybridFilter, LaplacianFilter, StatisticalFilter
from statfit.core.methods import batchable, resolve
from statfit.core.optim import UniformAdam
from statfit.core.settings import FitSpace
from statfit.geometry.closest import ClosestPointQuery
from statfit.objectives.landmarks import LandmarkObjective, WithLandmarks
from statfit.objectives.scan import ScanObjective, masked_median, masked_quantile
from statfit.objectives.scans import ScanBatch
from statfit.registration.job import register
from statfit.registration.many import register_many
from statfit.structures.frame import Frame
from statfit.synth.sample import sample_target, scan_from_view
from test_op_counts import WAITING, Counter

FITS = 3


@pytest.fixture(scope="module")
def space(embedded_model):
    return FitSpace.of(embedded_model, dtype=torch.float64)


@pytest.fixture(scope="module")
def shapes(embedded_model, space):
    """FITS shapes of the model (B, N, 3, fit frame, float64) and a scan (M_b, 3) of each."""
    rng = np.random.default_rng(5)
    targets = [sample_target(embedded_model, rng) for _ in range(FITS)]
    scans = [scan_from_view(t, embedded_model.faces, rng, 900 + 150 * b, 25.0 * b) for b, t in enumerate(targets)]
    return targets, scans


def test_filters_take_many_fits_at_once(embedded_model, space):
    g = torch.randn(FITS, embedded_model.num_vertices, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    laplacian = LaplacianFilter(embedded_model.template, embedded_model.faces, 19.0, dtype=torch.float64)
    for filt in (StatisticalFilter(space.basis_t, 30.0), HybridFilter(space.basis_t, 3.0, laplacian), laplacian):
        together = filt(g)
        assert together.shape == g.shape
        alone = torch.stack([filt(each) for each in g])
        torch.testing.assert_close(together, alone, rtol=1e-12, atol=1e-12)


def test_uniform_adam_steps_each_fit_as_alone():
    rng = torch.Generator().manual_seed(1)
    start = torch.randn(FITS, 50, 3, dtype=torch.float64, generator=rng)
    scales = torch.tensor([1.0, 100.0, 0.01], dtype=torch.float64)[:, None, None]   # very different gradients
    together = start.clone().requires_grad_(True)
    alone = [each.clone().requires_grad_(True) for each in start]
    opt_together = UniformAdam([together], lr=0.1, fits=True)
    opt_alone = [UniformAdam([p], lr=0.1) for p in alone]
    for _ in range(5):
        (scales * together.square()).sum().backward()
        opt_together.step()
        opt_together.zero_grad()
        for p, opt, scale in zip(alone, opt_alone, scales):
            (scale * p.square()).sum().backward()
            opt.step()
            opt.zero_grad()
    torch.testing.assert_close(together.detach(), torch.stack(alone).detach(), rtol=0, atol=1e-15)


def test_masked_quantile_and_median_per_row_are_torch_s():
    rng = np.random.default_rng(2)
    values = torch.as_tensor(rng.random((4, 37)))
    mask = torch.as_tensor(rng.random((4, 37)) < 0.6)
    quantiles, medians = masked_quantile(values, mask, 0.95), masked_median(values, mask)
    assert quantiles.shape == medians.shape == (4, 1)
    for row in range(4):
        kept = values[row][mask[row]]
        assert quantiles[row, 0] == torch.quantile(kept, 0.95)
        assert medians[row, 0] == kept.median()


def test_closest_points_of_many_meshes_are_each_mesh_s(embedded_model, space, shapes):
    targets, scans = shapes
    query = ClosestPointQuery(embedded_model.faces, embedded_model.num_vertices, k=2)
    vertices = torch.stack([space.mean + 0.01 * b for b in range(FITS)])
    count = min(len(s) for s in scans)
    frame = Frame.of(embedded_model.template)
    points = torch.as_tensor(np.stack([frame.to_unit(s[:count]) for s in scans]))
    together = query.many(vertices, points, points.numpy())
    faces = len(embedded_model.faces)
    for b in range(FITS):
        alone = query(vertices[b], points[b])
        rows = slice(b * count, (b + 1) * count)
        assert torch.equal(together.triangle[rows] - b * faces, alone.triangle)
        assert torch.equal(together.barycentric[rows], alone.barycentric)
        assert torch.equal(together.distance[rows], alone.distance)


def objectives(embedded_model, space, scans, clutter: bool):
    """One ScanObjective (with every rule on) and landmark term per scan, fit frame, float64."""
    query = ClosestPointQuery(embedded_model.faces, embedded_model.num_vertices, k=2)
    frame = Frame.of(embedded_model.template)
    region = torch.zeros(len(embedded_model.faces), dtype=torch.bool)
    region[: len(region) // 2] = True
    scan_terms, landmark_terms = [], []
    rng = np.random.default_rng(4)
    for b, points in enumerate(scans):
        unit = torch.as_tensor(frame.to_unit(points))
        normals = torch.nn.functional.normalize(torch.as_tensor(rng.normal(size=points.shape)), dim=1)
        scan_terms.append(ScanObjective(unit, query, trim=0.05, normals=normals, clutter=clutter and b != 1,
                                        region_faces=region if b == 2 else None))
        landmark_terms.append(None if b == 1 else LandmarkObjective(
            torch.tensor([3, 50, 700]), space.mean[[3, 50, 700]] + 0.02, 10.0 + b))
    return scan_terms, landmark_terms


@pytest.mark.parametrize("clutter", [False, True])
def test_one_data_term_for_many_scans_is_the_sum_of_theirs(embedded_model, space, shapes, clutter):
    targets, scans = shapes
    scan_terms, landmark_terms = objectives(embedded_model, space, scans, clutter)
    batch = ScanBatch(scan_terms, landmark_terms)
    vertices = torch.stack([space.mean + 0.01 * torch.as_tensor(np.random.default_rng(b).normal(size=space.mean.shape))
                            for b in range(FITS)]).requires_grad_(True)
    batch.prepare(vertices.detach(), 0)
    total = sum(batch(vertices).values())
    total.backward()
    expected_grad, expected = [], 0.0
    for b, (scan, landmarks) in enumerate(zip(scan_terms, landmark_terms)):
        term = scan if landmarks is None else WithLandmarks(scan, landmarks)
        x = vertices.detach()[b].clone().requires_grad_(True)
        term.prepare(x.detach(), 0)
        value = sum(term(x).values())
        value.backward()
        expected = expected + value.detach()
        expected_grad.append(x.grad)
        assert int(batch.kept()[b]) == scan.kept
    torch.testing.assert_close(total.detach(), expected, rtol=1e-12, atol=0)
    torch.testing.assert_close(vertices.grad, torch.stack(expected_grad), rtol=1e-12, atol=1e-15)
    per_fit = batch.per_fit(vertices.detach())
    assert sum(each["total"] for each in per_fit) == pytest.approx(float(expected), rel=1e-12)
    assert "landmarks" not in per_fit[1] and "landmarks" in per_fit[0]


def test_batchable_stages():
    default = resolve("default")
    assert [batchable(s) for s in default] == [False, True]      # Gauss–Newton, then hybrid
    assert batchable(resolve("laplacian")[-1]) and not batchable(resolve("pca", preset="paper")[0])


def test_a_stage_stepped_together_is_each_fit_alone(embedded_model, shapes):
    """A gradient stage from iteration 0 (no closed-form stage before it), two of three fits with
    landmarks: the same fit as alone, to float rounding (float64)."""
    targets, scans = shapes
    options = dict(method="hybrid", align="none", iterations=60, dtype=torch.float64, threads=1)
    marks = [targets[0][embedded_model.landmarks], None, targets[2][embedded_model.landmarks] + 0.002]
    together = register_many(embedded_model, scans, landmarks=marks, **options)
    for b, scan in enumerate(scans):
        alone = register(embedded_model, scan, landmarks=marks[b], **options)
        assert together[b].error is None
        np.testing.assert_allclose(together[b].fit.vertices, alone.vertices, rtol=0, atol=1e-9)
        assert together[b].fit.iterations == alone.iterations


def test_the_default_together_fits_as_well_as_alone(embedded_model, shapes):
    """The default pipeline: each fit's own pose and closed-form stage, then the hybrid stage of
    all together (correspondences renewed at other iterations than alone: not the same bits)."""
    targets, scans = shapes
    together = register_many(embedded_model, scans, threads=1)
    for b, scan in enumerate(scans):
        alone = register(embedded_model, scan, threads=1)
        error_alone = np.linalg.norm(alone.vertices - targets[b], axis=1).mean()
        error_together = np.linalg.norm(together[b].fit.vertices - targets[b], axis=1).mean()
        assert error_together <= 1.25 * error_alone + 1e-3 * np.ptp(targets[b], axis=0).max(), (b, error_together,
                                                                                                 error_alone)
        report, expected = together[b].fit.fallback, alone.fallback
        assert report["used"] == expected["used"]
        assert report["residual"] == pytest.approx(expected["residual"], abs=1e-3)      # radii; the test is at 0.02
        assert report["code"] == pytest.approx(expected["code"], rel=0.1)
        assert together[b].fit.pose["score"] == alone.pose["score"]


def test_a_failing_scan_fails_alone(embedded_model, shapes):
    targets, scans = shapes
    bad = np.full((50, 3), np.nan)
    out = register_many(embedded_model, [scans[0], bad, scans[1]], threads=1)
    assert out[1].fit is None and "NaN" in out[1].error
    assert out[0].error is None and out[2].error is None
    assert np.isfinite(out[0].fit.vertices).all()


def test_an_iteration_launches_one_fit_s_ops_for_many(embedded_model, shapes):
    """Ops per iteration of paper statistical (as test_op_counts counts them) for 1 and 6 fits
    together: the same, about one fit's (≤ 65), and no host wait."""
    targets, scans = shapes

    def per_iteration(fits: int) -> tuple[float, float]:
        counts = []
        for iterations in (20, 60):
            counter = Counter()
            with counter:
                register_many(embedded_model, [scans[0]] * fits, "statistical", preset="paper", align="none",
                              iterations=iterations)
            counts.append((sum(counter.ops.values()),
                           sum(n for name, n in counter.ops.items() if any(w in name for w in WAITING))))
        return tuple((b - a) / 40 for a, b in zip(*counts))

    one, six = per_iteration(1), per_iteration(6)
    assert six[0] <= 65 and six[0] <= one[0] + 6, (one, six)
    assert six[1] == 0


def test_a_solve_of_more_columns_than_cholespy_takes_on_cuda_runs_in_blocks(embedded_model):
    """cholespy's CUDA solve takes at most 128 right-hand sides (64 fits: 192 columns); the solver
    then solves in blocks. Forced on the CPU with blocks of 2: the same bits as one call."""
    from statfit.core.laplacian import smoothing_matrix
    from statfit.core.solvers import CholespySolver

    solver = CholespySolver(smoothing_matrix(embedded_model.template, embedded_model.faces, 19.0), torch.float32,
                            torch.device("cpu"))
    rhs = torch.randn(embedded_model.num_vertices, 7, generator=torch.Generator().manual_seed(0))
    whole = solver.solve(rhs)
    solver.max_columns = 2
    assert torch.equal(solver.solve(rhs), whole)


def test_scans_posed_side_by_side_fit_as_posed_one_after_another(embedded_model, monkeypatch):
    """The default on three scans in any pose and unit (one of a person far outside the model, whose
    pose search warns; one of NaNs): each fit's pose search, closed-form stage and fallback test on
    threads side by side (``threads`` unset: the cores allow two) and one after another
    (``threads=1``), the same poses and fits, and each fit keeps its own warnings and failure."""
    from statfit.core import together
    from statfit.core.threads import usable_cores
    from statfit.structures.scan import Scan
    from statfit.synth.scanner import realistic_scan

    scans = []
    for seed, spread in ((2, 3.0), (4, 1.0)):
        rng = np.random.default_rng(seed)
        shape = embedded_model.shape(spread * rng.standard_normal(embedded_model.num_modes))
        made = realistic_scan(shape, embedded_model.faces, rng, clutter=0.5, units=("mm", "cm")[seed % 3 == 1])
        scans.append(Scan.from_mesh(made.vertices, made.faces))
    scans.insert(1, np.full((50, 3), np.nan))
    side_by_side = []
    threads_of = together.map_in_threads
    monkeypatch.setattr(together, "map_in_threads", lambda work, items, threads: side_by_side.append(threads)
                        or threads_of(work, items, threads))
    apart = register_many(embedded_model, scans)
    if usable_cores() >= 2:
        assert len(side_by_side) >= 3 and min(side_by_side) >= 2     # poses, closed forms, fallback tests
    side_by_side.clear()
    after = register_many(embedded_model, scans, threads=1)
    assert not side_by_side
    assert apart[1].fit is None and "NaN" in apart[1].error and apart[1].error == after[1].error
    for b in (0, 2):
        assert apart[b].error is None and after[b].error is None
        assert apart[b].fit.pose == after[b].fit.pose
        np.testing.assert_array_equal(apart[b].fit.vertices, after[b].fit.vertices)
        assert apart[b].warnings == after[b].warnings
    assert any("far outside the model's people" in w for w in apart[0].warnings)
    assert not any("far outside the model's people" in w for w in apart[2].warnings)
