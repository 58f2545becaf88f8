"""End to end on the real ICT head model: one normal map (yaw 20°) of an identity sample plus the
jawOpen expression (outside the identity model); every fit is scored against the ground truth over
all vertices. What is asserted is what the rendering study measured at 256² (docs/studies.md §5:
paper statistical 0.0484, paper laplacian 0.0590); the test renders 128² to keep the suite short,
where the same four fits measured 0.0548 and 0.0619, tuned pca 0.0453, the default 0.0397 and the
template 0.1448 (the fits take a third of the 256² time).

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

    from statfit.normal_map import NormalMap
    from statfit.inverse_render import reconstruct
    from statfit.model import load_model
    from statfit.synth import camera_for_view, load_delta, render_target, sample_target

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


def test_paper_statistical_beats_paper_laplacian(errors):
    assert errors["paper statistical"] < errors["paper laplacian"], errors
    assert errors["paper statistical"] < 0.5 * errors["template"], errors


def test_default_beats_every_method_it_was_compared_with(errors):
    others = {k: v for k, v in errors.items() if k != "default"}
    assert errors["default"] < min(others.values()), errors
