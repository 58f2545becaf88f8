"""The model's code for a fitted mesh: the similarity that puts the model onto the data, the
least-squares coefficients of the fit in the model's modes, and what the modes do not explain.

A fit's vertices ``V`` (N, 3) lie in the data's frame; ``transform`` (model → data) is the fit's
pre-alignment. Undone, ``d = transform⁻¹(V) − template`` flattened to (3N,) is projected onto the
orthonormal ``basis`` (3N, K): ``c = (basisᵀ d) / std`` (standard deviations, one per mode), and
the residual ``r = d − basis basisᵀ d`` is the part of the fit off the model's span (per vertex,
``‖r_i‖``, model units). Evaluating ``transform(model.shape(c))`` gives the projection back.

The file format (JSON or npz) is in :mod:`statfit.model.params_file` and docs/formats.md.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np

from statfit.errors import StatfitError
from statfit.geometry.align import Similarity
from statfit.model.pca import fixed_signs
from statfit.model.statmodel import StatModel


@dataclass(frozen=True)
class Projection:
    """A fit in the model's code.

    coefficients: (K,) float64 in standard deviations, the model's own signs; transform: the
    similarity model → data; off_span: (N,) float64 distance of each fitted vertex from the
    model's span, model units (zero for a mesh the model makes, None when read from a file);
    units_factor: the unit the automatic alignment found between the data's units and the model's,
    a power of ten, or with landmarks one over 2.54 (inches) (None: not searched)."""

    coefficients: np.ndarray
    transform: Similarity
    off_span: np.ndarray | None = None
    units_factor: float | None = None


def project(model: StatModel, vertices: np.ndarray, transform: Similarity | None = None,
            units_factor: float | None = None) -> Projection:
    """The least-squares code of ``vertices`` (N, 3, the data's frame) under ``transform`` (model →
    data; None: the identity): coefficients (K,) and the per-vertex off-span residual (N,)."""
    vertices = np.asarray(vertices, dtype=np.float64)
    if vertices.shape != model.template.shape:
        raise StatfitError(f"the mesh has {len(vertices)} vertices; the model has {model.num_vertices}")
    transform = transform or Similarity()
    offset = (transform.inverse_apply(vertices) - model.template).reshape(-1)  # (3N,)
    raw = model.basis.T @ offset                                                # (K,) model units
    residual = (offset - model.basis @ raw).reshape(-1, 3)
    return Projection(raw / model.std, transform, np.linalg.norm(residual, axis=1), units_factor)


def posed_shape(model: StatModel, projection: Projection) -> np.ndarray:
    """The mesh (N, 3) the code makes: ``transform(template + basis · (std · c))``, the data's frame."""
    return projection.transform.apply(model.shape(projection.coefficients))


def off_span_summary(model: StatModel, off_span: np.ndarray) -> dict:
    """RMS and max of the per-vertex residual (N,), over all vertices and per model region."""
    def stats(values: np.ndarray) -> dict[str, float]:
        return {"rms": float(np.sqrt(np.mean(values**2))) if values.size else 0.0,
                "max": float(values.max()) if values.size else 0.0}

    return {**stats(off_span), "regions": {name: stats(off_span[index]) for name, index in sorted(model.regions.items())}}


def canonical_signs(model: StatModel) -> np.ndarray:
    """(K,) ±1 per mode: the sign that makes the mode's largest-magnitude basis entry positive. An
    SVD's signs may differ between LAPACK builds; coefficients times these do not."""
    return fixed_signs(model.basis.T)


def model_fingerprint(model: StatModel) -> dict:
    """What identifies a model in a params file: vertex, face and mode counts, and a sha256 of the
    template (float64), the faces (int64) and the standard deviations written to 6 significant
    digits (robust to an SVD's last bits)."""
    digest = hashlib.sha256()
    digest.update(np.ascontiguousarray(model.template, dtype="<f8").tobytes())
    digest.update(np.ascontiguousarray(model.faces, dtype="<i8").tobytes())
    digest.update(" ".join(f"{s:.5e}" for s in model.std).encode())
    return {"vertices": model.num_vertices, "faces": int(len(model.faces)), "modes": model.num_modes,
            "sha256": digest.hexdigest()}


def check_fingerprint(model: StatModel, found: dict, source: str) -> None:
    """Refuse a params file made for another model: one line naming the first mismatch."""
    own = model_fingerprint(model)
    for key, what in (("vertices", "vertices"), ("faces", "faces"), ("modes", "modes")):
        if found.get(key) != own[key]:
            raise StatfitError(f"{source} was made for a model of {found.get(key)} {what}; this model ({model.source}) "
                               f"has {own[key]} (use the model, and --k, the fit used)")
    if found.get("sha256") is not None and found["sha256"] != own["sha256"]:
        raise StatfitError(f"{source} was made for another model of the same size (its sha256 {found['sha256'][:12]}… "
                           f"differs from {model.source}'s {own['sha256'][:12]}…)")


def vertex_fields(projection: Projection, data_distance: np.ndarray, observed: np.ndarray) -> dict[str, np.ndarray]:
    """The fitted PLY's per-vertex fields (N,) each, all in the mesh's (the data's) units:
    ``data_distance`` and ``observed`` (:mod:`statfit.geometry.support`) and ``off_span``, the
    projection's residual scaled by the similarity's scale."""
    if projection.off_span is None:
        raise StatfitError("the projection has no per-vertex residual (read from a file?)")
    return {"data_distance": np.asarray(data_distance, dtype=np.float64), "observed": np.asarray(observed, dtype=bool),
            "off_span": projection.off_span * projection.transform.scale}
