"""End to end on the embedded synthetic model: the demo's case (a random head seen from one side)."""
from __future__ import annotations

from functools import lru_cache

import numpy as np
import pytest

from statfit.geometry.metrics import evaluate, observed_vertices
from statfit.registration.job import register
from statfit.synth.sample import sample_target, scan_from_view

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def fit(embedded_model):
    rng = np.random.default_rng(3)
    target = sample_target(embedded_model, rng, sigma=1.5)
    points = scan_from_view(target, embedded_model.faces, rng, 4300, 30.0)
    observed = observed_vertices(target, points)

    @lru_cache(maxsize=None)
    def run(method: str, preset: str) -> dict:
        result = register(embedded_model, points, method, preset=preset)
        return evaluate(result.vertices, target, embedded_model.faces, observed)

    return run


def test_paper_statistical_beats_laplacian_and_regularized(fit):
    statistical, laplacian, regularized = (fit(m, "paper") for m in ("statistical", "laplacian", "regularized"))
    assert statistical["all"]["mean"] < laplacian["all"]["mean"]
    assert statistical["all"]["mean"] < regularized["all"]["mean"]
    assert statistical["unobserved"]["mean"] < laplacian["unobserved"]["mean"]


def test_default_pipeline_beats_the_vertex_based_baselines(fit):
    """Not ``hybrid``: since the gradient methods start from the pose search's shape (docs/studies.md
    §19), its 1,000 steps fit this in-span demo head closer than the default (0.18 against 0.24 mm
    over all vertices); the cross-family studies keep the default (§17, §19)."""
    default = fit("default", "tuned")
    template = fit("none", "paper")
    for method in ("statistical", "laplacian", "regularized", "none"):
        assert default["all"]["mean"] < fit(method, "tuned")["all"]["mean"], method
    assert default["all"]["mean"] < 0.5 * template["all"]["mean"]


def test_a_settled_laplacian_fit_does_not_move_for_a_nudge_no_scanner_sees(embedded_model):
    """Half a face nudged by a millionth of the head's width: the tuned ``laplacian`` fit (the
    default's fallback), whose step settles over its last half, lands where it did to within 1e-5
    of the width; the same fit at a constant step ends wherever its last steps took it, 6e-4 apart
    on this case (docs/studies.md §30)."""
    from dataclasses import replace

    from statfit.core.methods import resolve

    rng = np.random.default_rng(2)
    target = sample_target(embedded_model, rng, 1.5)
    points = scan_from_view(target, embedded_model.faces, rng, 2000, 20.0)
    half = points[points[:, 0] > np.median(points[:, 0])]
    width = float(np.ptp(embedded_model.template[:, 0]))
    nudged = half + np.random.default_rng(1).standard_normal(half.shape) * 1e-6 * width
    settled = resolve("laplacian")
    assert settled[0].settle == 0.5

    def apart(stages) -> float:
        given, moved = (register(embedded_model, p, stages=stages, threads=1).vertices for p in (half, nudged))
        return float(np.linalg.norm(given - moved, axis=1).mean()) / width

    assert apart(settled) < 1e-5
    assert apart((replace(settled[0], settle=0.0),)) > 1e-4      # the case is one whose paths part
