"""Non-rigid registration of a model's template to a (partial) scan: the library entry point."""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import torch

from statfit.geometry.align import Similarity, icp, initial_guess, umeyama
from statfit.geometry.closest import ClosestPointQuery
from statfit.geometry.metrics import inside_distance
from statfit.core.device import resolve_device
from statfit.errors import StatfitError, StatfitWarning
from statfit.core.fit import StageTimer
from statfit.structures.frame import UNIT_MISMATCH_FACTOR, Frame
from statfit.registration.pose.hypotheses import DISTINCT_DEGREES
from statfit.registration.pose.search import CLUTTER_MATCHED, estimate_pose, refine_pose
from statfit.registration.hair import hair_points
from statfit.core.methods import (Fallback, fallback as method_fallback, landmark_weight as method_landmark_weight,
                                  resolve)
from statfit.core.settings import FitSpace, Settings
from statfit.model.params import project
from statfit.model.statmodel import StatModel, face_triangles, region_triangles, scalp_triangles
from statfit.objectives.landmarks import LandmarkObjective, WithLandmarks
from statfit.objectives.scan import ScanObjective
from statfit.structures.scan import Scan, sample_size
from statfit.core.stages import Fit, PipelineResult, run_stages
from statfit.core.threads import choose_threads, intra_op_threads

ALIGNMENTS = ("auto", "none", "rigid", "similarity")
# No scan in any length unit (metres to micrometres) has coordinates beyond this.
IMPLAUSIBLE_COORDINATE = 1e9
# Median scan-to-template distance (in model RMS radii) above which the scan is "far" from the model.
FAR_DISTANCE = 0.25
ROBUST_ALIGNMENT_ROUNDS = 10


def check_scan(points: np.ndarray, source: str = "scan") -> np.ndarray:
    """Validate an (M, 3) point array: enough points, all finite."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise StatfitError(f"{source}: expected points of shape (M, 3), got {points.shape}")
    if len(points) == 0:
        raise StatfitError(f"{source} has no points")
    if not np.isfinite(points).all():
        raise StatfitError(f"{source} has NaN or infinite coordinates ({int((~np.isfinite(points)).any(axis=1).sum())} points)")
    if len(points) < 10:
        raise StatfitError(f"{source} has only {len(points)} points; need at least 10")
    largest = float(np.abs(points).max())
    if largest > IMPLAUSIBLE_COORDINATE:
        raise StatfitError(f"{source} has coordinates as large as {largest:.3g}: not a scan in any length unit "
                           "(a damaged file?)")
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


def prealign(model: StatModel, scan: Scan, align: str, landmarks: np.ndarray | None = None, seed: int = 0
             ) -> tuple[Similarity, dict | None, np.ndarray | None]:
    """The model→scan transform for ``align`` in auto|none|rigid|similarity, and for auto the
    pose search's report (:mod:`statfit.registration.pose.search`) and the polished fit's coefficients
    (K,) (None otherwise); checks units first. With ``landmarks`` (L, 3), the landmark similarity is
    the start: with align auto polished on the scan (:func:`statfit.registration.pose.search.refine_pose`,
    whose report is returned), with none the result."""
    if align not in ALIGNMENTS:
        raise StatfitError(f"unknown alignment {align!r}; choose one of {', '.join(ALIGNMENTS)}")
    points = scan.points
    if landmarks is not None:
        start = landmark_alignment(model, landmarks)
        if align == "auto":
            estimate = refine_pose(model, scan, start, seed)
            return estimate.transform, {**estimate.summary(), "from_landmarks": True}, estimate.coefficients
        return (start if align == "none" else icp(model.template, model.faces, points,
                                                  align == "similarity", start=start)), None, None
    if align == "auto":
        estimate = estimate_pose(model, scan, seed)
        return estimate.transform, estimate.summary(), estimate.coefficients
    ratio = np.linalg.norm(np.ptp(points, axis=0)) / np.linalg.norm(np.ptp(model.template, axis=0))
    if align != "similarity" and not 1 / UNIT_MISMATCH_FACTOR < ratio < UNIT_MISMATCH_FACTOR:
        raise StatfitError(f"the scan is {ratio:.3g} times the model's size: are they in different units? "
                           "Rescale one, or use --align auto")
    if align == "none":
        return Similarity(), None, None
    with_scale = align == "similarity"
    start = initial_guess(model.template, points, with_scale)
    if not with_scale and np.linalg.norm(start.translation) < Frame.of(model.template).scale:
        start = Similarity()
    return icp(model.template, model.faces, points, with_scale, start=start), None, None


def fit_start(space: FitSpace, query: ClosestPointQuery, points: torch.Tensor, normals: torch.Tensor | None,
              shape: np.ndarray | None, first: Settings, trim: float) -> torch.Tensor:
    """The vertices (N, 3, fit frame) a fit starts from: the shape the pose search fitted along with
    its pose (``shape``: coefficients (K,) in standard deviations; None: no pose search, the mean).
    A closed-form first stage (Gauss–Newton, whose continuation starts from a strong prior centred
    on the mean) starts from the mean unless the mean lies far from the ``points`` (median distance
    over FAR_DISTANCE: a model whose modes also move the head, such as a body model's head, can put
    the mean centimetres away from the half a face the pose was found on); on the ICT studies the
    closed form fitted 5–7% worse from the pose's shape than from the mean, while every gradient
    method fitted better from it (docs/studies.md §19)."""
    if shape is None:
        return space.mean.clone()
    shaped = space.shape(shape)
    if first.optimizer != "gauss-newton":
        return shaped
    probe = ScanObjective(points, query, trim=trim, normals=normals)
    far = float(probe.refresh(space.mean).distance.median()) > FAR_DISTANCE
    return shaped if far else space.mean.clone()


def register(model: StatModel, points: np.ndarray | Scan, method: str = "default", *, preset: str = "tuned",
             align: str = "auto", device: str | None = None, dtype: torch.dtype = torch.float32,
             refresh_every: int = 10, trim: float = 0.05, seed: int = 0,
             on_record: Callable[[int, dict[str, float]], None] | None = None,
             timer: StageTimer | None = None, stages: tuple[Settings, ...] | None = None,
             region: str | None = None, landmarks: np.ndarray | None = None,
             on_snapshot: Callable[[int, np.ndarray], None] | None = None, threads: int | None = None,
             landmark_weight: float | None = None, clutter: bool | None = None,
             fallback: Fallback | bool | None = True, **overrides: Any) -> Fit:
    """Fit ``model`` to the scan ``points`` (M, 3), or a :class:`statfit.structures.scan.Scan` (e.g. drawn
    from a mesh scan by area), with ``method``.

    ``align``: ``auto`` finds the scan's pose, scale and power-of-ten units without landmarks and
    leaves a scan that already lies on the model where it is (:mod:`statfit.registration.pose.search`; its
    report is the result's ``pose``); ``none`` takes the scan as lying in the model's frame;
    ``rigid``/``similarity``: ICP from the centroids.

    ``region`` names a stored vertex subset: only scan points whose closest surface point lies on
    the region's triangles enter the data term, while the filter and prior still move every vertex.
    ``landmarks`` (L, 3), the scan's points for the model's landmarks (NaN = missing), pre-align the
    scan by a similarity first (refined by ICP when ``align`` is rigid or similarity), then stay a
    fit term of ``landmark_weight`` (0: the start only; None: the method's,
    :func:`statfit.core.methods.landmark_weight`; :mod:`statfit.objectives.landmarks`).
    ``clutter`` turns on the data term's rules for points off the template (normals, robust
    distance; :mod:`statfit.objectives.scan`) and, without a ``region``, leaves out the points a fit
    of the model's face alone finds to be hair and those nearest its scalp (:mod:`statfit.registration.hair`:
    hair passes every rule), or keeps the data term to the face (:func:`face_triangles`) when most
    of the scan is out there;
    ``None``: on when the automatic alignment found more than 1 − CLUTTER_MATCHED of the points
    unexplained by its fit with every mode.
    ``on_snapshot(iteration, vertices)`` receives the current vertices (N, 3), in the scan's frame,
    every 10 iterations (e.g. to trace the error against a ground truth). ``threads``: torch
    intra-op threads for the fit (default: chosen from the model's size, :mod:`statfit.core.threads`).

    ``overrides`` (iterations, lr, beta, power, lam, laplacian, solver, mode_gain) replace the
    method's settings; ``stages`` replaces the method altogether by an explicit pipeline.
    ``fallback``: True, the method's own (:func:`statfit.core.methods.fallback`: the default
    pipeline's, unless ``stages`` or ``overrides`` are given); a :class:`Fallback`; False or None: none.
    Where the fit leaves the scan points it was given farther than the fallback's residual from its
    surface on average, or its shape's code in the model is larger than the fallback's (RMS over the
    modes, standard deviations), the fallback's method refits from the same pose and its fit is
    returned (a StatfitWarning says so; the result's ``fallback`` reports both either way). The points
    are those the data term was given (the hair left out); it does not apply where the data term
    keeps to a region (``region``, or the face alone under hair): there the residual measures what
    the fit leaves out by design. Warns (StatfitWarning) when the scan is far from the model with align='none'.
    """
    scan = points if isinstance(points, Scan) else Scan.from_points(check_scan(points))
    # a dense scan: a subsample spread over it, sized from the model (statfit.structures.scan.sample_size)
    scan = scan.thinned(sample_size(model.num_vertices))
    points = check_scan(scan.points)
    if not 0 <= trim < 1:
        raise StatfitError(f"trim must lie in [0, 1), got {trim}")
    if refresh_every < 1:
        raise StatfitError(f"refresh_every must be at least 1, got {refresh_every}")
    weight = method_landmark_weight(method) if landmark_weight is None else landmark_weight
    if not (np.isfinite(weight) and 0 <= weight <= 1e6):
        raise StatfitError(f"landmark_weight must be a finite number in [0, 1e6], got {weight}")
    if fallback is True:
        fallback = None if stages is not None else method_fallback(method, preset, **overrides)
    stages = stages or resolve(method, preset, **overrides)
    torch_device = resolve_device(device, "register")
    threads = choose_threads(model.basis.size, threads)
    with intra_op_threads(threads):
        torch.manual_seed(seed)
        started = time.perf_counter()
        region_faces = None if region is None else torch.as_tensor(region_triangles(model, region),
                                                                   device=torch_device)
        transform, pose, shape = prealign(model, scan, align, landmarks, seed)
        if pose is not None and pose["ambiguous"]:
            warnings.warn(f"the scan's pose is ambiguous: the best scores {pose['score']:.3f}, another "
                          f"{DISTINCT_DEGREES:.0f}° or more away {pose['runner_up']:.3f} (0 best, 1 worst); check the "
                          "fit, or give --landmarks", StatfitWarning, stacklevel=2)
        if clutter is None:   # the pose search found points no shape of the model explains
            clutter = pose is not None and pose["matched"] < CLUTTER_MATCHED
        posed = _PosedScan(model, scan, points, transform, pose, None if preset == "paper" else shape, torch_device,
                           dtype, trim, region, region_faces, clutter, landmarks)
        timer = timer or StageTimer.for_device(torch_device)
        fit = posed.fit(stages, weight, refresh_every, timer, on_record, on_snapshot, warn_far=align == "none")
        report = None
        if fallback and fit.whole_model:
            with timer("fallback test"):
                residual, code = posed.residual(fit), posed.code(fit)
            report = {"method": fallback.method, "residual": residual, "threshold": fallback.residual,
                      "code": code, "code_threshold": fallback.code,
                      "used": bool(residual > fallback.residual or code > fallback.code)}
            if report["used"]:
                why = (f"leaves the scan {residual:.1%} of the model's radius away on average (over "
                       f"{fallback.residual:.0%})" if residual > fallback.residual else
                       f"needs {code:.1f} standard deviations per mode (over {fallback.code:g}; the model's "
                       "people need about 1)")
                warnings.warn(f"the fit {why}: a person the model cannot make, so its guess of what the scan does "
                              f"not show is unreliable; refitted with {fallback.method} (docs/method.md, \"When the "
                              "model cannot explain the scan\")", StatfitWarning, stacklevel=2)
                stages = resolve(fallback.method)
                weight = method_landmark_weight(fallback.method) if landmark_weight is None else landmark_weight
                first = fit.result.iterations
                fit = posed.fit(stages, weight, refresh_every, timer, on_record, on_snapshot, warn_far=False)
                fit.result.iterations += first
        return Fit(posed.to_scan_frame(fit.result.vertices), transform, stages, fit.result.loss,
                   time.perf_counter() - started, dict(timer.seconds), fit.result.iterations, fit.pose, threads,
                   report)


@dataclass
class _StagesRun:
    """One pipeline's fit of a posed scan: the result, the pose report with the fit's clutter
    facts, the scan points (M', 3, fit frame) its data term was given, and whether it was given
    the whole model (no region: neither the user's nor the face alone under hair)."""

    result: PipelineResult
    pose: dict | None
    points: torch.Tensor
    whole_model: bool


class _PosedScan:
    """A scan placed on the model (the pose search's or the landmarks' similarity), ready for one
    pipeline's fit or several (the fallback's refit shares the pose)."""

    def __init__(self, model: StatModel, scan: Scan, points: np.ndarray, transform: Similarity, pose: dict | None,
                 shape: np.ndarray | None, device: torch.device, dtype: torch.dtype, trim: float,
                 region: str | None, region_faces: torch.Tensor | None, clutter: bool, landmarks: np.ndarray | None):
        self.model, self.transform, self.pose, self.shape = model, transform, pose, shape
        self.trim, self.clutter, self.landmarks = trim, clutter, landmarks
        self.region, self.region_faces = region, region_faces
        self.device, self.dtype = device, dtype
        self.frame = frame = Frame.of(model.template)
        self.space = FitSpace.of(model, frame, device, dtype)
        self.points = torch.as_tensor(frame.to_unit(transform.inverse_apply(points)), dtype=dtype, device=device)
        self.normals = torch.as_tensor(scan.normals @ transform.rotation, dtype=dtype, device=device)
        self.query = ClosestPointQuery(model.faces, model.num_vertices, k=2, device=device)

    def to_scan_frame(self, x: torch.Tensor) -> np.ndarray:
        return self.transform.apply(self.frame.from_unit(x.detach().cpu().double().numpy()))

    def fit(self, stages: tuple[Settings, ...], landmark_weight: float, refresh_every: int, timer: StageTimer,
            on_record: Callable[[int, dict[str, float]], None] | None,
            on_snapshot: Callable[[int, np.ndarray], None] | None, warn_far: bool) -> _StagesRun:
        """Run ``stages`` from where their first stage starts (:func:`fit_start`), the hair left out
        where the clutter rules find it (the hair test starts where the fit does)."""
        model, space, device, trim = self.model, self.space, self.device, self.trim
        fit_points, fit_normals, region_faces = self.points, self.normals, self.region_faces
        start = fit_start(space, self.query, fit_points, fit_normals, self.shape, stages[0], trim)
        hair_share = None
        if self.clutter and self.region_faces is None and (face := face_triangles(model)) is not None:
            face = torch.as_tensor(face, device=device)
            scalp = torch.as_tensor(scalp_triangles(model), device=device)
            hair = hair_points(space, self.query, fit_points, fit_normals, face, trim, start, scalp)
            if hair is None:                    # no head under that much: fit the face alone
                region_faces = face
            else:                               # fit everything but the hair
                hair_share = float(hair.double().mean())
                fit_points, fit_normals = fit_points[~hair], fit_normals[~hair]
        pose = self.pose
        if pose is not None:
            pose = {**pose, "clutter_rules": self.clutter, "face_only": self.clutter and self.region_faces is None
                    and region_faces is not None, "hair_share": hair_share}
        objective = ScanObjective(fit_points, self.query, refresh_every=refresh_every, trim=trim,
                                  region_faces=region_faces, normals=fit_normals, clutter=self.clutter)
        median = float(objective.refresh(start).distance.median())
        if objective.kept == 0:
            raise StatfitError(f"no scan point lies closest to the region {self.region!r}: is the scan of another "
                               "part?")
        if warn_far and self.landmarks is None and median > FAR_DISTANCE:
            warnings.warn(f"the scan is far from the model (median distance {median * self.frame.scale:.3g}, "
                          f"{median:.2f} model radii); consider --align rigid", StatfitWarning, stacklevel=3)
        if self.landmarks is not None and landmark_weight > 0:
            present = present_landmarks(model, self.landmarks)
            targets = self.frame.to_unit(self.transform.inverse_apply(
                np.asarray(self.landmarks, dtype=np.float64)[present]))
            objective = WithLandmarks(objective, LandmarkObjective(
                torch.as_tensor(model.landmarks[present], device=device),
                torch.as_tensor(targets, dtype=self.dtype, device=device), landmark_weight))
        snapshot = None if on_snapshot is None else lambda it, x: on_snapshot(it, self.to_scan_frame(x))
        result = run_stages(stages, space, objective, start, on_record=on_record, on_snapshot=snapshot, timer=timer)
        return _StagesRun(result, pose, fit_points, region_faces is None)

    def residual(self, run: _StagesRun) -> float:
        """The mean distance of the scan points the fit was given to its surface, in the posed
        model's RMS radii (the fit frame's unit), points beyond its open boundary left out
        (:func:`statfit.geometry.metrics.inside_distance`); 0 if every point lies beyond."""
        distance = inside_distance(run.points.detach().cpu().double().numpy(),
                                   run.result.vertices.detach().cpu().double().numpy(), self.model.faces)
        inside = distance[np.isfinite(distance)]
        return float(inside.mean()) if inside.size else 0.0

    def code(self, run: _StagesRun) -> float:
        """The RMS over the modes of the fitted shape's code in the model (standard deviations:
        :func:`statfit.model.params.project`, the least-squares coefficients of the fit in the model's
        frame)."""
        in_model_frame = self.frame.from_unit(run.result.vertices.detach().cpu().double().numpy())
        return float(np.sqrt(np.mean(project(self.model, in_model_frame).coefficients ** 2)))
