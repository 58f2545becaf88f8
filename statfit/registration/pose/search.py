"""Automatic pose, scale and units: a scan in any orientation, offset and length unit put onto the model.

Plain ICP from one start finds the nearest local fit, and a smooth head has many (upside down,
back to front, turned by 90°). So:

1. **Units.** The scale between scan and model is snapped to the power of ten nearest the ratio of
   their RMS radii (mm, cm, m all differ by one); within a hypothesis the scale stays in
   [1/SCALE_RANGE, SCALE_RANGE] of that (a person's size, not another unit).
2. **Hypotheses.** The 60 rotations of the icosahedral group (every rotation is within ~38° of
   one), each placed so that the side of the model facing the scan's mean normal (the scanner's
   side) sits on the scan's centroid. Only poses that turn the model's face (+z, by the usual
   convention) towards the scanner, give or take 15°, go on: the scan is of a face.
3. **Trimmed point-to-plane ICP**, all hypotheses at once on a subsample of the scan: a point counts
   only where its normal agrees with the surface's (up to sign) and it is not among the farthest.
   After SCREEN_ROUNDS, only the SCREENED best-scoring hypotheses go on.
4. **The best few** (distinct by ≥ DISTINCT_DEGREES) are refined against the mean *and its first
   modes*: ICP alternates with a Gauss–Newton solve for REFINE_MODES coefficients, so a face
   wider or longer than the mean does not pull the pose.
5. **Polish.** The best pose is refined once more against every mode, trimming as the fit does
   (OUTLIER_SIGMAS), on more points: a pose the first modes could not explain is what the fit,
   which cannot turn the model, would keep. Hair would tilt it: the modes bulge the head towards a
   surface 5–9 mm over the scalp. So, for a model with a face (a ``face`` region or landmarks),
   the polish runs three times: on the whole head; then where hair cannot reach — on the face
   alone (around its landmarks, POSE_FACE_RADIUS), or, when the first pass left more than
   1 − CLUTTER_MATCHED of the points unexplained (clutter), on everything but the scalp
   (:func:`statfit.model.statmodel.scalp_triangles`: the face, the ears, the jaw and the sides below the
   hairline, a longer lever for the head's tilt than the face alone); and last on every point
   except those lying :data:`statfit.registration.hair.HAIR_OFFSET` beyond the second pass's scalp and, with
   clutter, those on the scalp.
6. **Score**: a truncated residual — each point's squared distance capped at TOLERANCE², a point
   whose normal disagrees counting as the cap — over the cap: 0 is a perfect fit, 1 nothing
   matched. The runner-up (another pose ≥ DISTINCT_DEGREES away) within AMBIGUITY of the best
   marks the result ambiguous; too few matched points, or a fit that needs implausible
   coefficients (a sphere, a plane), refuse the scan. A scan that already lies on
   the model, in its units, scoring within KEEP_FRAME of the best pose, is left where it is.

Everything runs in the model's unit frame (:class:`statfit.structures.frame.Frame`), so no threshold
depends on units.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from statfit.geometry.align import Similarity, compose
from statfit.geometry.closest import ClosestPointQuery
from statfit.errors import StatfitError
from statfit.structures.frame import Frame
from statfit.core.gauss_newton import fit_coefficients, mode_directions
from statfit.registration.hair import hair_suspects
from statfit.model.statmodel import StatModel, face_triangles, scalp_triangles
from statfit.objectives.scan import ScanObjective
from statfit.structures.scan import Scan

HYPOTHESES = Rotation.create_group("I").as_matrix()   # (60, 3, 3)
SCALE_RANGE = 1.35
SUBSAMPLE = 300
ROUNDS = 15
# Successive halving: after SCREEN_ROUNDS of ICP only the SCREENED best-scoring hypotheses go on to
# the remaining rounds (the ICP of all 60 was a third of the alignment's time).
SCREEN_ROUNDS = 5
SCREENED = 15
KEEP = 0.7                 # fraction of the normal-compatible points kept per ICP round (the nearest)
NORMAL_COSINE = 0.5        # |cos| between scan and surface normals for a point to count (60°)
TOLERANCE = 0.05           # truncation of the score, model RMS radii (≈ 5 mm on a head)
REFINED = 3
REFINE_MODES = 10
REFINE_ROUNDS = 2
REFINE_SUBSAMPLE = 600
POLISH_ITERATIONS = 12
POLISH_SUBSAMPLE = 3000
POLISH_NOISE = 0.01        # the polish's prior (docs/method.md, "Real scans": 0.02 and 0.04 turn better on
                           # ICT and move worse on the embedded head)
POLISH_TOLERANCE = 0.02    # the polished poses' score: a fit with every mode lies this close, clutter farther
DISTINCT_DEGREES = 30.0
# Share of the scan's points the fit with every mode explains (within POLISH_TOLERANCE) below which
# the scan holds clutter: clean ICT study scans ≥ 0.91, scans with hair, neck and shoulders worth 50%
# of the face's points ≤ 0.82 (docs/method.md, "The registration objective").
CLUTTER_MATCHED = 0.87
KEEP_FRAME = 1.05          # the scan as it lies scores within this factor of the best pose: keep it
NEAR_OFFSET = 0.5          # ... and is polished to see whether it does only when the best pose lies this near
                           # (model RMS radii; and within DISTINCT_DEGREES): a second polish costs ~0.4 s
# The face the polish trusts over hair, for a model with landmarks but no face region: this many RMS
# radii around them (ICT: 2.2 cm) — the second pass's region on a clean scan, and the face the hair
# test spares. The fit's face (FACE_RADIUS, 0.5) reaches over the hairline, so hair there tilted the
# face-only pass and escaped the hair test: hair-and-neck scans of the benchmark posed 1.85° off on
# average at 0.5, 1.44° at 0.35, 1.19° at 0.25; clean scans 0.42° and 0.47°. (With clutter, the
# second pass now fits everything but the scalp region instead: 0.58°.)
POSE_FACE_RADIUS = 0.25
LEAD_SUBSAMPLE = 1500      # points of the two polishes that find the face (as good as 3,000 on §16's scans)
AMBIGUITY = 1.15           # runner-up score within this factor of the best: ambiguous
FACING_MIN = -0.25         # cos between the model's face direction (+z) and the scan's mean normal
IMPLAUSIBLE_RMS = 2.0       # coefficients (std-devs) no scan of a face needs, on average ...
IMPLAUSIBLE_COEFFICIENT = 6.5  # ... or for one mode (a chance of ~1e-10 under the model)
MIN_MATCHED = 0.3          # fewer scan points than this within TOLERANCE: no part of the scan is the model


@dataclass(frozen=True)
class PoseEstimate:
    """The model→scan ``transform``; ``score`` (truncated residual, 0 best, 1 worst, after the
    first modes' refinement) of the best pose and ``runner_up`` that of the best pose ≥
    DISTINCT_DEGREES from it; ``matched`` the share of scan points within POLISH_TOLERANCE (with
    agreeing normals) of the polished fit; ``units`` the power of ten
    taken as the scan's unit relative to the model's."""

    transform: Similarity
    score: float
    matched: float
    runner_up: float
    units: float

    @property
    def ambiguous(self) -> bool:
        return self.runner_up <= AMBIGUITY * self.score

    def summary(self) -> dict:
        rotation = Rotation.from_matrix(self.transform.rotation)
        return {"score": round(self.score, 4), "matched": round(self.matched, 4),
                "runner_up": round(self.runner_up, 4), "ambiguous": self.ambiguous, "units_factor": self.units,
                "scale": self.transform.scale, "rotation_deg": np.degrees(rotation.as_rotvec()).round(2).tolist(),
                "translation": self.transform.translation.tolist()}


@dataclass
class _Poses:
    """H similarities x ↦ s R x + t, as arrays: s (H,), R (H, 3, 3), t (H, 3)."""

    scale: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray

    def to_model(self, points: np.ndarray) -> np.ndarray:
        """Points (M, 3) mapped back by each pose: (H, M, 3)."""
        return np.einsum("hmi,hij->hmj", points[None] - self.translation[:, None], self.rotation) \
            / self.scale[:, None, None]

    @classmethod
    def of(cls, pose: Similarity) -> "_Poses":
        """One pose."""
        return cls(np.array([pose.scale]), pose.rotation[None], pose.translation[None])

    def subset(self, indices: np.ndarray) -> "_Poses":
        """The poses at ``indices`` (K,)."""
        return _Poses(self.scale[indices], self.rotation[indices], self.translation[indices])

    def pick(self, index: int) -> Similarity:
        return Similarity(float(self.scale[index]), self.rotation[index], self.translation[index])


class _Matcher:
    """Nearest points and normals on one shape (N, 3) for many scan points in its frame: the
    nearest vertex's tangent plane (a KD-tree query; ICP's classic approximation of the surface,
    within a fraction of the vertex spacing of the true distance)."""

    def __init__(self, faces: np.ndarray, vertices: np.ndarray):
        self.faces = np.asarray(faces)
        self.query = ClosestPointQuery(faces, len(vertices), k=2)
        self.set_shape(vertices)

    def set_shape(self, vertices: np.ndarray) -> None:
        self.vertices = vertices
        self.tree = cKDTree(vertices)
        a, b, c = (vertices[self.faces[:, i]] for i in range(3))
        corner_normals = np.repeat(np.cross(b - a, c - a), 3, axis=0)
        normals = np.stack([np.bincount(self.faces.reshape(-1), corner_normals[:, i], len(vertices))
                            for i in range(3)], axis=1)
        self.normals = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
        self.spacing = float(np.linalg.norm(b - a, axis=1).mean())

    def __call__(self, local: np.ndarray, local_normals: np.ndarray) -> tuple[np.ndarray, ...]:
        """For ``local`` (H, M, 3): nearest vertices and their normals (H, M, 3), distances (H, M)
        (the tangent plane's, plus how far beyond a vertex spacing the point lies sideways) and
        whether the normals agree up to sign (H, M)."""
        _, nearest = self.tree.query(local.reshape(-1, 3))
        nearest = nearest.reshape(local.shape[:2])
        surface, normals = self.vertices[nearest], self.normals[nearest]
        offset = local - surface
        along = (offset * normals).sum(axis=-1)
        sideways = np.sqrt(np.maximum((offset * offset).sum(axis=-1) - along**2, 0))
        distance = np.sqrt(along**2 + np.maximum(sideways - self.spacing, 0) ** 2)
        agree = np.abs((normals * local_normals).sum(axis=-1)) >= NORMAL_COSINE
        return surface, normals, distance, agree


def _icp(matcher: _Matcher, points: np.ndarray, normals: np.ndarray, poses: _Poses, rounds: int,
         scale_bounds: tuple[float, float]) -> _Poses:
    """Trimmed point-to-plane similarity ICP of every pose at once, scale kept within bounds: of the
    points whose normals agree, the nearest KEEP fraction count."""
    for _ in range(rounds):
        local = poses.to_model(points)
        surface, surface_normals, distance, agree = matcher(local, np.einsum("mi,hij->hmj", normals, poses.rotation))
        cut = _row_quantile(distance, agree, KEEP)
        weight = (agree & (distance <= cut[:, None])).astype(np.float64)
        centre = (weight[..., None] * surface).sum(axis=1) / np.maximum(weight.sum(axis=1), 1)[:, None]
        q, p = surface - centre[:, None], local - centre[:, None]
        columns = np.concatenate([np.cross(q, surface_normals), surface_normals,
                                  (surface_normals * q).sum(axis=-1, keepdims=True)], axis=-1)   # (H, M, 7)
        rhs = ((p - q) * surface_normals).sum(axis=-1)
        lhs = np.einsum("hmi,hm,hmj->hij", columns, weight, columns)
        lhs += 1e-9 * np.eye(7) * (np.trace(lhs, axis1=1, axis2=2)[:, None, None] + 1e-12)
        step = np.linalg.solve(lhs, np.einsum("hmi,hm,hm->hi", columns, weight, rhs)[..., None])[..., 0]
        step[weight.sum(axis=1) < 10] = 0.0            # too few matches to say where to go: stay
        step[:, 6] = np.clip(step[:, 6], -0.2, 0.2)    # a linearised scale step is trusted only so far
        step_rotation = Rotation.from_rotvec(step[:, :3]).as_matrix()
        step_scale = np.exp(step[:, 6])
        step_translation = centre + step[:, 3:6] - step_scale[:, None] * np.einsum("hij,hj->hi", step_rotation, centre)
        poses = _Poses(np.clip(poses.scale * step_scale, *scale_bounds),
                       np.einsum("hij,hjk->hik", poses.rotation, step_rotation),
                       poses.scale[:, None] * np.einsum("hij,hj->hi", poses.rotation, step_translation)
                       + poses.translation)
    return poses


def _row_quantile(values: np.ndarray, mask: np.ndarray, q: float) -> np.ndarray:
    """Per row of ``values`` (H, M), the ``q`` quantile of the entries ``mask`` (H, M) keeps, as
    ``np.quantile`` (linear) computes it, or inf for a row keeping 10 or fewer: all rows at once."""
    count = mask.sum(axis=1)
    last = np.maximum(count, 1) - 1
    ordered = np.sort(np.where(mask, values, np.inf), axis=1)
    position = q * last
    low = np.floor(position).astype(np.int64)
    t = position - low
    a = np.take_along_axis(ordered, low[:, None], 1)[:, 0]
    b = np.take_along_axis(ordered, np.minimum(low + 1, last)[:, None], 1)[:, 0]
    with np.errstate(invalid="ignore"):      # inf − inf on rows that keep nothing, masked below
        diff = b - a
        value = np.where(t >= 0.5, b - diff * (1 - t), a + diff * t)   # numpy's own interpolation
    return np.where(count > 10, value, np.inf)


def _score(matcher: _Matcher, points: np.ndarray, normals: np.ndarray, poses: _Poses, tolerance: float = TOLERANCE
           ) -> tuple[np.ndarray, np.ndarray]:
    """Truncated residual (H,) in [0, 1] and matched share (H,) of each pose."""
    local = poses.to_model(points)
    _, _, distance, agree = matcher(local, np.einsum("mi,hij->hmj", normals, poses.rotation))
    inlier = agree & (distance < tolerance)
    capped = np.where(agree, np.minimum(distance / tolerance, 1.0) ** 2, 1.0)
    return capped.mean(axis=1), inlier.mean(axis=1)


def _starts(model_unit: np.ndarray, model_normals: np.ndarray, facing: np.ndarray) -> _Poses:
    """One pose per hypothesis rotation: the model's vertices facing ``facing`` (scan frame)
    centred on the origin (the scan's centroid)."""
    count = len(HYPOTHESES)
    translation = np.empty((count, 3))
    for h, rotation in enumerate(HYPOTHESES):
        visible = model_normals @ (rotation.T @ facing) > 0.3
        translation[h] = -rotation @ model_unit[visible].mean(axis=0)
    return _Poses(np.ones(count), HYPOTHESES.copy(), translation)


def _distinct(poses: _Poses, order: np.ndarray, count: int) -> list[int]:
    """The first ``count`` poses in ``order`` that differ pairwise by ≥ DISTINCT_DEGREES."""
    chosen: list[int] = []
    for index in order:
        if all(_angle(poses.rotation[index], poses.rotation[other]) >= DISTINCT_DEGREES for other in chosen):
            chosen.append(int(index))
        if len(chosen) == count:
            break
    return chosen


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(Rotation.from_matrix(a.T @ b).magnitude()))


def estimate_pose(model: StatModel, scan: Scan, seed: int = 0) -> PoseEstimate:
    """The similarity that puts ``model`` onto ``scan`` (any rotation, offset and power-of-ten
    units), found without landmarks; raises StatfitError when no pose matches enough of the scan."""
    frame = Frame.of(model.template)
    centroid = scan.points.mean(axis=0)
    radius = float(np.sqrt(((scan.points - centroid) ** 2).sum(axis=1).mean()))
    if radius <= 0:
        raise StatfitError("the scan's points all coincide")
    units = float(10.0 ** np.round(np.log10(radius / frame.scale)))
    points = (scan.points - centroid) / (units * frame.scale)
    rng = np.random.default_rng(seed)
    few = rng.choice(len(points), min(SUBSAMPLE, len(points)), replace=False)
    many = rng.choice(len(points), min(REFINE_SUBSAMPLE, len(points)), replace=False)

    mean = frame.to_unit(model.template)
    matcher = _Matcher(model.faces, mean)
    facing = scan.normals.mean(axis=0)
    facing = facing / max(np.linalg.norm(facing), 1e-12)
    bounds = (1 / SCALE_RANGE, SCALE_RANGE)
    poses = _icp(matcher, points[few], scan.normals[few], _starts(mean, matcher.normals, facing), SCREEN_ROUNDS,
                 bounds)
    screened = np.argsort(_score(matcher, points[few], scan.normals[few], poses)[0])[:SCREENED]
    poses = _icp(matcher, points[few], scan.normals[few], poses.subset(screened), ROUNDS - SCREEN_ROUNDS, bounds)
    score, _ = _score(matcher, points[few], scan.normals[few], poses)
    facing_scanner = poses.rotation[:, :, 2] @ facing > FACING_MIN    # the model's +z (its face) towards the scanner
    candidates = _distinct(poses, np.argsort(np.where(facing_scanner, score, np.inf)), REFINED)

    basis_t = torch.as_tensor(np.ascontiguousarray(model.basis[:, :REFINE_MODES].T))
    std = torch.as_tensor(model.std[:REFINE_MODES] / frame.scale)
    refined = [_refine(matcher, mean, basis_t, std, points[many], scan.normals[many], poses.pick(i), bounds)
               for i in candidates]
    best = int(np.argmin([score for _, score, _ in refined]))
    coarse_pose, coarse_score, coarse_matched = refined[best]
    others = [score for index, (pose, score, _) in enumerate(refined)
              if index != best and _angle(pose.rotation, coarse_pose.rotation) >= DISTINCT_DEGREES]
    runner_up = min(others, default=1.0)
    every_mode = _every_mode(model, frame)
    polish = rng.choice(len(points), min(POLISH_SUBSAMPLE, len(points)), replace=False)
    start, hair = coarse_pose, None
    if (face := face_triangles(model, POSE_FACE_RADIUS)) is not None:   # step 5: head, face, all but hair
        lead = polish[:LEAD_SUBSAMPLE]
        start, _, head_matched, _ = _polish(matcher, mean, every_mode, points[lead], scan.normals[lead], start)
        scalp = scalp_triangles(model) if head_matched < CLUTTER_MATCHED else None    # clutter: hair can be there
        start, _, _, face_fit = _polish(matcher, mean, every_mode, points[lead], scan.normals[lead], start,
                                        region=face if scalp is None else ~scalp)
        face_shape = mean + (every_mode @ torch.as_tensor(face_fit)).numpy()
        hair = hair_suspects(matcher.query, torch.as_tensor(face_shape),
                             torch.as_tensor(start.inverse_apply(points[polish])), torch.as_tensor(face),
                             None if scalp is None else torch.as_tensor(scalp))
        hair = None if hair is None else hair.numpy()    # None: not a head under hair, fit every point
    transform, polished_score, matched, coefficients = _polish(matcher, mean, every_mode, points[polish],
                                                               scan.normals[polish], start,
                                                               used=None if hair is None else ~hair)
    in_place = Similarity(1.0, np.eye(3), (frame.center - centroid) / frame.scale)
    if units == 1.0 and _near(in_place, coarse_pose):   # only then can the scan as it lies compete
        _, in_place_score, in_place_matched, in_place_coefficients = _polish(
            matcher, mean, every_mode, points[polish], scan.normals[polish], in_place, move=False)
        if in_place_score <= KEEP_FRAME * polished_score:
            transform, matched, coefficients = in_place, in_place_matched, in_place_coefficients
    _check_plausible(coarse_matched, coefficients, TOLERANCE * frame.scale)
    return PoseEstimate(_to_scan_frame(transform, frame, centroid, units), coarse_score, matched, runner_up, units)


def _near(pose: Similarity, other: Similarity) -> bool:
    """Whether two poses (unit frames) are within DISTINCT_DEGREES and NEAR_OFFSET of each other."""
    return (_angle(pose.rotation, other.rotation) < DISTINCT_DEGREES
            and float(np.linalg.norm(pose.translation - other.translation)) < NEAR_OFFSET)


def _to_scan_frame(transform: Similarity, frame: Frame, centroid: np.ndarray, units: float) -> Similarity:
    """A pose between unit frames (model: u = (x − centre)/scale; scan: q = (p − centroid)/(units·scale))
    as the model → scan similarity, written out so that the scale is the unit's exactly (a
    composition would round it)."""
    return Similarity(units * transform.scale, transform.rotation,
                      centroid + units * frame.scale * transform.translation
                      - units * transform.scale * transform.rotation @ frame.center)


def _to_unit_frames(transform: Similarity, frame: Frame, centroid: np.ndarray, units: float) -> Similarity:
    """The inverse of :func:`_to_scan_frame`: a model → scan similarity as a pose between the unit frames."""
    return Similarity(transform.scale / units, transform.rotation,
                      (transform.scale * transform.rotation @ frame.center + transform.translation - centroid)
                      / (units * frame.scale))


def refine_pose(model: StatModel, scan: Scan, start: Similarity, seed: int = 0) -> PoseEstimate:
    """``start`` (model → scan, e.g. placed by landmarks) polished like :func:`estimate_pose`'s
    best pose: a rigid pose and every coefficient by Gauss–Newton on the scan, the scale snapped to
    the power of ten nearest ``start``'s (the person's size is the modes' to explain). Landmarks on
    part of a face tilt their similarity by degrees and scale it by ±10%, which no fit of the
    model's modes can undo (docs/studies.md §15: half a face, 10° and 20 mm held-out error). The
    estimate's ``score`` is the polished pose's and ``runner_up`` 1 (no other pose is searched)."""
    frame = Frame.of(model.template)
    centroid = scan.points.mean(axis=0)
    units = float(10.0 ** np.round(np.log10(start.scale)))
    points = (scan.points - centroid) / (units * frame.scale)
    in_units = _to_unit_frames(start, frame, centroid, units)
    mean = frame.to_unit(model.template)
    rng = np.random.default_rng(seed)
    polish = rng.choice(len(points), min(POLISH_SUBSAMPLE, len(points)), replace=False)
    transform, score, matched, _ = _polish(_Matcher(model.faces, mean), mean, _every_mode(model, frame), points[polish],
                                           scan.normals[polish], in_units)
    return PoseEstimate(_to_scan_frame(transform, frame, centroid, units), score, matched, 1.0, units)


def _check_plausible(matched: float, coefficients: np.ndarray, tolerance: float) -> None:
    """Refuse a scan that nothing of the model matches, or only a shape far outside the model:
    fewer than MIN_MATCHED of its points near the first modes' best fit, or the best fit with every
    mode needing coefficients beyond IMPLAUSIBLE_RMS on average or IMPLAUSIBLE_COEFFICIENT in one
    mode (measured: a sphere, a plane, a shoulders tube ≥ 3.0 on average and ≥ 9.7 in one mode;
    realistic face scans with clutter ≤ 1.3 and ≤ 4.0)."""
    if matched < MIN_MATCHED:
        raise StatfitError(f"the scan does not look like the model anywhere: at best {matched:.0%} of its points lie "
                           f"within {tolerance:.3g} model units of the surface in any pose (need {MIN_MATCHED:.0%}); "
                           "is it a scan of what the model describes?")
    rms, largest = float(np.sqrt(np.mean(coefficients**2))), float(np.abs(coefficients).max())
    if rms > IMPLAUSIBLE_RMS or largest > IMPLAUSIBLE_COEFFICIENT:
        raise StatfitError(f"the scan does not look like the model's shape: its best fit needs coefficients of "
                           f"{rms:.1f} standard deviations on average and {largest:.1f} at most, where a scan of what the model "
                           "describes needs about 1 (if it is one, place it with --landmarks)")


def _refine(matcher: _Matcher, mean: np.ndarray, basis_t: torch.Tensor, std: torch.Tensor, points: np.ndarray,
            normals: np.ndarray, start: Similarity, bounds: tuple[float, float]) -> tuple[Similarity, float, float]:
    """``start`` refined against the mean plus its first modes (``basis_t`` (K, 3N) orthonormal,
    ``std`` (K,) in the unit frame): trimmed ICP and a Gauss–Newton coefficient solve, alternated.
    Returns the pose (model unit frame → scan unit frame), its score and matched share, scored on
    the shape fitted."""
    poses = _Poses.of(start)
    shape = mean
    for _ in range(REFINE_ROUNDS):
        poses = _icp(matcher, points, normals, poses, ROUNDS // 2, bounds)
        local = torch.as_tensor(poses.to_model(points)[0])
        objective = ScanObjective(local, matcher.query, trim=1 - KEEP)
        fitted = fit_coefficients(torch.as_tensor(mean), basis_t, std, objective, torch.as_tensor(shape), 8,
                                  noise=0.05, levels=1)
        shape = fitted.vertices.numpy()
        matcher.set_shape(shape)
    score, matched = _score(matcher, points, normals, poses)
    matcher.set_shape(mean)
    return poses.pick(0), float(score[0]), float(matched[0])


def _polish(matcher: _Matcher, mean: np.ndarray, directions: torch.Tensor, points: np.ndarray,
            normals: np.ndarray, start: Similarity, move: bool = True, region: np.ndarray | None = None,
            used: np.ndarray | None = None) -> tuple[Similarity, float, float, np.ndarray]:
    """Gauss–Newton on a rigid pose and every coefficient at once (``directions`` (N, 3, K): the
    modes times their standard deviations, :func:`_every_mode`): the fit's own robust
    point-to-plane residuals, a Gaussian prior on the coefficients only, the pose updated by a small
    rigid motion of the scan points each step. The scale is the units' (``start``'s scale is
    dropped, keeping the scan's centroid in place): a person's size is the model's to explain, by
    its modes and under its prior; a free scale would trade against them at no cost. ``move`` False
    holds the pose; ``region`` (F,) bool: only points attached to these
    triangles are fitted; ``used`` (M,) bool: only these points are fitted (every point is scored).
    Returns the pose (model unit frame → scan unit frame), its score (POLISH_TOLERANCE), matched
    share and the coefficients (K,) in standard deviations."""
    middle = start.inverse_apply(points).mean(axis=0)
    start = Similarity(1.0, start.rotation, start.apply(middle) - start.rotation @ middle)
    k = directions.shape[-1]
    coefficients = torch.zeros(k, dtype=torch.float64)
    pose, mean_t = start, torch.as_tensor(mean)
    fitted, fitted_normals = (points, normals) if used is None else (points[used], normals[used])
    region_faces = None if region is None else torch.as_tensor(region)
    for _ in range(POLISH_ITERATIONS):
        local = torch.as_tensor(pose.inverse_apply(fitted))
        objective = ScanObjective(local, matcher.query, trim=0.05, normals=torch.as_tensor(fitted_normals @ pose.rotation),
                                  clutter=True, region_faces=region_faces)
        x = mean_t + directions @ coefficients
        objective.refresh(x)
        if objective.kept < 10:     # nothing left to say where to go (e.g. no point on the region): stay
            break
        residuals = objective.residuals(x)
        count = max(residuals.numel(), 1)
        jacobian = objective.jacobian(directions)
        centre = local.mean(dim=0)
        if move:
            jacobian = torch.cat([jacobian, objective.pose_jacobian(centre)[:, :6]], dim=1)
        prior = torch.zeros(jacobian.shape[1], dtype=torch.float64)
        prior[:k] = POLISH_NOISE**2 / count
        lhs = jacobian.T @ jacobian / count
        lhs = lhs + torch.diag(prior + 1e-12 * float(lhs.diagonal().mean()))
        rhs = jacobian.T @ residuals / count
        rhs[:k] += prior[:k] * coefficients
        step = -torch.linalg.solve(lhs, rhs).numpy()
        coefficients = coefficients + torch.as_tensor(step[:k])
        if move:
            rotation = Rotation.from_rotvec(step[k:k + 3]).as_matrix()
            c = centre.numpy()
            moved = c + step[k + 3:] - rotation @ c          # the scan points' motion: p ↦ R p + moved
            pose = compose(pose, Similarity(1.0, rotation.T, -rotation.T @ moved))
    shape = (mean_t + directions @ coefficients).numpy()
    matcher.set_shape(shape)
    poses = _Poses.of(pose)
    score, matched = _score(matcher, points, normals, poses, POLISH_TOLERANCE)
    matcher.set_shape(mean)
    return pose, float(score[0]), float(matched[0]), coefficients.numpy()


def _every_mode(model: StatModel, frame: Frame) -> torch.Tensor:
    """Every mode scaled by its standard deviation in the model's unit frame, vertex-major: (N, 3, K)."""
    basis_t = torch.as_tensor(np.ascontiguousarray(model.basis.T))
    return mode_directions(basis_t, torch.as_tensor(model.std / frame.scale))
