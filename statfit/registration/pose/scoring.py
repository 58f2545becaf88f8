"""Step 6 of the pose search: how well a pose explains the scan, and when no pose is plausible."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from statfit.errors import StatfitError
from statfit.registration.pose.hypotheses import VISIBLE_COSINE, Poses
from statfit.registration.pose.icp import Matcher, vertex_normals
from statfit.structures.kdtree import kd_tree

TOLERANCE = 0.05           # truncation of the score, model RMS radii (≈ 5 mm on a head)
POLISH_TOLERANCE = 0.02    # the polished poses' score: a fit with every mode lies this close, clutter farther
IMPLAUSIBLE_RMS = 2.0       # coefficients (std-devs) no scan of a face needs, on average ...
IMPLAUSIBLE_COEFFICIENT = 6.5  # ... or for one mode (a chance of ~1e-10 under the model)
MIN_MATCHED = 0.3          # fewer scan points than this within TOLERANCE: no part of the scan is the model
# ... unless the fit with every mode explains this share of the points (within POLISH_TOLERANCE): then the
# scan is of what the model describes, a person far outside its population (measured: a sphere, a plane,
# a shoulders tube ≤ 0.62; heads of another model family fitted 0.81-0.90, with coefficients up to
# 2.2 on average and 6.6 in one mode; docs/studies.md §17).
EXPLAINED = 0.75
# ... or, clutter lowering that share (hair, neck and shoulders explain nothing), the fit needs at most
# these, the scan supports this share of the fit's surface that faces the scanner and the pose is clear
# (docs/studies.md §40: chosen on cluttered people of four families under each other's models, whose right
# poses this refused under the three real families' models needed ≤ 2.76 on average and ≤ 9.5 in one mode,
# supported ≥ 0.53; of nine kinds of shapes, those that come this near are capsules and half spheres,
# whose poses are all ambiguous).
FAR_RMS = 2.75
FAR_COEFFICIENT = 10.0
SUPPORTED = 0.5
BEYOND_ANY_PERSON = 12.5   # in one mode, however much of the scan the fit explains (people ≤ 11.7; planes ≥ 14.7)
NOTHING_EXPLAINED = 0.1    # the polished fit near fewer of the points: it never fitted (people ≥ 0.29 at clutter 2)
# A fit with plausible coefficients that lies near fewer than HALF_EXPLAINED of the points while the scan
# holds up less than BARELY_SUPPORTED of its facing surface only touches the scan: a plane the settled
# polish bent a head onto (explained 0.32, supported 0.16). People's right poses held up ≥ 0.41 of it, and
# no person the rest of the rule accepts is refused by this (docs/studies.md §40, §41); the face crops and
# half faces tried explained ≥ 0.78.
HALF_EXPLAINED = 0.5
BARELY_SUPPORTED = 0.3


@dataclass(frozen=True)
class ScanCover:
    """The scan as the model's side of a score sees it: a KD-tree of its points (the search's unit
    frame) and the scanner's direction ``facing`` (3,), the scan's mean normal."""

    tree: cKDTree
    facing: np.ndarray


def score_poses(matcher: Matcher, points: np.ndarray, normals: np.ndarray, poses: Poses, tolerance: float = TOLERANCE,
                cover: ScanCover | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Truncated residual (H,) in [0, 1] and matched share (H,) of each pose. With ``cover`` (a model
    of part of a subject, as a face mask is), the residual is averaged with the model's side of it
    (:func:`unsupported_share`): a mask explains about half of a head's scan wherever it lies on the
    head, and only its own surface, which nothing supports off the face, tells where it belongs."""
    local = poses.to_model(points)
    _, _, distance, agree = matcher(local, np.einsum("mi,hij->hmj", normals, poses.rotation))
    inlier = agree & (distance < tolerance)
    capped = np.where(agree, np.minimum(distance / tolerance, 1.0) ** 2, 1.0)
    if cover is None:
        return capped.mean(axis=1), inlier.mean(axis=1)
    return (capped.mean(axis=1) + unsupported_share(matcher, poses, cover, tolerance)) / 2, inlier.mean(axis=1)


def unsupported_share(matcher: Matcher, poses: Poses, cover: ScanCover, tolerance: float) -> np.ndarray:
    """The model's side of the score (H,) in [0, 1]: each of its vertices that faces the scanner in a
    pose at its squared distance to the nearest scan point over ``tolerance``², capped at 1; each
    other vertex (turned away: a scanner cannot have seen it) at the cap."""
    placed = poses.scale[:, None, None] * np.einsum("nj,hij->hni", matcher.vertices, poses.rotation) \
        + poses.translation[:, None]                                                      # (H, N, 3)
    towards_scanner = np.einsum("hji,j->hi", poses.rotation, cover.facing)                  # Rᵀ facing (H, 3)
    seen = np.einsum("ni,hi->hn", matcher.normals, towards_scanner) > VISIBLE_COSINE       # (H, N)
    capped = np.ones(seen.shape)
    # bounded at the cap: a vertex beyond it gets ∞, which the cap makes 1 as its own distance would
    distance, _ = cover.tree.query(placed[seen], distance_upper_bound=tolerance)
    capped[seen] = np.minimum(distance / tolerance, 1.0) ** 2
    return capped.mean(axis=1)


def supported_share(faces: np.ndarray, shape: np.ndarray, points: np.ndarray, facing: np.ndarray,
                    tolerance: float) -> float:
    """The share of ``shape``'s vertices (N, 3; placed in the frame of the scan's ``points`` (M, 3))
    that face the scanner (``facing`` (3,), unit) and have a scan point within ``tolerance``, widened
    to twice the points' median spacing for a sparse scan: how much of the fit the scan holds up,
    which clutter around it does not lower."""
    tree = kd_tree(points)
    spacing = float(np.median(tree.query(points, k=2)[0][:, 1]))
    seen = vertex_normals(faces, shape) @ facing > VISIBLE_COSINE
    if not seen.any():
        return 0.0
    distance, _ = tree.query(shape[seen], distance_upper_bound=max(tolerance, 2 * spacing))
    return float(np.isfinite(distance).mean())


def check_plausible(matched: float, explained: float, coefficients: np.ndarray, tolerance: float,
                    has_landmarks: bool = True, *, supported: float = 0.0, clear: bool = False) -> str | None:
    """Refuse a scan that nothing of the model matches, or only a shape far outside the model:
    fewer than MIN_MATCHED of its points near the first modes' best fit, or fewer than
    NOTHING_EXPLAINED near the fit with every mode (``explained``, the polished fit's matched share);
    or that fit needing coefficients beyond IMPLAUSIBLE_RMS on average or IMPLAUSIBLE_COEFFICIENT in
    one mode (measured: a sphere, a plane, a shoulders tube ≥ 3.0 on average and ≥ 9.7 in one mode;
    realistic face scans with clutter ≤ 1.3 and ≤ 4.0) unless it explains EXPLAINED of the points
    with at most BEYOND_ANY_PERSON in one mode, or its coefficients stay within FAR_RMS and
    FAR_COEFFICIENT, the scan supports at least SUPPORTED of the fit's surface that faces it
    (``supported``, :func:`supported_share`) and the pose is ``clear`` (no other pose scores near it:
    a capsule or a ball fits as well turned any way); docs/studies.md §40. The refusal's advice
    names --landmarks where the model ``has_landmarks``. Returns a warning for a scan the model
    explains only with such coefficients (a person far outside the model's people), else None."""
    if matched < MIN_MATCHED:
        raise StatfitError(f"the scan does not look like the model anywhere: at best {matched:.0%} of its points lie "
                           f"within {tolerance:.3g} model units of the surface in any pose (need {MIN_MATCHED:.0%}); "
                           "is it a scan of what the model describes?")
    if explained < NOTHING_EXPLAINED:
        raise StatfitError(f"the scan does not look like the model anywhere: the model's best fit lies near "
                           f"{explained:.0%} of its points; is it a scan of what the model describes?")
    rms, largest = float(np.sqrt(np.mean(coefficients**2))), float(np.abs(coefficients).max())
    if rms <= IMPLAUSIBLE_RMS and largest <= IMPLAUSIBLE_COEFFICIENT:
        if explained < HALF_EXPLAINED and supported < BARELY_SUPPORTED:
            raise StatfitError(f"the scan does not look like the model anywhere: the model's best fit lies near "
                               f"{explained:.0%} of its points and the scan holds up {supported:.0%} of the fit's "
                               "surface that faces it; is it a scan of what the model describes?")
        return None
    explains = explained >= EXPLAINED and largest <= BEYOND_ANY_PERSON
    held_up = clear and rms <= FAR_RMS and largest <= FAR_COEFFICIENT and supported >= SUPPORTED
    if not (explains or held_up):
        raise StatfitError(f"the scan does not look like the model's shape: its best fit needs coefficients of "
                           f"{rms:.1f} standard deviations on average and {largest:.1f} at most, where a scan of what "
                           "the model describes needs about 1 (if it is one, place it with "
                           + ("--landmarks)" if has_landmarks else
                              "--align similarity: this model has no landmarks)"))
    return (f"the scan lies far outside the model's people: its fit needs coefficients of {rms:.1f} standard "
            f"deviations on average and {largest:.1f} at most (about 1 is usual); check the fit")
