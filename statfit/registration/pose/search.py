"""Automatic pose, scale and units: a scan in any orientation, offset and length unit put onto the model.

Plain ICP from one start finds the nearest local fit, and a smooth head has many (upside down,
back to front, turned by 90°). So:

1. **Units.** The scale between scan and model is snapped to the power of ten nearest the ratio of
   their RMS radii (mm, cm, m all differ by one); within a hypothesis the scale stays in
   [1/SCALE_RANGE, SCALE_RANGE] of that (a person's size, not another unit). A scan in inches is
   placed only by landmarks (:func:`landmark_units`): a partial metric scan's size over the model's
   reaches as far from a power of ten as an inch scan's (docs/studies.md §39).
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
5. **Polish.** Each refined pose is refined once more against every mode at the units' scale,
   trimming as the fit does (OUTLIER_SIGMAS), on more points; the refinement's best goes on unless
   another polishes POLISHED_SWITCH times better: a pose the first modes could not explain is what
   the fit, which cannot turn the model, would keep, and the refinement's free scale can stretch a
   model over what it does not describe (a face mask over a head scan's side scored 0.64 there
   against 0.73 where it belongs; polished, 0.76 against 0.55). Hair would tilt it: the modes
   bulge the head towards a surface 5–9 mm over the scalp. So, for a model with a face (a ``face``
   region or landmarks), the polish runs three times: on the whole head; then where hair cannot reach — on the face
   alone (around its landmarks, POSE_FACE_RADIUS), or, when the first pass left more than
   1 − CLUTTER_MATCHED of the points unexplained (clutter), on everything but the scalp
   (:func:`statfit.model.statmodel.scalp_triangles`: the face, the ears, the jaw and the sides below the
   hairline, a longer lever for the head's tilt than the face alone); and last on every point
   except those lying :data:`statfit.registration.hair.HAIR_OFFSET` beyond the second pass's scalp and, with
   clutter, those on the scalp.
6. **Score** (the refinement's; the polish's where it overruled): a truncated residual — each
   point's squared distance capped at TOLERANCE², a point whose normal disagrees counting as the
   cap — over the cap: 0 is a perfect fit, 1 nothing
   matched. A model of part of a subject (a face mask: its surface faces one way,
   :func:`statfit.geometry.metrics.of_part_of_a_subject`) is screened and its candidates for step 4
   chosen by a score from both sides: the scan's points on the model and the model's vertices
   facing the scanner on the scan, since a mask explains about half of a head's scan wherever it
   lies (docs/studies.md §37). The runner-up (another pose ≥ DISTINCT_DEGREES away) within
   AMBIGUITY of the best marks the result ambiguous; too few matched points, or a fit that needs
   implausible coefficients (a sphere, a plane), refuse the scan. A scan that already lies on
   the model, in its units, scoring within KEEP_FRAME of the best pose, is left where it is.
7. **A second look.** Where the pose found leaves doubt (the scan would be refused, the pose is
   ambiguous, or its fit needs more than DOUBTFUL_RMS standard deviations on average), steps 2–5
   run again from a second grid, the group turned between its rotations, and step 6 chooses among
   both grids' candidates: a model whose mean stands poorly for its people has narrow ICP basins
   (docs/studies.md §44). A scan without doubt pays nothing for it.

Everything runs in the model's unit frame (:class:`statfit.structures.frame.Frame`), so no threshold
depends on units.
"""
from __future__ import annotations

import copy
import warnings
from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from statfit.core.threads import map_in_threads, task_threads
from statfit.errors import StatfitError, StatfitWarning
from statfit.geometry.align import Similarity
from statfit.geometry.metrics import of_part_of_a_subject
from statfit.model.statmodel import StatModel, face_triangles, scalp_triangles
from statfit.registration.hair import hair_suspects
from statfit.registration.pose.frames import landmark_units, to_scan_frame, to_unit_frames
from statfit.registration.pose.hypotheses import (DISTINCT_DEGREES, HYPOTHESES, SECOND_HYPOTHESES, angle_between,
                                                   distinct_poses, hypothesis_starts)
from statfit.registration.pose.icp import Matcher, trimmed_icp
from statfit.registration.pose.refinement import ROUNDS, polish_pose, refine_with_first_modes, scaled_modes
from statfit.registration.pose.scoring import (TOLERANCE, ScanCover, check_plausible, score_poses,
                                                supported_share)
from statfit.structures.kdtree import kd_tree
from statfit.structures.scan import Scan

SCALE_RANGE = 1.35
SUBSAMPLE = 300
# Successive halving: after SCREEN_ROUNDS of ICP only the SCREENED best-scoring hypotheses go on to
# the remaining rounds (the ICP of all 60 was a third of the alignment's time).
SCREEN_ROUNDS = 5
SCREENED = 15
REFINED = 3
REFINE_MODES = 10
REFINE_SUBSAMPLE = 600
POLISH_SUBSAMPLE = 3000
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
# The refinement's best pose gives way to another only where that one polishes this much better: poses
# far apart often polish to within a few per cent of each other (a half face, another family's model),
# and such a near tie is no ground to move. (1.25: the face cut of the embedded head on its own head
# scan 1.47; §17's cross-family half scans whose choice flipped: 1.01-1.36; docs/studies.md §33.)
POLISHED_SWITCH = 1.25
AMBIGUITY = 1.15           # runner-up score within this factor of the best: ambiguous
FACING_MIN = -0.25         # cos between the model's face direction (+z) and the scan's mean normal
# Step 7's doubt: a fit needing more than this on average (standard deviations; a model's own people need
# about 1, and 0.6-0.9 from a one-sided scan) sends the search to its second grid (docs/studies.md §44).
DOUBTFUL_RMS = 1.0


@dataclass(frozen=True)
class PoseEstimate:
    """The model→scan ``transform``; ``score`` (truncated residual, 0 best, 1 worst, after the
    first modes' refinement) of the best pose and ``runner_up`` that of the best pose ≥
    DISTINCT_DEGREES from it; ``matched`` the share of scan points within POLISH_TOLERANCE (with
    agreeing normals) of the polished fit; ``units`` the scan's unit relative to the model's (a
    power of ten; with landmarks, or one over INCH: inches against a metric model); ``coefficients``
    (K,) the polished fit's shape, in standard deviations of the model's modes."""

    transform: Similarity
    score: float
    matched: float
    runner_up: float
    units: float
    coefficients: np.ndarray

    @property
    def ambiguous(self) -> bool:
        return self.runner_up <= AMBIGUITY * self.score

    def summary(self) -> dict:
        rotation = Rotation.from_matrix(self.transform.rotation)
        return {"score": round(self.score, 4), "matched": round(self.matched, 4),
                "runner_up": round(self.runner_up, 4), "ambiguous": self.ambiguous, "units_factor": self.units,
                "scale": self.transform.scale, "rotation_deg": np.degrees(rotation.as_rotvec()).round(2).tolist(),
                "translation": self.transform.translation.tolist()}


def estimate_pose(model: StatModel, scan: Scan, seed: int = 0, threads: int | None = None) -> PoseEstimate:
    """The similarity that puts ``model`` onto ``scan`` (any rotation, offset and power-of-ten
    units), found without landmarks; raises StatfitError when no pose matches enough of the scan.
    ``threads``: the most threads it may run on (None: the cores this process may use).

    Step 7: where the pose found leaves doubt — the scan would be refused, the pose is ambiguous, or
    its fit needs coefficients beyond DOUBTFUL_RMS on average (more than the model's typical person) —
    the search looks again from SECOND_HYPOTHESES (the icosahedral group turned halfway between its
    rotations), and the choice is made again among both searches' candidates (docs/studies.md §44).
    A pose the first search found plausible stays where the second look's choice would be refused."""
    search = Search.of(model, scan, seed, threads)
    found = search.candidates(HYPOTHESES)
    try:
        first = search.choose(found)
    except StatfitError:
        first = None
    if first is not None and not doubtful(first[0]):
        estimate, warning = first
    else:
        try:
            estimate, warning = search.choose(found + search.candidates(SECOND_HYPOTHESES))
        except StatfitError:
            if first is None:
                raise
            estimate, warning = first       # the second look's choice refused: the first's plausible pose stays
    if warning is not None:
        warnings.warn(warning, StatfitWarning, stacklevel=2)
    return estimate


def doubtful(estimate: PoseEstimate) -> bool:
    """Whether a plausible pose leaves doubt enough for step 7's second look: it is ambiguous, or its
    fit needs more than DOUBTFUL_RMS standard deviations a mode on average."""
    return estimate.ambiguous or float(np.sqrt(np.mean(estimate.coefficients**2))) > DOUBTFUL_RMS


Refined = tuple[Similarity, float, float]                    # pose, score, matched share
Polished = tuple[Similarity, float, float, np.ndarray]       # pose, score, matched share, coefficients (K,)


@dataclass(frozen=True)
class Search:
    """What every candidate pose of one search shares: the model (its mean ``mean`` (N, 3), modes and
    ``matcher``) and the scan (``points``, ``normals`` (M, 3)) in their unit frames, the scan's
    ``centroid`` and ``units``, the subsamples each step uses (index arrays) and the scanner's
    direction ``facing`` (3,)."""

    model: StatModel
    centroid: np.ndarray
    units: float
    points: np.ndarray
    normals: np.ndarray
    few: np.ndarray
    many: np.ndarray
    polish: np.ndarray
    mean: np.ndarray
    matcher: Matcher
    facing: np.ndarray
    cover: ScanCover | None
    every_mode: torch.Tensor
    threads: int | None
    finished: dict[int, tuple] = field(default_factory=dict, compare=False, repr=False)   # finish's, by candidate

    @classmethod
    def of(cls, model: StatModel, scan: Scan, seed: int, threads: int | None) -> "Search":
        frame = model.frame
        centroid = scan.points.mean(axis=0)
        radius = float(np.sqrt(((scan.points - centroid) ** 2).sum(axis=1).mean()))
        if radius <= 0:
            raise StatfitError("the scan's points all coincide")
        units = float(10.0 ** np.round(np.log10(radius / frame.scale)))
        points = (scan.points - centroid) / (units * frame.scale)
        rng = np.random.default_rng(seed)
        few = rng.choice(len(points), min(SUBSAMPLE, len(points)), replace=False)
        many = rng.choice(len(points), min(REFINE_SUBSAMPLE, len(points)), replace=False)
        polish = rng.choice(len(points), min(POLISH_SUBSAMPLE, len(points)), replace=False)
        mean = frame.to_unit(model.template)
        facing = scan.normals.mean(axis=0)
        facing = facing / max(np.linalg.norm(facing), 1e-12)
        # a model of part of a subject (a face mask) is scored from both sides: the scan's and its own
        cover = ScanCover(kd_tree(points), facing) if of_part_of_a_subject(mean, model.faces) else None
        return cls(model, centroid, units, points, scan.normals, few, many, polish, mean, Matcher(model.faces, mean),
                   facing, cover, scaled_modes(model, frame), threads)

    def candidates(self, rotations: np.ndarray) -> list[tuple[Refined, Polished]]:
        """Steps 2–5's first pass from one start per rotation of ``rotations`` (H, 3, 3): the REFINED
        best distinct poses, each refined with the first modes and polished with every mode."""
        few_points, few_normals = self.points[self.few], self.normals[self.few]
        bounds = (1 / SCALE_RANGE, SCALE_RANGE)
        poses = trimmed_icp(self.matcher, few_points, few_normals,
                            hypothesis_starts(self.mean, self.matcher.normals, self.facing, rotations),
                            SCREEN_ROUNDS, bounds)
        score = score_poses(self.matcher, few_points, few_normals, poses, cover=self.cover)[0]
        poses = trimmed_icp(self.matcher, few_points, few_normals, poses.subset(np.argsort(score)[:SCREENED]),
                            ROUNDS - SCREEN_ROUNDS, bounds)
        score, _ = score_poses(self.matcher, few_points, few_normals, poses, cover=self.cover)
        facing_scanner = poses.rotation[:, :, 2] @ self.facing > FACING_MIN    # the model's +z (its face) to it
        chosen = distinct_poses(poses, np.argsort(np.where(facing_scanner, score, np.inf)), REFINED)
        frame = self.model.frame
        basis_t = torch.as_tensor(np.ascontiguousarray(self.model.basis[:, :REFINE_MODES].T))
        std = torch.as_tensor(self.model.std[:REFINE_MODES] / frame.scale)
        lead = self.polish[:LEAD_SUBSAMPLE]

        def refine_and_polish(candidate: int) -> tuple[Refined, Polished]:
            """A candidate refined, then polished at the units' scale with every mode (step 5's first
            pass): the refinement's free scale can stretch a model over what it does not describe (a
            face mask over a head scan's sides) and score better there than where it belongs. On a
            matcher of its own (a copy: its shape is this candidate's to change)."""
            own = copy.copy(self.matcher)
            refined = refine_with_first_modes(own, self.mean, basis_t, std, self.points[self.many],
                                              self.normals[self.many], poses.pick(candidate), bounds)
            return refined, polish_pose(own, self.mean, self.every_mode, self.points[lead], self.normals[lead],
                                        refined[0])

        # The candidates are independent: each on a thread of its own where there are cores for it.
        return map_in_threads(refine_and_polish, chosen, task_threads(len(chosen), self.threads))

    def choose(self, found: list[tuple[Refined, Polished]]) -> tuple[PoseEstimate, str | None]:
        """The best of the candidates ``found`` (steps 5 and 6), polished on the face and without hair,
        and the warning for a scan it explains only with far coefficients; raises StatfitError where
        no pose is plausible. Leaves the matcher as it found it."""
        refined, leads = zip(*found)
        best = int(np.argmin([score for _, score, _ in refined]))
        polished = int(np.argmin([score for _, score, _, _ in leads]))
        # The deciding scores: the refinement's, or the polish's where it overrules a near tie's keeper.
        deciding = [score for _, score, _ in refined]
        if leads[best][1] > POLISHED_SWITCH * leads[polished][1]:
            best, deciding = polished, [score for _, score, _, _ in leads]
        coarse_pose, coarse_score = refined[best][0], deciding[best]
        coarse_matched = max(matched for _, _, matched in refined)      # "at best, in any pose": for the refusal
        others = [deciding[index] for index, (pose, _, _) in enumerate(refined)
                  if index != best and angle_between(pose.rotation, coarse_pose.rotation) >= DISTINCT_DEGREES]
        runner_up = min(others, default=1.0)
        # a second look that keeps the first search's best candidate finds it finished already
        key = id(found[best])
        if key not in self.finished:
            self.finished[key] = self.finish(*found[best])
        transform, matched, coefficients, supported = self.finished[key]
        warning = check_plausible(coarse_matched, matched, coefficients, TOLERANCE * self.model.frame.scale,
                                  self.model.landmarks is not None, supported=supported,
                                  clear=runner_up > AMBIGUITY * coarse_score)
        return PoseEstimate(to_scan_frame(transform, self.model.frame, self.centroid, self.units), coarse_score,
                            matched, runner_up, self.units, coefficients), warning

    def finish(self, refined: Refined, lead: Polished) -> tuple[Similarity, float, np.ndarray, float]:
        """The chosen candidate's last polishes (step 5: on the face, then without hair) and whether the
        scan as it lies does as well: its pose, matched share, coefficients (K,) and the share of its
        fit's facing surface the scan supports."""
        model, frame, matcher, mean = self.model, self.model.frame, self.matcher, self.mean
        points, normals, polish = self.points, self.normals, self.polish
        start, hair = refined[0], None
        if (face := face_triangles(model, POSE_FACE_RADIUS)) is not None:   # step 5: head, face, all but hair
            start, _, head_matched, _ = lead
            scalp = scalp_triangles(model) if head_matched < CLUTTER_MATCHED else None    # clutter: hair can be there
            lead_points = polish[:LEAD_SUBSAMPLE]
            start, _, _, face_fit = polish_pose(matcher, mean, self.every_mode, points[lead_points],
                                                normals[lead_points], start,
                                                region=face if scalp is None else ~scalp, settle=True)
            face_shape = mean + (self.every_mode @ torch.as_tensor(face_fit)).numpy()
            hair = hair_suspects(matcher.query, torch.as_tensor(face_shape),
                                 torch.as_tensor(start.inverse_apply(points[polish])), torch.as_tensor(face),
                                 None if scalp is None else torch.as_tensor(scalp))
            hair = None if hair is None else hair.numpy()    # None: not a head under hair, fit every point
        transform, polished_score, matched, coefficients = polish_pose(
            matcher, mean, self.every_mode, points[polish], normals[polish], start,
            used=None if hair is None else ~hair, settle=True)
        in_place = Similarity(1.0, np.eye(3), (frame.center - self.centroid) / frame.scale)
        if self.units == 1.0 and near(in_place, refined[0]):   # only then can the scan as it lies compete
            _, in_place_score, in_place_matched, in_place_coefficients = polish_pose(
                matcher, mean, self.every_mode, points[polish], normals[polish], in_place, move=False)
            if in_place_score <= KEEP_FRAME * polished_score:
                transform, matched, coefficients = in_place, in_place_matched, in_place_coefficients
        fitted = transform.apply(mean + (self.every_mode @ torch.as_tensor(coefficients)).numpy())
        return transform, matched, coefficients, supported_share(model.faces, fitted, points[polish], self.facing,
                                                                 TOLERANCE)


def refine_pose(model: StatModel, scan: Scan, start: Similarity, seed: int = 0) -> PoseEstimate:
    """``start`` (model → scan, e.g. placed by landmarks) polished like :func:`estimate_pose`'s
    best pose: a rigid pose and every coefficient by Gauss–Newton on the scan, the scale snapped to
    the unit nearest ``start``'s (:func:`landmark_units`; the person's size is the modes' to
    explain). Landmarks on part of a face tilt their similarity by degrees and scale it by ±10%,
    which no fit of the model's modes can undo (docs/studies.md §15: half a face, 10° and 20 mm
    held-out error). The
    estimate's ``score`` is the polished pose's and ``runner_up`` 1 (no other pose is searched)."""
    frame = model.frame
    centroid = scan.points.mean(axis=0)
    units = landmark_units(start.scale)
    points = (scan.points - centroid) / (units * frame.scale)
    in_units = to_unit_frames(start, frame, centroid, units)
    mean = frame.to_unit(model.template)
    rng = np.random.default_rng(seed)
    polish = rng.choice(len(points), min(POLISH_SUBSAMPLE, len(points)), replace=False)
    transform, score, matched, coefficients = polish_pose(Matcher(model.faces, mean), mean, scaled_modes(model, frame),
                                                          points[polish], scan.normals[polish], in_units)
    return PoseEstimate(to_scan_frame(transform, frame, centroid, units), score, matched, 1.0, units, coefficients)


def near(pose: Similarity, other: Similarity) -> bool:
    """Whether two poses (unit frames) are within DISTINCT_DEGREES and NEAR_OFFSET of each other."""
    return (angle_between(pose.rotation, other.rotation) < DISTINCT_DEGREES
            and float(np.linalg.norm(pose.translation - other.translation)) < NEAR_OFFSET)
