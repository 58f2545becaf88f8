"""Smoke test of the benchmark's peer adapters (benchmarks/peers.py) on the embedded model."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from statfit.structures.frame import Frame
from statfit.synth.sample import sample_target, scan_from_view

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import peers  # noqa: E402


@pytest.fixture(scope="module")
def problem(embedded_model) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Template, faces, a 2,000-point partial scan and the ground truth, in the template's unit frame."""
    rng = np.random.default_rng(3)
    target = sample_target(embedded_model, rng, sigma=1.5)
    points = scan_from_view(target, embedded_model.faces, rng, 2000, 30.0)
    frame = Frame.of(embedded_model.template)
    return frame.to_unit(embedded_model.template), embedded_model.faces, frame.to_unit(points), frame.to_unit(target)


def mean_error(vertices: np.ndarray, target: np.ndarray) -> float:
    return float(np.linalg.norm(vertices - target, axis=1).mean())


def test_largesteps_follows_the_statfit_laplacian_trajectory(problem):
    pytest.importorskip("largesteps")    # no wheel: a machine without network may lack it
    template, faces, points, target = problem
    ours = peers.statfit_laplacian(template, faces, points, 19.0, 0.01, 30)
    theirs = peers.largesteps_laplacian(template, faces, points, 19.0, 0.01, 30)
    assert np.abs(ours.vertices - theirs.vertices).max() < 1e-4
    assert mean_error(ours.vertices, target) < mean_error(template, target)


def test_amberg_and_cpd_fit_closer_than_the_template(problem):
    template, faces, points, target = problem
    amberg = peers.nricp(template, faces, points, "amberg", [[1.0, 0, 0.5, 2]], peers.AMBERG_THRESHOLD)
    moved = peers.cpd(template, points, **peers.CPD | {"controls": 300, "iterations": 10})
    start = mean_error(template, target)
    assert mean_error(amberg, target) < start
    assert mean_error(moved, target) < start
