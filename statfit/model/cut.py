"""Other models made from one: a part of it (a face mask cut from a head), fewer vertices
(decimated), other units, its modes without rigid motion. Each is again a model of the same
people: the shapes of the original, seen on a subset of its vertices, so its modes are re-derived by
SVD of the original's restricted to those vertices (a restricted basis is no longer orthonormal).

These make the model families statfit's defaults are checked on besides the ones they were chosen
on (docs/studies.md): a face-mask model, the shape of BFM 2017 and most scanner-built models, is
ICT's face region cut out, decimated to a few thousand vertices, in millimetres.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from functools import cached_property

import igl
import numpy as np

from statfit.errors import StatfitError, StatfitWarning
from statfit.model.statmodel import StatModel, model_from_arrays
from statfit.structures.kdtree import kd_tree


def vertex_subset(model: StatModel, keep: np.ndarray, faces: np.ndarray | None = None,
                  source: str | None = None, nearest_landmarks: bool = False) -> StatModel:
    """The model on the vertices ``keep`` (K,) indices into the model's, in that order.

    faces: (F', 3) triangles over the kept vertices' new indices; default: the model's triangles whose
    three corners are kept, renumbered. Landmarks are kept when all of them are (else dropped, with a
    warning: a landmark file numbers all of them), or with ``nearest_landmarks`` each moves to the
    kept vertex nearest it on the template; regions keep their kept vertices, and a region left
    without a whole triangle is dropped (with a warning)."""
    keep = np.asarray(keep, dtype=np.int64).reshape(-1)
    if keep.size < 3 or len(np.unique(keep)) != keep.size or keep.min() < 0 or keep.max() >= model.num_vertices:
        raise StatfitError(f"a model part needs 3 or more distinct vertices of the model's {model.num_vertices}")
    new_index = np.full(model.num_vertices, -1, dtype=np.int64)
    new_index[keep] = np.arange(keep.size)
    if faces is None:
        whole = (new_index[model.faces] >= 0).all(axis=1)
        faces = new_index[model.faces[whole]]
    if len(faces) == 0:
        raise StatfitError("the part keeps no whole triangle of the model")
    shapedirs = (model.basis * model.std).reshape(model.num_vertices, 3, model.num_modes)[keep]
    landmarks = None
    if model.landmarks is not None and nearest_landmarks:
        landmarks = kd_tree(model.template[keep]).query(model.template[model.landmarks])[1]
    elif model.landmarks is not None:
        if (new_index[model.landmarks] >= 0).all():
            landmarks = new_index[model.landmarks]
        else:
            warnings.warn(f"{int((new_index[model.landmarks] < 0).sum())} of the model's {len(model.landmarks)} "
                          "landmarks lie outside the part: the part has no landmarks", StatfitWarning, stacklevel=2)
    regions = {name: new_index[index][new_index[index] >= 0] for name, index in model.regions.items()}
    regions = {name: index for name, index in regions.items() if np.isin(faces, index).all(axis=1).any()}
    if lost := sorted(set(model.regions) - set(regions)):
        warnings.warn(f"the part keeps no whole triangle of the region(s) {', '.join(lost)}: it has none of them",
                      StatfitWarning, stacklevel=2)
    return model_from_arrays(model.template[keep], faces, shapedirs, landmarks, regions,
                             source=source or f"{model.source} (part)")


def region_part(model: StatModel, name: str) -> StatModel:
    """The model on its region ``name``'s vertices that lie on a whole triangle of the region."""
    if name not in model.regions:
        known = ", ".join(sorted(model.regions)) or "none"
        raise StatfitError(f"the model has no region {name!r} (its regions: {known})")
    inside = np.zeros(model.num_vertices, dtype=bool)
    inside[model.regions[name]] = True
    whole = inside[model.faces].all(axis=1)
    if not whole.any():
        raise StatfitError(f"the region {name!r} contains no whole triangle")
    return vertex_subset(model, np.unique(model.faces[whole]), source=f"{model.source} ({name})")


def decimated(model: StatModel, vertices: int) -> StatModel:
    """The model on about ``vertices`` of its vertices: edge collapses (libigl's ``decimate``) choose
    the vertices and the triangles between them; each kept vertex keeps its place and its modes in
    the original (no new positions, so the part is exactly the original's shapes seen there); a
    landmark moves to the nearest kept vertex (within about one new edge length)."""
    if vertices >= model.num_vertices:
        return model
    if vertices < 4:
        raise StatfitError(f"decimating to {vertices} vertices leaves no surface; ask for 4 or more")
    target_faces = max(4, int(round(len(model.faces) * vertices / model.num_vertices)))
    result = igl.decimate(model.template, model.faces.astype(np.int32), target_faces)
    _, faces, _, birth = result[-4:]     # libigl 2.5 returns a success flag first
    faces, birth = np.asarray(faces, dtype=np.int64), np.asarray(birth, dtype=np.int64)
    used = np.unique(faces)
    renumber = np.full(len(birth), -1, dtype=np.int64)
    renumber[used] = np.arange(used.size)
    return vertex_subset(model, birth[used], renumber[faces], source=f"{model.source} ({used.size} vertices)",
                         nearest_landmarks=True)


def rescaled(model: StatModel, factor: float) -> StatModel:
    """The model in other units: template and modes times ``factor`` (e.g. 10 for cm → mm)."""
    if not np.isfinite(factor) or factor <= 0:
        raise StatfitError(f"a model's scale factor must be a positive number, got {factor}")
    return StatModel(model.template * factor, model.faces, model.basis, model.std * factor, model.landmarks,
                     model.regions, model.source)


# Modes whose non-rigid part is below this share of their size are rigid motion and rounding alone.
RIGID_ONLY = 1e-9


def without_rigid_motion(model: StatModel) -> StatModel:
    """The model with its modes' rigid motion taken out: from each mode (its direction times its
    standard deviation) the least-squares small rigid motion of the template (a translation and a
    rotation about the template's centroid) is subtracted, and the modes are re-derived by SVD.

    A part cut from a larger model moves as the whole did: a head cut from a body model rises and
    falls with the body's height, so most of its modes' variance is where the head is, not its shape
    (MakeHuman's: 99.8%). A fit finds the pose itself; modes that move the part rigidly trade against
    it. To first order every shape of the model is a rigid motion of a shape of this one. Modes left
    with (almost) nothing are dropped (StatfitError if every one is); landmarks and regions are
    kept. Not for every model: on a face mask (30% rigid) `register`'s default guessed the unseen
    half worse without it, though `render` fitted closer (docs/studies.md §43); the jobs apply it
    above :data:`MOSTLY_RIGID` (:func:`fitting_model`)."""
    return _with_modes(model, _less_rigid_motion(model))


def _with_modes(model: StatModel, shaped: np.ndarray) -> StatModel:
    """The model with the modes ``shaped`` (3N, K) (directions times standard deviations,
    :func:`_less_rigid_motion`), re-derived by SVD; StatfitError if nothing is left of them."""
    if _nothing_left(model, shaped):
        raise StatfitError("the model's modes only move it rigidly: without that motion no mode is left")
    return model_from_arrays(model.template, model.faces, shaped.reshape(model.num_vertices, 3, -1), model.landmarks,
                             model.regions, source=f"{model.source} (without rigid motion)")


def _nothing_left(model: StatModel, shaped: np.ndarray) -> bool:
    return bool(np.linalg.norm(shaped) <= RIGID_ONLY * np.linalg.norm(model.std))


RIGID_MODES = ("auto", "keep", "drop")
# ``auto`` drops the modes' rigid motion above this share of their variance. Measured: the families
# at 12–30% (where dropping it made `register` worse on a face mask) and at 99.8–99.9% (parts cut
# from a body model, which fit far closer without it; docs/studies.md §43–§44). MakeHuman's whole
# body model lies at 73% (a taller body's centroid is higher): its studies were made as built and it
# was not measured without, so it keeps them.
MOSTLY_RIGID = 0.9
# Modes with less than this share of rigid motion hold none to speak of (a model fitted without it):
# `register`'s closed form then moves the pose itself (statfit.registration.posed.POSE_STD; docs/studies.md
# §47). ICT's head holds 21%, its mask 30%, the embedded head 12%.
NO_RIGID_MOTION = 0.01


# In a job whose alignment finds the pose before the fit (``render``), ``auto`` also drops it, on a
# model at most PLACE_DECIDES rigid, where that alignment moved the model farther than OFF_ITS_PLACE
# standard deviations of the modes' own rigid motion (:func:`rigid_motion_distance`; 4.1 is the 99th
# percentile of that distance over six degrees of freedom): the person is then not where the model
# places its people, and the modes' rigid motion, the model's statistics of that place, only trades
# with the found pose (docs/studies.md §46). Measured on head models at 21–30%, where it gains, and
# on MakeHuman's body model at 73.5%, where a body's size goes with its place (a smaller body's
# centroid is lower) and dropping that motion cost a small body's alignment (50 → 88 mm); the bound
# between them keeps the one body family measured as built.
OFF_ITS_PLACE = 4.1
PLACE_DECIDES = 0.5


def check_rigid_modes(rigid_modes: str) -> str:
    """``rigid_modes`` if it is one of :data:`RIGID_MODES`, else StatfitError."""
    if rigid_modes not in RIGID_MODES:
        raise StatfitError(f"unknown --rigid-modes {rigid_modes!r}; choose one of {', '.join(RIGID_MODES)}")
    return rigid_modes


def fitting_model(model: StatModel, rigid_modes: str = "auto", finds_pose: bool = True) -> StatModel:
    """The model a fit uses: ``keep``, the model as given; ``drop``, :func:`without_rigid_motion`;
    ``auto``, without its modes' rigid motion where the fit ``finds_pose`` itself (the pose is then
    the fit's, not the modes') and that motion is more than :data:`MOSTLY_RIGID` of their variance
    (a StatfitWarning says so) and some shape is left, else as given. The fit's mesh is in the
    model's topology either way; the CLI's params project it onto the given model."""
    return fitting_model_and_rule(model, rigid_modes, finds_pose)[0]


@dataclass(eq=False)
class PlaceRule:
    """``auto``'s rule where the alignment decides (:data:`OFF_ITS_PLACE`) for ``model``, whose
    modes less their rigid motion are ``shaped`` (3N, K) (:func:`_less_rigid_motion`): the model
    without that motion, :attr:`rigid_free`, is derived once, at the first fit whose alignment moved
    the model off its place (0.34 s on ICT's head), and shared by the maps fitted together."""

    model: StatModel
    shaped: np.ndarray

    @cached_property
    def rigid_free(self) -> StatModel:
        return _with_modes(self.model, self.shaped)


def fitting_model_and_rule(model: StatModel, rigid_modes: str, finds_pose: bool) -> tuple[StatModel, PlaceRule | None]:
    """:func:`fitting_model`'s model, and the rule by which ``auto`` leaves the modes' rigid motion
    to what a render fit's alignment finds (:data:`OFF_ITS_PLACE`), or None: it applies to a model
    fitted as given whose modes have some rigid motion, at most :data:`PLACE_DECIDES` of their variance."""
    if check_rigid_modes(rigid_modes) == "keep":
        return model, None
    if rigid_modes == "drop":
        return without_rigid_motion(model), None
    if not finds_pose:          # a scan or map in the model's frame: the modes may be all that moves it
        return model, None
    shaped = _less_rigid_motion(model)
    share = _rigid_share(model, shaped)
    if share <= MOSTLY_RIGID or _nothing_left(model, shaped):   # nothing left: the fit has them as given
        return model, PlaceRule(model, shaped) if 0.0 < share <= PLACE_DECIDES else None
    warnings.warn(f"{share:.1%} of the model's modes' variance is rigid motion (a part cut from a larger model?): "
                  "the fit uses its modes without it (--rigid-modes keep: as built)", StatfitWarning, stacklevel=3)
    return _with_modes(model, shaped), None


def rigid_motion_distance(model: StatModel, rotation: np.ndarray, shift: np.ndarray) -> float:
    """How far a rigid move of the model lies outside its modes' own rigid motion: ``rotation``
    (3, 3), and ``shift`` (3,), the template centroid's move in the model's units. The Mahalanobis
    distance (in standard deviations) of the move (shift in RMS radii, rotation vector in radians)
    under the covariance (6, 6) of the modes' least-squares rigid motions; a move in a direction
    the modes do not move the model is far (a floor of 1e-9 of the variance)."""
    from scipy.spatial.transform import Rotation

    centred = model.template - model.template.mean(axis=0)
    radius = float(np.sqrt((centred**2).sum(axis=1).mean()))
    generators = _rigid_fields(model.template) * [radius, radius, radius, 1.0, 1.0, 1.0]   # a radius, a radian
    motions = np.linalg.solve(generators.T @ generators, generators.T @ (model.basis * model.std))   # (6, K)
    covariance = motions @ motions.T
    covariance += 1e-9 * max(float(np.trace(covariance)), np.finfo(float).tiny) * np.eye(6)
    move = np.concatenate([np.asarray(shift, dtype=float) / radius,
                           Rotation.from_matrix(np.asarray(rotation, dtype=float)).as_rotvec()])
    return float(np.sqrt(move @ np.linalg.solve(covariance, move)))


def rigid_motion_share(model: StatModel) -> float:
    """The share of the modes' variance that is small rigid motion of the template (0–1;
    :func:`without_rigid_motion`), from the modes' projection on the template's small rigid motions."""
    total = float((model.std**2).sum())
    motion = (rigid_motion_basis(model.template).T @ model.basis) * model.std        # (6, K)
    return min(float((motion**2).sum()) / total, 1.0) if total > 0 else 0.0


def _rigid_share(model: StatModel, shaped: np.ndarray) -> float:
    total = float((model.std**2).sum())
    return 1.0 - float((shaped**2).sum()) / total if total > 0 else 0.0


def _less_rigid_motion(model: StatModel) -> np.ndarray:
    """(3N, K): the modes (directions times standard deviations) less their least-squares small
    rigid motion of the template (translations, and rotations about its centroid)."""
    rigid = rigid_motion_basis(model.template)
    modes = model.basis * model.std
    return modes - rigid @ (rigid.T @ modes)


def rigid_motion_basis(template: np.ndarray) -> np.ndarray:
    """(3N, 6) orthonormal: the small rigid motions of ``template`` (N, 3) as flattened vertex
    displacements; its first three columns span the translations, the last three the rotations
    about the centroid less their translation part."""
    return np.linalg.qr(_rigid_fields(template))[0]


def _rigid_fields(template: np.ndarray) -> np.ndarray:
    """(3N, 6): the displacements of ``template`` (N, 3) by a unit translation along x, y, z and a
    small rotation of one radian about x, y, z through its centroid."""
    n = len(template)
    centred = template - template.mean(axis=0)
    axes = np.eye(3)
    fields = [np.broadcast_to(axis, (n, 3)) for axis in axes] + [np.cross(axis, centred) for axis in axes]
    return np.stack([field.reshape(-1) for field in fields], axis=1)
