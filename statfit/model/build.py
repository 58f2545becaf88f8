"""Build a model from registered meshes (same topology, vertices in correspondence) by PCA."""
from __future__ import annotations

import warnings

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from statfit.errors import StatfitError, StatfitWarning
from statfit.io.mesh import read_mesh
from statfit.model.statmodel import StatModel, model_from_arrays
from statfit.model.pca import principal_components


@dataclass(frozen=True)
class BuiltModel:
    """The model and the cumulative fraction of the meshes' variance its first k modes explain, (K,)."""

    model: StatModel
    variance_explained: np.ndarray


def build_model(meshes: Sequence[tuple[np.ndarray, np.ndarray]], k: int | None = None, *,
                names: Sequence[str] | None = None, randomized: bool | None = None, seed: int = 0) -> BuiltModel:
    """PCA of ``meshes`` [(vertices (N, 3), faces (F, 3))]: mean template, the first ``k`` principal
    directions (all, M − 1, by default), the first mesh's faces. Meshes must share the topology."""
    names = list(names or (f"mesh {i}" for i in range(len(meshes))))
    if len(meshes) < 2:
        raise StatfitError(f"building a model needs at least 2 meshes, got {len(meshes)}")
    first_vertices, faces = meshes[0]
    for name, (vertices, other_faces) in zip(names[1:], meshes[1:]):
        if len(vertices) != len(first_vertices):
            raise StatfitError(f"{name} has {len(vertices)} vertices, the first mesh ({names[0]}) "
                               f"{len(first_vertices)}: meshes must be in correspondence")
        if other_faces.shape != faces.shape or (other_faces != faces).any():
            raise StatfitError(f"the faces of {name} differ from those of the first mesh ({names[0]}): "
                               "meshes must share one topology")
    samples = np.stack([vertices.reshape(-1) for vertices, _ in meshes])
    most = len(meshes) - 1
    if k is not None and k > most:  # as build_texture_model does: a model, with a word on what it can hold
        warnings.warn(f"{len(meshes)} meshes give at most {most} modes; keeping {most}", StatfitWarning)
        k = most
    pca = principal_components(samples, most if k is None else k, randomized=randomized, seed=seed)
    n = len(first_vertices)
    model = model_from_arrays(pca.mean.reshape(n, 3), faces, pca.scaled_directions.T.reshape(n, 3, -1),
                              source=f"PCA of {len(meshes)} meshes")
    return BuiltModel(model, pca.variance_explained())


def build_model_from_files(paths: Sequence[str | Path], k: int | None = None, **options) -> BuiltModel:
    """:func:`build_model` of mesh files (PLY, OBJ, STL, OFF)."""
    return build_model([read_mesh(path) for path in paths], k, names=[str(p) for p in paths], **options)
