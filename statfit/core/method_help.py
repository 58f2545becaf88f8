"""What the built-in fitting methods are called and say of themselves, in a module that imports no
torch: the command line's ``--help`` reads it without loading the fitting code, and
:mod:`statfit.core.methods` builds its registry from it."""
from __future__ import annotations

# The landmark term's weight (against the scan's mean squared distance) unless a method says
# otherwise: docs/studies.md §12 (the default's landmarks at 0.39x the start-only error at 10).
LANDMARK_WEIGHT = 10.0
# pca's: its span is all it can move; a heavier term bends it out of shape (§12).
PCA_LANDMARK_WEIGHT = 1.0

# Each built-in method's one-line summary, in the order ``--method``'s help lists them.
SUMMARIES = {
    "statistical": "x = x0 + F u, F = αUUᵀ + (1 − α)I",
    "laplacian": "x = x0 + (I + λL)⁻¹ u (Nicolet et al. 2021)",
    "hybrid": "x = x0 + F u, F = αUUᵀ + (1 − α)(I + λL)⁻¹",
    "pca": "x = x̄ + U diag(std) c: the model's coefficients only",
    "regularized": "free x, prior β/N ‖(I − UUᵀ)(x − x̄)‖²",
    "none": "free x, Adam",
}
