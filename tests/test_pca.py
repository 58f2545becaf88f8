"""PCA of samples in correspondence: exact and randomised agree and recover a known subspace."""
from __future__ import annotations

import numpy as np
import pytest

from statfit.errors import StatfitError
from statfit.model.pca import principal_components


def _samples(rng, m=300, d=900, k=5, noise=1e-3):
    basis, _ = np.linalg.qr(rng.standard_normal((d, k)))
    std = np.linspace(5.0, 1.0, k)
    coeffs = rng.standard_normal((m, k)) * std
    return 3.0 + coeffs @ basis.T + noise * rng.standard_normal((m, d)), basis


def test_recovers_known_subspace_exact_and_randomized(rng):
    samples, basis = _samples(rng)
    exact = principal_components(samples, 5, randomized=False)
    fast = principal_components(samples, 5, randomized=True)
    for result in (exact, fast):
        np.testing.assert_allclose(result.directions @ result.directions.T, np.eye(5), atol=1e-10)
        # Projector onto the found subspace equals the true one.
        np.testing.assert_allclose(result.directions.T @ result.directions, basis @ basis.T, atol=1e-3)
        assert result.variance_explained()[-1] == pytest.approx(1.0, abs=1e-4)
        assert (np.diff(result.std) <= 0).all()
    np.testing.assert_allclose(fast.std, exact.std, rtol=1e-8)
    np.testing.assert_allclose(np.abs(fast.directions @ exact.directions.T), np.eye(5), atol=1e-6)
    # Sample standard deviations along the directions, with the usual (M - 1) normalisation.
    projected = (samples - exact.mean) @ exact.directions.T
    np.testing.assert_allclose(projected.std(axis=0, ddof=1), exact.std, rtol=1e-10)


def test_truncation_reports_partial_variance(rng):
    samples = rng.standard_normal((50, 20))
    result = principal_components(samples, 3)
    assert 0.0 < result.variance_explained()[-1] < 0.5
    assert result.scaled_directions.shape == (3, 20)


@pytest.mark.parametrize("samples,k,message", [
    (np.ones((1, 4)), 1, "at least 2 samples"),
    (np.ones((5, 4)), 2, "identical"),
    (np.arange(20.0).reshape(5, 4), 5, "between 1 and 4"),
    (np.full((5, 4), np.nan), 1, "NaN"),
])
def test_bad_input(samples, k, message):
    with pytest.raises(StatfitError, match=message):
        principal_components(samples, k)
