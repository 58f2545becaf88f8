"""Step 6 of the pose search: how well a pose explains the scan, and when no pose is plausible."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from statfit.errors import StatfitError
from statfit.registration.pose.hypotheses import VISIBLE_COSINE, Poses
from statfit.registration.pose.icp import Matcher

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


def check_plausible(matched: float, explained: float, coefficients: np.ndarray, tolerance: float,
                    has_landmarks: bool = True) -> str | None:
    """Refuse a scan that nothing of the model matches, or only a shape far outside the model:
    fewer than MIN_MATCHED of its points near the first modes' best fit; or the best fit with every
    mode needing coefficients beyond IMPLAUSIBLE_RMS on average or IMPLAUSIBLE_COEFFICIENT in one
    mode (measured: a sphere, a plane, a shoulders tube ≥ 3.0 on average and ≥ 9.7 in one mode;
    realistic face scans with clutter ≤ 1.3 and ≤ 4.0) while explaining less than EXPLAINED of the
    points (``explained``, the polished fit's matched share); the refusal's advice names
    --landmarks where the model ``has_landmarks``. Returns a warning for a scan the model
    explains only with such coefficients (a person far outside the model's people), else None."""
    if matched < MIN_MATCHED:
        raise StatfitError(f"the scan does not look like the model anywhere: at best {matched:.0%} of its points lie "
                           f"within {tolerance:.3g} model units of the surface in any pose (need {MIN_MATCHED:.0%}); "
                           "is it a scan of what the model describes?")
    rms, largest = float(np.sqrt(np.mean(coefficients**2))), float(np.abs(coefficients).max())
    if rms <= IMPLAUSIBLE_RMS and largest <= IMPLAUSIBLE_COEFFICIENT:
        return None
    if explained < EXPLAINED:
        raise StatfitError(f"the scan does not look like the model's shape: its best fit needs coefficients of "
                           f"{rms:.1f} standard deviations on average and {largest:.1f} at most, where a scan of what the model "
                           "describes needs about 1 (if it is one, place it with "
                           + ("--landmarks)" if has_landmarks else
                              "--align similarity: this model has no landmarks)"))
    return (f"the scan lies far outside the model's people: its fit needs coefficients of {rms:.1f} standard "
            f"deviations on average and {largest:.1f} at most (about 1 is usual); check the fit")
