"""The closed-form pca stage: its Jacobian, its fixed point, and what it recovers."""
from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from statfit.geometry.closest import ClosestPointQuery
from statfit.structures.frame import Frame
from statfit.core.gauss_newton import fit_coefficients
from statfit.core.methods import resolve
from statfit.objectives.scan import ScanObjective
from statfit.registration.job import register
from statfit.core.settings import FitSpace
from statfit.synth.sample import scan_from_view


def _scan_objective(model, points: np.ndarray, frame: Frame) -> ScanObjective:
    scan = torch.as_tensor(frame.to_unit(points), dtype=torch.float64)
    return ScanObjective(scan, ClosestPointQuery(model.faces, model.num_vertices), trim=0.0)


def test_jacobian_matches_finite_differences_of_the_residuals(embedded_model, rng):
    """∂r/∂c from ``jacobian`` equals central differences of ``residuals`` along each direction."""
    frame = Frame.of(embedded_model.template)
    space = FitSpace.of(embedded_model, frame, torch.device("cpu"), torch.float64)
    mesh = trimesh.Trimesh(embedded_model.shape(rng.standard_normal(embedded_model.num_modes)), embedded_model.faces,
                           process=False)
    objective = _scan_objective(embedded_model, mesh.sample(400, seed=3), frame)
    objective.refresh(space.mean)
    directions = (space.basis_t * space.std[:, None]).T.reshape(*space.mean.shape, -1).contiguous()
    jac = objective.jacobian(directions)
    h = 1e-6
    for k in range(0, directions.shape[-1], 7):
        step = h * directions[..., k]
        numeric = (objective.residuals(space.mean + step) - objective.residuals(space.mean - step)) / (2 * h)
        torch.testing.assert_close(jac[:, k], numeric, rtol=1e-6, atol=1e-9)


def test_recovers_an_in_span_shape_from_a_partial_scan(embedded_model, rng):
    """A shape inside the model seen from one side: the noise-free fit finds its coefficients."""
    coeffs = rng.standard_normal(embedded_model.num_modes)
    target = embedded_model.shape(coeffs)
    points = scan_from_view(target, embedded_model.faces, rng, 3000, 30.0)
    frame = Frame.of(embedded_model.template)
    space = FitSpace.of(embedded_model, frame, torch.device("cpu"), torch.float64)
    objective = _scan_objective(embedded_model, points, frame)
    fit = fit_coefficients(space.mean, space.basis_t, space.std, objective, space.mean, 100, noise=0.0, levels=1,
                           tolerance=1e-9)
    error = np.linalg.norm(frame.from_unit(fit.vertices.numpy()) - target, axis=1).mean() / frame.scale
    assert error < 1e-4
    assert fit.iterations < 100
    np.testing.assert_allclose(fit.coefficients.numpy(), coeffs, atol=2e-2)


def test_prior_shrinks_towards_the_mean(embedded_model, rng):
    """A larger noise σ weighs the prior more: the coefficients' norm falls monotonically."""
    target = embedded_model.shape(2 * rng.standard_normal(embedded_model.num_modes))
    points = scan_from_view(target, embedded_model.faces, rng, 2000, -20.0)
    frame = Frame.of(embedded_model.template)
    space = FitSpace.of(embedded_model, frame, torch.device("cpu"), torch.float64)
    norms = []
    for noise in (0.0, 0.05, 0.5):
        fit = fit_coefficients(space.mean, space.basis_t, space.std, _scan_objective(embedded_model, points, frame),
                               space.mean, 50, noise, levels=1)
        norms.append(float(fit.coefficients.norm()))
    assert norms[0] > norms[1] > norms[2]


def test_continuation_relaxes_the_prior_to_the_final_noise(embedded_model, rng):
    """The path ends where a fit at the final σ that starts at the path's end would stay. Within
    1e-2 of coefficients up to 3.5: the two stop at their tolerance 0.0002–0.0022 apart with the
    thread count and the library versions (numpy 2.4 one thread, numpy 1.26 two threads; session
    33), where a final σ 25% off ends 0.20 away."""
    target = embedded_model.shape(1.5 * rng.standard_normal(embedded_model.num_modes))
    points = scan_from_view(target, embedded_model.faces, rng, 2000, 10.0)
    frame = Frame.of(embedded_model.template)
    space = FitSpace.of(embedded_model, frame, torch.device("cpu"), torch.float64)
    path = fit_coefficients(space.mean, space.basis_t, space.std, _scan_objective(embedded_model, points, frame),
                            space.mean, 200, 0.01, levels=5, tolerance=1e-8)
    again = fit_coefficients(space.mean, space.basis_t, space.std, _scan_objective(embedded_model, points, frame),
                             path.vertices, 200, 0.01, levels=1, tolerance=1e-8)
    np.testing.assert_allclose(path.coefficients.numpy(), again.coefficients.numpy(), atol=1e-2)


def test_pca_method_is_the_closed_form_stage_and_beats_adam_at_equal_time(embedded_model, rng):
    """register's pca: Gauss–Newton, stops by itself, and fits closer than 200 Adam steps from the
    same start (the mean: ``align="none"``, the scan lies in the model's frame; with the pose search
    Adam would start from its fitted shape, the closed form from the mean)."""
    (stage,) = resolve("pca")
    assert stage.optimizer == "gauss-newton"
    target = embedded_model.sample(rng)
    points = scan_from_view(target, embedded_model.faces, rng, 2000, 20.0)
    closed = register(embedded_model, points, "pca", align="none")
    adam = register(embedded_model, points, "pca", align="none", stages=(stage.__class__("pca", 200, 0.05),))
    assert closed.iterations < stage.iterations
    error = lambda fit: np.linalg.norm(fit.vertices - target, axis=1).mean()  # noqa: E731
    assert error(closed) < 0.5 * error(adam)


def test_gauss_newton_needs_a_least_squares_objective(embedded_model):
    from statfit.errors import StatfitError
    from statfit.core.stages import run_stages

    class Plain:
        def reset(self):
            pass

    space = FitSpace.of(embedded_model, Frame.of(embedded_model.template), torch.device("cpu"), torch.float32)
    with pytest.raises(StatfitError, match="least-squares"):
        run_stages(resolve("pca"), space, Plain(), space.mean)


def test_held_out_error_is_the_step_refitted_without_the_held_rows(rng):
    """The held rows' mean squared residual after the regularised step that never saw them, against
    a least-squares solve of the stacked system [J/√n; √ρ I] δ = −[r/√n; √ρ c] over the other rows."""
    from statfit.core.gauss_newton import held_out_error

    jac, r, coeffs = rng.standard_normal((60, 5)), rng.standard_normal(60), rng.standard_normal(5)
    held, prior = rng.random(60) < 0.25, 0.3
    kept = ~held
    stacked = np.vstack([jac[kept] / np.sqrt(kept.sum()), np.sqrt(prior) * np.eye(5)])
    step = np.linalg.lstsq(stacked, -np.concatenate([r[kept] / np.sqrt(kept.sum()), np.sqrt(prior) * coeffs]),
                           rcond=None)[0]
    expected = np.mean((r[held] + jac[held] @ step) ** 2)
    as_tensor = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731
    got = held_out_error(as_tensor(jac), as_tensor(r), as_tensor(coeffs), prior, torch.as_tensor(held))
    assert got == pytest.approx(expected, rel=1e-9)


def test_held_out_error_is_infinite_where_it_cannot_be_scored(rng):
    """No row held, every row held, or no prior and fewer rows than modes: a level that cannot be
    scored is never chosen."""
    from statfit.core.gauss_newton import held_out_error

    jac, r, coeffs = (torch.as_tensor(a) for a in (rng.standard_normal((8, 5)), rng.standard_normal(8),
                                                    rng.standard_normal(5)))
    for held in (torch.zeros(8, dtype=torch.bool), torch.ones(8, dtype=torch.bool)):
        assert held_out_error(jac, r, coeffs, 0.1, held) == float("inf")
    one_kept = torch.arange(8) > 0
    assert held_out_error(torch.zeros(8, 5, dtype=torch.float64), r, coeffs, 0.0, one_kept) == float("inf")


def test_the_edge_is_the_quarter_of_the_points_towards_the_start():
    from statfit.core.gauss_newton import edge_rows

    points = torch.stack([torch.arange(100.0), torch.zeros(100), torch.zeros(100)], dim=1)
    start = torch.tensor([[-500.0, 3.0, 0.0], [-400.0, -3.0, 0.0]])       # centroid far along −x
    assert torch.equal(edge_rows(points, start), torch.arange(100) < 25)


@pytest.mark.parametrize("scan_noise, kept", [(0.0, 1), (0.03, 0)], ids=["clean-scan", "noisy-scan"])
def test_choosing_levels_keeps_the_level_whose_edge_is_predicted_best(embedded_model, scan_noise, kept):
    """With ``choose_levels`` 2 the fit is the continuation stopped at its last level or the one
    before, whichever predicts the scan's edge better, each made on its own and scored afresh: the
    last (the weakest prior) for a clean scan of a person of the model, the one before for a scan
    with noise of 3% of the model's radius, which the weaker prior fits. Its answer is its own
    record, so a fit that ignored the choice would keep the last level on both."""
    from statfit.core.gauss_newton import edge_rows, held_out_error, mode_directions

    rng = np.random.default_rng(1234)
    target = embedded_model.shape(2.5 * rng.standard_normal(embedded_model.num_modes))
    frame = Frame.of(embedded_model.template)
    points = scan_from_view(target, embedded_model.faces, rng, 1500, 40.0)
    points = points + rng.normal(scale=scan_noise * frame.scale, size=points.shape)
    space = FitSpace.of(embedded_model, frame, torch.device("cpu"), torch.float64)
    directions = mode_directions(space.basis_t, space.std)

    def fit(noise: float, levels: int, choose: int = 0):
        objective = _scan_objective(embedded_model, points, frame)
        result = fit_coefficients(space.mean, space.basis_t, space.std, objective, space.mean, 200, noise, levels,
                                  choose, tolerance=1e-9)
        objective.refresh(result.vertices)
        r = objective.residuals(result.vertices).double()
        held = edge_rows(objective.residual_points(), space.mean)
        return result, held_out_error(objective.jacobian(directions), r, result.coefficients, noise**2 / len(r), held)

    ends = [fit(0.003 * np.sqrt(10.0), 4), fit(0.003, 5)]
    chosen, _ = fit(0.003, 5, choose=2)
    assert min(range(2), key=lambda i: ends[i][1]) == kept
    # The path to level 4 is the same maths on its own, though σ's rounding can move a closest-point
    # attachment on the noisy scan and part the paths a little: near the end chosen, far from the other.
    apart = float((ends[0][0].coefficients - ends[1][0].coefficients).norm())
    assert float((chosen.coefficients - ends[kept][0].coefficients).norm()) < 0.1 * apart


def test_choose_levels_is_checked():
    from statfit.core.settings import Settings
    from statfit.errors import StatfitError

    with pytest.raises(StatfitError, match="choose_levels must be a whole number from 0 to 5"):
        Settings("pca", 10, 0.0, optimizer="gauss-newton", choose_levels=6)
    with pytest.raises(StatfitError, match="Gauss–Newton"):
        Settings("pca", 10, 0.1, choose_levels=1)
