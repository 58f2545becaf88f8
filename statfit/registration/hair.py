"""Hair: scan points over the scalp where a fit of the face alone expects skin.

Hair passes every clutter rule of the data term (:mod:`statfit.objectives.scan`): a layer 5–9 mm
over the scalp, with the scalp's normals, near enough to pull the fit outwards until it is nearer
still. The face, which hair does not cover, tells where the scalp is: fitted to the face alone, the
model's modes carry the head's shape with it. Points lying more than HAIR_OFFSET outside that fit,
nearest to a triangle off the face, are hair (or a hat, or anything else over the head); the rest of
the scan — the face, the ears and the sides of the head it leaves bare — can then be fitted whole
(docs/method.md, "The registration objective"). Both the pose search
(:mod:`statfit.registration.pose.search`) and the fit (:mod:`statfit.registration`) use this rule.

That scalp is a guess, and for a person outside the model a few millimetres off: hair 5 mm out
then passes for skin. So on a scan with clutter, every point nearest the scalp region
(:func:`statfit.model.statmodel.scalp_triangles`: where hair can grow) counts as hair too, wherever it lies
(docs/studies.md §16, "The scalp as a region").
"""
from __future__ import annotations

import torch

from statfit.geometry.closest import ClosestPointQuery
from statfit.core.gauss_newton import fit_coefficients
from statfit.core.methods import resolve
from statfit.objectives.scan import ScanObjective
from statfit.core.settings import FitSpace

# Scan points this far outside a fit of the face alone (model RMS radii, ~4.5 mm on a head), off the
# face, are hair (docs/studies.md §16; 0.02 found 1.4–2.4× as many points and fitted no better).
HAIR_OFFSET = 0.05
# ... unless more of the scan than this lies there: that is no head under hair (the pose search then
# fits every point, the fit the face alone).
MAX_HAIR_SHARE = 0.6
# The face-only fit that finds the scalp: the closed-form pca stage, at most this many steps.
FACE_FIT_ITERATIONS = 40
# Fewer scan points than this closest to the face: no face to fit, so no hair can be told from it.
MIN_FACE_POINTS = 10


def hair_suspects(query: ClosestPointQuery, shape: torch.Tensor, points: torch.Tensor, face: torch.Tensor,
                  scalp: torch.Tensor | None = None) -> torch.Tensor | None:
    """(M,) bool: ``points`` (M, 3) lying more than HAIR_OFFSET outside ``shape`` (N, 3, the
    model's unit frame; outside = along its closest triangle's normal, the mesh wound outwards)
    whose closest triangle is off the ``face`` (F,) bool triangles, and those whose closest
    triangle is on the ``scalp`` (F,) bool (:func:`statfit.model.statmodel.scalp_triangles`), wherever they
    lie; None where more than MAX_HAIR_SHARE of the points lie outside off the face: no head under hair."""
    attached = query(shape, points)
    a, b, c = shape[query.faces[attached.triangle]].unbind(dim=1)
    normals = torch.nn.functional.normalize(torch.linalg.cross(b - a, c - a), dim=-1)
    surface = (torch.stack([a, b, c], dim=1) * attached.barycentric[..., None]).sum(dim=1)
    outside = ((points - surface) * normals).sum(dim=-1)
    suspects = (outside > HAIR_OFFSET) & ~face[attached.triangle]
    if float(suspects.double().mean()) > MAX_HAIR_SHARE:
        return None
    return suspects if scalp is None else suspects | scalp[attached.triangle]


def hair_points(space: FitSpace, query: ClosestPointQuery, points: torch.Tensor, normals: torch.Tensor | None,
                face: torch.Tensor, trim: float, start: torch.Tensor, scalp: torch.Tensor | None = None
                ) -> torch.Tensor | None:
    """(M,) bool: the scan ``points`` (M, 3, fit frame; ``normals`` (M, 3) or None) that are hair
    over the head of a fit of the model to its ``face`` (F,) bool triangles alone (the closed-form
    pca stage as shipped from ``start`` (N, 3), at most FACE_FIT_ITERATIONS steps; the data term's
    clutter rules and ``trim``), or on its ``scalp`` (F,) bool triangles; None: no head under hair
    (:func:`hair_suspects`). Where too few points lie closest to the face to fit it, none is hair."""
    objective = ScanObjective(points, query, trim=trim, region_faces=face, normals=normals, clutter=True)
    objective.refresh(start)
    if objective.kept < MIN_FACE_POINTS:
        return torch.zeros(len(points), dtype=torch.bool, device=points.device)
    pca = resolve("pca")[0]
    fitted = fit_coefficients(space.mean, space.basis_t, space.std, objective, start, FACE_FIT_ITERATIONS,
                              pca.noise, pca.levels)
    return hair_suspects(query, fitted.vertices, points, face, scalp)
