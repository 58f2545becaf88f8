"""Principal component analysis of samples in correspondence (meshes, images), exact or randomised.

A sample is one row of ``samples (M, D)``. The result follows the model contract: directions
scaled by their standard deviations, so a new sample is ``mean + directions.T @ c`` with
c ~ N(0, I).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from statfit.errors import StatfitError

EXACT_MAX_ELEMENTS = 4_000_000  # below this many entries in the smaller Gram side, a dense SVD is cheap


@dataclass(frozen=True)
class PCA:
    """mean (D,); directions (K, D) orthonormal rows; std (K,) decreasing; total_variance of the
    samples (all modes, not just the K kept)."""

    mean: np.ndarray
    directions: np.ndarray
    std: np.ndarray
    total_variance: float

    @property
    def scaled_directions(self) -> np.ndarray:
        """Directions times their standard deviations, (K, D)."""
        return self.directions * self.std[:, None]

    def variance_explained(self) -> np.ndarray:
        """Cumulative fraction of the samples' variance explained by the first k modes, (K,)."""
        return np.cumsum(self.std**2) / self.total_variance


def principal_components(samples: np.ndarray, k: int, *, randomized: bool | None = None,
                         seed: int = 0, power_iterations: int = 4) -> PCA:
    """The first ``k`` principal components of ``samples (M, D)`` (M ≥ 2).

    ``randomized=None`` picks the exact SVD for small problems and a randomised range finder
    (Halko et al. 2011, with ``power_iterations`` subspace iterations) for large ones. Each
    direction's sign is fixed so that its largest-magnitude entry is positive.
    """
    samples = np.asarray(samples, dtype=np.float64)
    if samples.ndim != 2 or samples.shape[0] < 2:
        raise StatfitError(f"PCA needs at least 2 samples, got {samples.shape[0] if samples.ndim else 0}")
    if not np.isfinite(samples).all():
        raise StatfitError("PCA samples contain NaN or infinite values")
    m, d = samples.shape
    k_max = min(m - 1, d)
    if not 1 <= k <= k_max:
        raise StatfitError(f"k must be between 1 and {k_max} for {m} samples of size {d}, got {k}")
    mean = samples.mean(axis=0)
    centred = samples - mean
    total_variance = float(np.einsum("ij,ij->", centred, centred) / (m - 1))
    if total_variance == 0.0:
        raise StatfitError("all samples are identical: there is no variation to model")
    if randomized is None:
        randomized = min(m, d) ** 2 > EXACT_MAX_ELEMENTS and k < min(m, d) // 2
    if randomized:
        s, vt = _randomized_svd(centred, k, np.random.default_rng(seed), power_iterations)
    else:
        _, s, vt = np.linalg.svd(centred, full_matrices=False)
        s, vt = s[:k], vt[:k]
    std = s / np.sqrt(m - 1)
    keep = std > std[0] * 1e-10
    return PCA(mean, with_fixed_signs(vt[keep]), std[keep], total_variance)


def with_fixed_signs(directions: np.ndarray) -> np.ndarray:
    """``directions`` (K, D), each row's sign flipped so that its largest-magnitude entry is positive."""
    return directions * fixed_signs(directions)[:, None]


def fixed_signs(directions: np.ndarray) -> np.ndarray:
    """(K,) ±1: the sign of each row of ``directions`` (K, D) at its largest-magnitude entry (+1 for a
    zero row), so that SVDs of different LAPACK builds agree once multiplied by it."""
    signs = np.sign(directions[np.arange(len(directions)), np.abs(directions).argmax(axis=1)])
    return np.where(signs == 0, 1.0, signs)


def _randomized_svd(a: np.ndarray, k: int, rng: np.random.Generator,
                    power_iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """Top ``k`` singular values and right singular vectors (k, D) of ``a`` by a randomised range finder."""
    width = min(k + max(10, k // 2), min(a.shape))
    q, _ = np.linalg.qr(a @ rng.standard_normal((a.shape[1], width)))
    for _ in range(power_iterations):  # re-orthonormalise each pass to keep small singular values
        q, _ = np.linalg.qr(a.T @ q)
        q, _ = np.linalg.qr(a @ q)
    _, s, vt = np.linalg.svd(q.T @ a, full_matrices=False)
    return s[:k], vt[:k]
