"""``on_snapshot``: the fit's vertices every 10 iterations, in the input's frame (for convergence traces)."""
from __future__ import annotations

import numpy as np

from statfit.registration.job import register
from statfit.synth.sample import sample_target, scan_from_view


def test_register_snapshots_are_in_the_scan_frame(embedded_model):
    rng = np.random.default_rng(5)
    target = sample_target(embedded_model, rng)
    points = 1000.0 * scan_from_view(target, embedded_model.faces, rng, 2000, 30.0)  # millimetres
    snapshots, records = [], []
    result = register(embedded_model, points, "statistical", preset="paper", align="similarity", iterations=25,
                      on_record=lambda it, terms: records.append(it),
                      on_snapshot=lambda it, vertices: snapshots.append((it, vertices)))
    assert [it for it, _ in snapshots] == records == [0, 10, 20, 24]
    # The first snapshot is the aligned template; the last is one step before the result.
    np.testing.assert_allclose(snapshots[0][1], result.transform.apply(embedded_model.template), atol=1e-3)
    radius = np.sqrt(((result.vertices - result.vertices.mean(0)) ** 2).sum(1).mean())
    assert np.abs(snapshots[-1][1] - result.vertices).max() < 0.01 * radius
    errors = [np.linalg.norm(v - 1000.0 * target, axis=1).mean() for _, v in snapshots]
    assert errors[-1] < errors[0]
