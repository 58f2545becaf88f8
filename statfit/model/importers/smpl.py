"""FLAME, SMPL-X and SMPL models: pickles (chumpy era or plain numpy) and npz files.

The three share one layout: ``v_template (N, 3)``, ``f (F, 3)`` and ``shapedirs (N, 3, K)`` whose
columns are already directions scaled for coefficients ~ N(0, 1) (the npz contract's scaling), plus
skinning data (``posedirs``, ``J_regressor``, ``weights``, ``kintree_table``) that a shape model does
not need. FLAME 2020/2023 (K = 400) and SMPL-X v1.1 (K = 400) put 300 identity directions first and
100 expression directions after them; SMPL-X v1.0 (K = 20) 10 and 10; SMPL's are all identity.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

import numpy as np

from statfit.errors import StatfitError
from statfit.model.importers.safe_pickle import load_pickle
from statfit.model.statmodel import StatModel, model_from_arrays

REQUIRED_KEYS = ("v_template", "f", "shapedirs")
IDENTITY_MODES = 300  # FLAME and SMPL-X v1.1: shapedirs[..., :300] identity, the rest expression
SMPLX_V10 = (10475, 20)  # SMPL-X v1.0: (vertices, K) with 10 identity + 10 expression directions
SMPLX_KEYS = ("hands_componentsl", "hands_componentsr")


def identity_count(arrays: Mapping[str, Any], num_vertices: int, num_directions: int) -> int:
    """How many of the leading ``shapedirs`` columns are identity (shape) directions."""
    smplx = any(key in arrays for key in SMPLX_KEYS) or num_vertices == SMPLX_V10[0]
    if smplx and num_directions == SMPLX_V10[1]:
        return 10
    return min(num_directions, IDENTITY_MODES)


def family(arrays: Mapping[str, Any], num_vertices: int) -> str:
    """FLAME, SMPL-X or SMPL, for messages."""
    if any(key in arrays for key in SMPLX_KEYS) or num_vertices == SMPLX_V10[0]:
        return "SMPL-X"
    return "SMPL" if num_vertices == 6890 else "FLAME"


def from_arrays(arrays: Mapping[str, Any], source: str, *, k: int | None = None,
                expressions: bool = False) -> StatModel:
    """A StatModel from a SMPL-family dict: the identity directions (first ``k`` of them when
    given), followed by the expression directions with ``expressions``."""
    missing = [key for key in REQUIRED_KEYS if key not in arrays]
    if missing:
        raise StatfitError(f"{source} lacks the key(s) {', '.join(missing)} of a FLAME/SMPL-X model")
    shapedirs = np.asarray(arrays["shapedirs"])
    template = np.asarray(arrays["v_template"])
    if shapedirs.ndim != 3 or shapedirs.shape[:2] != template.shape or template.ndim != 2:
        raise StatfitError(f"{source}: shapedirs {shapedirs.shape} does not match v_template {template.shape} "
                           "(expected (N, 3, K) and (N, 3))")
    n_identity = identity_count(arrays, template.shape[0], shapedirs.shape[2])
    name = family(arrays, template.shape[0])
    if k is not None and not 1 <= k <= n_identity:
        hint = f" (--expressions adds the other {shapedirs.shape[2] - n_identity}, the expression directions)" \
            if shapedirs.shape[2] > n_identity else ""
        raise StatfitError(f"--k must be between 1 and {n_identity}, the {name} model's identity directions{hint}")
    directions = shapedirs[..., :k or n_identity]
    if expressions:
        if shapedirs.shape[2] == n_identity:
            raise StatfitError(f"{source}: the model has no expression directions")
        directions = np.concatenate([directions, shapedirs[..., n_identity:]], axis=2)
    return model_from_arrays(template, arrays["f"], directions, source=f"{source} ({name})")


def read_pickle(path: str | Path) -> dict[str, Any]:
    """The dict in a FLAME/SMPL-X pickle (chumpy arrays become numpy arrays, nothing is executed)."""
    loaded = load_pickle(path)
    if not isinstance(loaded, dict):
        raise StatfitError(f"{path}: not a model pickle (expected a dict with {', '.join(REQUIRED_KEYS)}; "
                           f"got a {type(loaded).__name__})")
    return loaded
