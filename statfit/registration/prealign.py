"""Where a scan lies against the model before any fit: the scan checked, and the model→scan
similarity found (automatic pose search, landmarks, ICP) or taken as given."""
from __future__ import annotations

import numpy as np

from statfit.errors import StatfitError
from statfit.geometry.align import Similarity, icp, initial_guess, umeyama
from statfit.model.statmodel import StatModel
from statfit.registration.pose.search import estimate_pose, refine_pose
from statfit.structures.frame import UNIT_MISMATCH_FACTOR
from statfit.structures.kdtree import kd_tree
from statfit.structures.scan import Scan

ALIGNMENTS = ("auto", "none", "rigid", "similarity")
# No scan in any length unit (metres to micrometres) has coordinates beyond this.
IMPLAUSIBLE_COORDINATE = 1e9
ROBUST_ALIGNMENT_ROUNDS = 10
# Landmarks are marked on the scan: their median distance to its nearest point beyond this many of the
# scan's RMS radii (a head's: ~4 cm) says they are in other units or another frame.
LANDMARK_REACH = 0.5


def check_scan(points: np.ndarray, source: str = "scan") -> np.ndarray:
    """Validate an (M, 3) point array: enough points, all finite."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise StatfitError(f"{source}: expected points of shape (M, 3), got {points.shape}")
    if len(points) == 0:
        raise StatfitError(f"{source} has no points")
    if not np.isfinite(points).all():
        bad = int((~np.isfinite(points)).any(axis=1).sum())
        raise StatfitError(f"{source} has NaN or infinite coordinates ({bad} {'point' if bad == 1 else 'points'})")
    if len(points) < 10:
        raise StatfitError(f"{source} has only {len(points)} {'point' if len(points) == 1 else 'points'}; need at least 10")
    largest = float(np.abs(points).max())
    if largest > IMPLAUSIBLE_COORDINATE:
        raise StatfitError(f"{source} has coordinates as large as {largest:.3g}: not a scan in any length unit "
                           "(a damaged file?)")
    spread = points - points.mean(axis=0)
    widths = np.sqrt(np.clip(np.linalg.eigvalsh(spread.T @ spread), 0.0, None))    # ascending; a 3 × 3 solve
    if widths[2] > 0 and widths[1] <= 1e-6 * widths[2]:
        raise StatfitError(f"{source}'s points lie on one line: there is no surface to fit")
    return points


def present_landmarks(model: StatModel, landmarks: np.ndarray) -> np.ndarray:
    """(L,) bool: the scan's landmarks given (not NaN), after checking the count against the model's."""
    if model.landmarks is None:
        raise StatfitError(f"the model {model.source} has no landmarks, so --landmarks cannot be used")
    landmarks = np.asarray(landmarks, dtype=np.float64)
    if landmarks.shape != (model.landmarks.size, 3):
        raise StatfitError(f"expected {model.landmarks.size} landmarks (one x y z row per model landmark, NaN "
                           f"for a missing one), got an array of shape {landmarks.shape}")
    present = np.isfinite(landmarks).all(axis=1)
    source = model.template[model.landmarks[present]]
    if present.sum() < 3 or np.linalg.matrix_rank(source - source.mean(axis=0), tol=1e-9 * np.ptp(source)) < 2:
        raise StatfitError(f"--landmarks needs at least 3 present, non-collinear landmarks; got {int(present.sum())}")
    return present


def check_scan_landmarks(points: np.ndarray, landmarks: np.ndarray, present: np.ndarray) -> None:
    """Refuse the scan's ``present`` (L,) ``landmarks`` (L, 3) where no pose can come of them: all
    on one line (or one point), or, by their median, farther than LANDMARK_REACH of the scan's
    ``points`` (M, 3) RMS radius from its nearest point (other units, or another scan's frame)."""
    target = landmarks[present]
    spread = target - target.mean(axis=0)
    if np.linalg.matrix_rank(spread, tol=1e-9 * float(np.abs(spread).max(initial=0.0))) < 2:
        raise StatfitError("the scan's landmarks lie on one line (or coincide): no pose can be read from them")
    centred = points - points.mean(axis=0)
    radius = float(np.sqrt(np.square(centred).sum(axis=1).mean()))
    distance = float(np.median(kd_tree(points).query(target)[0]))
    if distance > LANDMARK_REACH * radius:
        raise StatfitError(f"the scan's landmarks lie {distance / radius:.3g} of the scan's radius from its points "
                           "(median): are they in the scan's units and frame?")


def landmark_alignment(model: StatModel, landmarks: np.ndarray) -> Similarity:
    """The similarity (scale, rotation, translation) that best maps the model's landmark vertices
    onto the scan's ``landmarks`` (L, 3), in the model's landmark order; NaN rows are missing.
    Robust to a few misplaced landmarks: iteratively reweighted (Geman–McClure, scale from the
    median residual), so a landmark far from where the others put it stops counting."""
    landmarks = np.asarray(landmarks, dtype=np.float64)
    present = present_landmarks(model, landmarks)
    source, target = model.template[model.landmarks[present]], landmarks[present]
    transform = umeyama(source, target, with_scale=True)
    floor = 1e-3 * float(np.linalg.norm(np.ptp(target, axis=0)))
    for _ in range(ROBUST_ALIGNMENT_ROUNDS):
        residual2 = np.square(transform.apply(source) - target).sum(axis=1)
        s2 = max(1.4826 * float(np.sqrt(np.median(residual2))), floor) ** 2
        transform = umeyama(source, target, with_scale=True, weights=(s2 / (s2 + residual2)) ** 2)
    return transform


def prealign(model: StatModel, scan: Scan, align: str, landmarks: np.ndarray | None = None, seed: int = 0,
             threads: int | None = None) -> tuple[Similarity, dict | None, np.ndarray | None]:
    """The model→scan transform for ``align`` in auto|none|rigid|similarity, and for auto the
    pose search's report (:mod:`statfit.registration.pose.search`) and the polished fit's coefficients
    (K,) (None otherwise); checks units first. With ``landmarks`` (L, 3), the landmark similarity is
    the start: with align auto polished on the scan (:func:`statfit.registration.pose.search.refine_pose`,
    whose report is returned), with none the result. ``threads``: the most the pose search may run
    on (None: the cores this process may use)."""
    if align not in ALIGNMENTS:
        raise StatfitError(f"unknown alignment {align!r}; choose one of {', '.join(ALIGNMENTS)}")
    points = scan.points
    if landmarks is not None:
        check_scan_landmarks(points, np.asarray(landmarks, dtype=np.float64), present_landmarks(model, landmarks))
        start = landmark_alignment(model, landmarks)
        if align == "auto":
            estimate = refine_pose(model, scan, start, seed)
            return estimate.transform, {**estimate.summary(), "from_landmarks": True}, estimate.coefficients
        return (start if align == "none" else icp(model.template, model.faces, points,
                                                  align == "similarity", start=start)), None, None
    if align == "auto":
        estimate = estimate_pose(model, scan, seed, threads)
        return estimate.transform, estimate.summary(), estimate.coefficients
    ratio = np.linalg.norm(np.ptp(points, axis=0)) / np.linalg.norm(np.ptp(model.surface_template, axis=0))
    if align != "similarity" and not 1 / UNIT_MISMATCH_FACTOR < ratio < UNIT_MISMATCH_FACTOR:
        raise StatfitError(f"the scan is {ratio:.3g} times the model's size: are they in different units? "
                           "Rescale one, or use --align auto")
    if align == "none":
        return Similarity(), None, None
    with_scale = align == "similarity"
    start = initial_guess(model.surface_template, points, with_scale)
    if not with_scale and np.linalg.norm(start.translation) < model.frame.scale:
        start = Similarity()
    aligned = icp(model.template, model.faces, points, with_scale, start=start)
    if with_scale and not 1 / UNIT_MISMATCH_FACTOR < aligned.scale / start.scale < UNIT_MISMATCH_FACTOR:
        raise StatfitError(f"the similarity alignment ran away (its scale {aligned.scale / start.scale:.3g} times the "
                           "one the extents give): use --align auto or --landmarks")
    return aligned, None, None
