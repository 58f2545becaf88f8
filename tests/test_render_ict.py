"""End to end on the real ICT head model: one normal map (yaw 20°) of an identity sample plus the
jawOpen expression (outside the identity model); every fit is scored against the ground truth over
all vertices. The test renders 128² to keep the suite short (the fits take a third of the 256²
time), where the fits measured (session 9, the rigid alignment fitting the coefficients at its own
step): tuned pca 0.0452, the default 0.0421, the template 0.1448; the tuned hybrid 0.0416
(docs/studies.md §13: on this case the default loses to it, and has the lowest mean over §11's four
faces).

The paper's two filters are not fitted here any more (session 39; 80 s a fit, a third of the file).
From the alignment's converged start (0.0465) both only drift away at 3,000 iterations (error at
iteration 250, 1,000 and 3,000: paper `statistical` 0.0458, 0.0476, 0.0505; paper `laplacian`
0.0452, 0.0458, 0.0472; docs/studies.md §13), so "both fit the jaw the model lacks" held by the
alignment alone and could not fail through the filters; the default's lead over them is wider than
over tuned pca, which stays.

The two fits run side by side, one thread each.
"""
from __future__ import annotations

import numpy as np
import pytest

from cases import NORMAL_CASES
from conftest import ICT_DIR, run_two_at_a_time

pytestmark = pytest.mark.slow

SIZE = 128
RUNS = {"tuned pca": ("pca", "tuned"), "default": ("default", "tuned")}


def fit_error(method: str, preset: str) -> float:
    """Relative mean vertex error of one fit of the jaw-open case (runs in a worker process)."""
    import torch

    from statfit.structures.normal_map import NormalMap
    from statfit.render.job import reconstruct
    from statfit.model.statmodel import load_model
    from statfit.synth.sample import camera_for_view, load_delta, sample_target
    from statfit.renderer.images import render_target

    torch.set_num_threads(1)
    model = load_model(ICT_DIR / "ict_face_identity.npz")
    seed, expression, weight, yaw, pitch = NORMAL_CASES["jaw-open"]
    truth = sample_target(model, np.random.default_rng(seed), 1.0,
                          load_delta(str(ICT_DIR / "ict_face_expressions.npz"), expression), weight)
    if method == "template":
        return _relative_error(model.template, truth)
    camera = camera_for_view(truth, yaw, pitch, SIZE)
    normal_map = NormalMap(*render_target(truth, model.faces, camera))
    return _relative_error(reconstruct(model, normal_map, camera, method, preset=preset).vertices, truth)


def _relative_error(vertices: np.ndarray, truth: np.ndarray) -> float:
    scale = np.sqrt(((truth - truth.mean(axis=0)) ** 2).sum(axis=1).mean())
    return float(np.linalg.norm(vertices - truth, axis=1).mean() / scale)


@pytest.fixture(scope="module")
def errors(ict_model):
    return run_two_at_a_time(fit_error, RUNS) | {"template": fit_error("template", "")}


def test_the_default_fits_closer_than_tuned_pca_and_far_closer_than_the_template(errors):
    assert errors["default"] < errors["tuned pca"], errors
    assert errors["default"] < 0.35 * errors["template"], errors
