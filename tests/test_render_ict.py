"""End to end on the real ICT head model: one normal map (yaw 20°) of an identity sample plus the
jawOpen expression (outside the identity model); every fit is scored against the ground truth over
all vertices. The test renders 128² to keep the suite short (the fits take a third of the 256²
time), where the four fits measured (session 9, the rigid alignment fitting the coefficients at its
own step): paper statistical 0.0502, paper laplacian 0.0470, tuned pca 0.0452, the default 0.0421,
the template 0.1448.

From that converged start the paper's Laplacian filter is the closer of the paper's two here (at
the pose's step, until session 9: statistical 0.0548, laplacian 0.0619), and closer on average over
the rendering study's four faces at 256² (0.0183 against 0.0194; docs/studies.md §13): the paper's
comparison is no longer asserted, only that both fit what the model lacks.

The four 3000-iteration fits run two at a time, one thread each: at 256² a fit gains little from a
second thread, so this halves the wall time on a 2-core machine.
"""
from __future__ import annotations

import numpy as np
import pytest

from cases import NORMAL_CASES
from conftest import ICT_DIR, run_two_at_a_time

pytestmark = pytest.mark.slow

SIZE = 128
RUNS = {"paper statistical": ("statistical", "paper"), "paper laplacian": ("laplacian", "paper"),
        "tuned pca": ("pca", "tuned"), "default": ("default", "tuned")}


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


def test_the_papers_filters_both_fit_the_jaw_the_model_lacks(errors):
    assert errors["paper statistical"] < 0.5 * errors["template"], errors
    assert errors["paper laplacian"] < 0.5 * errors["template"], errors


def test_default_beats_every_method_it_was_compared_with(errors):
    others = {k: v for k, v in errors.items() if k != "default"}
    assert errors["default"] < min(others.values()), errors
