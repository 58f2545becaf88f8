"""End to end on the real ICT-FaceKit model: identity sample + an expression outside the model,
partial scans of 4,300 points. Errors are always against the ground truth.

What is asserted is what the study (docs/benchmarks.md) measured: the paper's statistical filter
beats the paper's Laplacian and regulariser (the Laplacian wins on the two jaw cases, which is
documented, not tested away), and the default pipeline beats every method at its tuned settings on
cases with large expressions (on small expressions a converged pca fit is as good or better).
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np
import pytest

from statfit.metrics import evaluate, observed_vertices
from statfit.register import register
from statfit.synth import sample_target, scan_from_view

pytestmark = pytest.mark.slow

# name: (seed, expression, weight, yaw, pitch) — cases of the study.
CASES = {
    "smile": (11, "mouthSmile_R", 1.0, 0.0, 0.0),
    "brow-up": (23, "browInnerUp_L", 0.9, -40.0, 0.0),
    "jaw-open": (3, "jawOpen", 1.0, 30.0, 0.0),
}


@pytest.fixture(scope="module")
def fit_case(ict_model, ict_expressions):
    names, deltas = ict_expressions

    @lru_cache(maxsize=None)
    def scan(case: str):
        seed, expression, weight, yaw, pitch = CASES[case]
        rng = np.random.default_rng(seed)
        target = sample_target(ict_model, rng, 1.0, deltas[..., names.index(expression)], weight)
        points = scan_from_view(target, ict_model.faces, rng, 4300, yaw, pitch)
        return target, points, observed_vertices(target, points)

    @lru_cache(maxsize=None)
    def run(case: str, method: str, preset: str) -> dict:
        target, points, observed = scan(case)
        result = register(ict_model, points, method, preset=preset)
        return evaluate(result.vertices, target, ict_model.faces, observed)

    return run


@pytest.mark.parametrize("case", ["smile", "brow-up"])
def test_paper_statistical_beats_paper_laplacian_and_regularized(fit_case, case):
    statistical = fit_case(case, "statistical", "paper")
    laplacian = fit_case(case, "laplacian", "paper")
    regularized = fit_case(case, "regularized", "paper")
    assert statistical["all"]["mean"] < laplacian["all"]["mean"]
    assert statistical["all"]["mean"] < regularized["all"]["mean"]
    assert statistical["unobserved"]["mean"] < laplacian["unobserved"]["mean"]


def test_paper_statistical_beats_paper_regularized_on_jaw_open(fit_case):
    assert fit_case("jaw-open", "statistical", "paper")["all"]["mean"] < \
        fit_case("jaw-open", "regularized", "paper")["all"]["mean"]


@pytest.mark.parametrize("case", ["jaw-open"])
def test_default_pipeline_beats_every_tuned_method(fit_case, case):
    default = fit_case(case, "default", "tuned")
    for method in ("statistical", "hybrid", "laplacian", "pca", "regularized", "none"):
        other = fit_case(case, method, "tuned")
        assert default["all"]["mean"] < other["all"]["mean"], method
    assert default["observed_surface"]["mean"] < fit_case(case, "pca", "tuned")["observed_surface"]["mean"]
