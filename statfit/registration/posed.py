"""A scan placed on the model, ready for one pipeline's fit or several: what every fit of
:func:`statfit.registration.job.register` and :func:`statfit.registration.many.register_many` is
made of (the options checked once, the model's tensors shared, the pose searched once, the start
and the data term of each pipeline, the fallback's test)."""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import torch

from statfit.core.device import resolve_device
from statfit.core.fit import StageTimer
from statfit.core.methods import (FALLBACK_BORDER_BAND, Fallback, fallback as method_fallback,
                                  landmark_weight as method_landmark_weight, resolve)
from statfit.core.settings import FitSpace, Settings
from statfit.core.stages import PipelineResult, run_stages
from statfit.core.threads import choose_threads
from statfit.errors import DivergenceError, StatfitError, StatfitWarning
from statfit.geometry.align import Similarity
from statfit.geometry.closest import ClosestPointQuery
from statfit.geometry.metrics import inside_distance
from statfit.model.cut import NO_RIGID_MOTION, rigid_motion_share
from statfit.model.params import project
from statfit.model.statmodel import StatModel, face_triangles, region_triangles, scalp_triangles
from statfit.objectives.landmarks import LandmarkObjective, WithLandmarks
from statfit.objectives.scan import ScanObjective
from statfit.registration.hair import hair_points
from statfit.registration.pose.hypotheses import DISTINCT_DEGREES
from statfit.registration.pose.search import CLUTTER_MATCHED
from statfit.registration.prealign import check_scan, prealign, present_landmarks
from statfit.structures.scan import Scan, sample_size

# Median scan-to-template distance (in model RMS radii) above which the scan is "far" from the model.
FAR_DISTANCE = 0.25
# A fit whose vertices lie farther than this from the scan points (median, model radii) ran away.
RUNAWAY = 10.0
# A model whose modes hold less than NO_RIGID_MOTION of their variance in rigid motion (one fitted without
# it) cannot move the pose a fit was given; its closed-form stage moves it by small rigid motions of
# POSE_STD per standard deviation (RMS radii; docs/studies.md §47).
POSE_STD = 0.03


@dataclass(frozen=True)
class FitPlan:
    """What every scan of a :func:`register` call is fitted with, checked: the pipeline, the landmark
    term's weight (the fallback's too), the fallback (None: none), the data term's trim and refresh
    period, whether a fit starts from the pose search's shape (not the paper's preset), the device,
    the fit's intra-op threads and the threads the caller asked for (None: as the machine allows;
    they cap the pose search's own), and the closed form's own rigid motion (``pose_std``, RMS radii per
    standard deviation; 0: none)."""

    stages: tuple[Settings, ...]
    weight: float
    fallback: Fallback | None
    fallback_weight: float
    trim: float
    refresh_every: int
    start_from_pose: bool
    device: torch.device
    threads: int
    threads_asked: int | None
    pose_std: float


def plan_fits(model: StatModel, method: str, preset: str, stages: tuple[Settings, ...] | None,
              overrides: dict[str, Any], trim: float, refresh_every: int, landmark_weight: float | None,
              fallback: Fallback | bool | None, device: str | None, threads: int | None) -> FitPlan:
    """:func:`register`'s options checked and resolved (one line, StatfitError, for a bad one). Where
    ``model``'s modes hold (almost) no rigid motion (below NO_RIGID_MOTION of their variance: a model
    fitted without it, :func:`statfit.model.cut.fitting_model`), the closed form moves the pose by
    small rigid motions of POSE_STD."""
    if not 0 <= trim < 1:
        raise StatfitError(f"trim must lie in [0, 1), got {trim}")
    if refresh_every < 1:
        raise StatfitError(f"refresh_every must be at least 1, got {refresh_every}")
    weight = method_landmark_weight(method) if landmark_weight is None else landmark_weight
    if not (np.isfinite(weight) and 0 <= weight <= 1e6):
        raise StatfitError(f"landmark_weight must be a finite number in [0, 1e6], got {weight}")
    if fallback is True:
        fallback = None if stages is not None else method_fallback(method, preset, **overrides)
    fallback = fallback or None
    fallback_weight = weight if fallback is None or landmark_weight is not None else \
        method_landmark_weight(fallback.method)
    return FitPlan(stages or resolve(method, preset, **overrides), weight, fallback, fallback_weight, trim,
                   refresh_every, preset != "paper", resolve_device(device, "register"),
                   choose_threads(model.basis.size, threads), threads,
                   POSE_STD if rigid_motion_share(model) < NO_RIGID_MOTION else 0.0)


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


def model_tensors(model: StatModel, plan: FitPlan, dtype: torch.dtype) -> tuple[FitSpace, ClosestPointQuery]:
    """The model in the fit frame as tensors (with ``plan``'s rigid motion for the closed form), and its
    closest-point query: what every fit of the model on ``plan``'s device shares."""
    device = plan.device
    return (FitSpace.of(model, model.frame, device, dtype, plan.pose_std),
            ClosestPointQuery(model.faces, model.num_vertices, k=2, device=device))


@dataclass
class FitSetup:
    """A posed scan's fit, ready to run: the scan's data term, its landmark term (None: none), the
    start (N, 3, fit frame), the pose report with the fit's clutter facts, the scan points
    (M', 3) the data term was given and whether it was given the whole model."""

    scan: ScanObjective
    landmarks: LandmarkObjective | None
    start: torch.Tensor
    pose: dict | None
    points: torch.Tensor
    whole_model: bool

    @property
    def objective(self) -> ScanObjective | WithLandmarks:
        return self.scan if self.landmarks is None else WithLandmarks(self.scan, self.landmarks)

    def ran(self, result: PipelineResult) -> _StagesRun:
        """The run of ``result``; raises DivergenceError for a fit that ran away (finite, but most of
        its vertices more than RUNAWAY model radii from the scan points: a step size far too large)."""
        reach = float((result.vertices.detach() - self.points.mean(dim=0)).norm(dim=-1).median())
        if not reach <= RUNAWAY:
            raise DivergenceError(f"the fit diverged: its vertices lie {reach:.3g} model radii from the scan "
                                  "(median; step size too large?)")
        return _StagesRun(result, self.pose, self.points, self.whole_model)


@dataclass
class _StagesRun:
    """One pipeline's fit of a posed scan: the result, the pose report with the fit's clutter
    facts, the scan points (M', 3, fit frame) its data term was given, and whether it was given
    the whole model (no region: neither the user's nor the face alone under hair)."""

    result: PipelineResult
    pose: dict | None
    points: torch.Tensor
    whole_model: bool


class PosedScan:
    """A scan placed on the model (the pose search's or the landmarks' similarity), ready for one
    pipeline's fit or several (the fallback's refit shares the pose)."""

    def __init__(self, model: StatModel, scan: Scan, points: np.ndarray, transform: Similarity, pose: dict | None,
                 shape: np.ndarray | None, device: torch.device, dtype: torch.dtype, trim: float, refresh_every: int,
                 region: str | None, region_faces: torch.Tensor | None, clutter: bool, landmarks: np.ndarray | None,
                 shared: tuple[FitSpace, ClosestPointQuery]):
        self.model, self.transform, self.pose, self.shape = model, transform, pose, shape
        self.trim, self.refresh_every, self.clutter, self.landmarks = trim, refresh_every, clutter, landmarks
        self.region, self.region_faces = region, region_faces
        self.device, self.dtype = device, dtype
        self.frame = frame = model.frame
        self.space, self.query = shared
        self.points = torch.as_tensor(frame.to_unit(transform.inverse_apply(points)), dtype=dtype, device=device)
        self.normals = torch.as_tensor(scan.normals @ transform.rotation, dtype=dtype, device=device)

    @classmethod
    def of(cls, model: StatModel, points: np.ndarray | Scan, plan: FitPlan, align: str, landmarks: np.ndarray | None,
           clutter: bool | None, region: str | None, seed: int, dtype: torch.dtype,
           shared: tuple[FitSpace, ClosestPointQuery] | None = None) -> PosedScan:
        """The scan checked (a dense one thinned), placed on the model (:func:`prealign`) and set up
        for fits with ``plan``; ``shared``: the model's :func:`model_tensors`, if the caller keeps
        them (a batch)."""
        scan = points if isinstance(points, Scan) else Scan.from_points(check_scan(points))
        # a dense scan: a subsample spread over it, sized from the model (statfit.structures.scan.sample_size)
        scan = scan.thinned(sample_size(model.num_vertices))
        points = check_scan(scan.points)
        region_faces = None if region is None else torch.as_tensor(region_triangles(model, region),
                                                                   device=plan.device)
        transform, pose, shape = prealign(model, scan, align, landmarks, seed, plan.threads_asked)
        if pose is not None and pose["ambiguous"]:
            warnings.warn(f"the scan's pose is ambiguous: the best scores {pose['score']:.3f}, another "
                          f"{DISTINCT_DEGREES:.0f}° or more away {pose['runner_up']:.3f} (0 best, 1 worst); check the "
                          "fit, or give --landmarks", StatfitWarning, stacklevel=3)
        if clutter is None:   # the pose search found points no shape of the model explains
            clutter = pose is not None and pose["matched"] < CLUTTER_MATCHED
            if clutter and region is None and face_triangles(model) is None:
                warnings.warn(f"the model explains {pose['matched']:.0%} of the scan's points (clutter such as hair, "
                              "neck or shoulders, or a person outside the model) and has neither landmarks nor a "
                              "face region to keep the fit to the face: give it either (statfit model import MODEL "
                              "--landmarks FILE, or --masks FILE with a face region)", StatfitWarning, stacklevel=3)
        return cls(model, scan, points, transform, pose, shape if plan.start_from_pose else None, plan.device, dtype,
                   plan.trim, plan.refresh_every, region, region_faces, clutter, landmarks,
                   shared or model_tensors(model, plan, dtype))

    def to_scan_frame(self, x: torch.Tensor) -> np.ndarray:
        return self.transform.apply(self.frame.from_unit(x.detach().cpu().double().numpy()))

    def setup(self, stages: tuple[Settings, ...], landmark_weight: float, warn_far: bool) -> FitSetup:
        """What a fit of ``stages`` starts from (:func:`fit_start`) and its objective, the hair left
        out where the clutter rules find it (the hair test starts where the fit does)."""
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
        scan = ScanObjective(fit_points, self.query, refresh_every=self.refresh_every, trim=trim,
                             region_faces=region_faces, normals=fit_normals, clutter=self.clutter)
        median = float(scan.refresh(start).distance.median())
        if scan.kept == 0:
            raise StatfitError(f"no scan point lies closest to the region {self.region!r}: is the scan of another "
                               "part?")
        if warn_far and self.landmarks is None and median > FAR_DISTANCE:
            warnings.warn(f"the scan is far from the model (median distance {median * self.frame.scale:.3g}, "
                          f"{median:.2f} model radii); consider --align rigid", StatfitWarning, stacklevel=4)
        landmarks = None
        if self.landmarks is not None and landmark_weight > 0:
            present = present_landmarks(model, self.landmarks)
            targets = self.frame.to_unit(self.transform.inverse_apply(
                np.asarray(self.landmarks, dtype=np.float64)[present]))
            landmarks = LandmarkObjective(torch.as_tensor(model.landmarks[present], device=device),
                                          torch.as_tensor(targets, dtype=self.dtype, device=device), landmark_weight)
        return FitSetup(scan, landmarks, start, pose, fit_points, region_faces is None)

    def fit(self, stages: tuple[Settings, ...], landmark_weight: float, timer: StageTimer,
            on_record: Callable[[int, dict[str, float]], None] | None,
            on_snapshot: Callable[[int, np.ndarray], None] | None, warn_far: bool) -> _StagesRun:
        """Run ``stages`` from :meth:`setup`'s start."""
        setup = self.setup(stages, landmark_weight, warn_far)
        snapshot = None if on_snapshot is None else lambda it, x: on_snapshot(it, self.to_scan_frame(x))
        result = run_stages(stages, self.space, setup.objective, setup.start, on_record=on_record,
                            on_snapshot=snapshot, timer=timer)
        return setup.ran(result)

    def fallback_test(self, run: _StagesRun, fallback: Fallback) -> dict:
        """Whether ``run`` calls for ``fallback``: the report (method, residual and threshold, code
        and its threshold, used); a StatfitWarning says why where it does."""
        residual, code = self.residual(run), self.code(run)
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
                          "model cannot explain the scan\")", StatfitWarning, stacklevel=3)
        return report

    def residual(self, run: _StagesRun) -> float:
        """The mean distance of the scan points the fit was given to its surface, in the posed
        model's RMS radii (the fit frame's unit), leaving out the points whose nearest surface point
        lies on its open boundary or within FALLBACK_BORDER_BAND of it
        (:func:`statfit.geometry.metrics.inside_distance`); 0 if every point is left out."""
        distance = inside_distance(run.points.detach().cpu().double().numpy(),
                                   run.result.vertices.detach().cpu().double().numpy(), self.model.faces,
                                   border_band=FALLBACK_BORDER_BAND)
        inside = distance[np.isfinite(distance)]
        return float(inside.mean()) if inside.size else 0.0

    def code(self, run: _StagesRun) -> float:
        """The RMS over the modes of the fitted shape's code in the model (standard deviations:
        :func:`statfit.model.params.project`, the least-squares coefficients of the fit in the model's
        frame)."""
        in_model_frame = self.frame.from_unit(run.result.vertices.detach().cpu().double().numpy())
        return float(np.sqrt(np.mean(project(self.model, in_model_frame).coefficients ** 2)))
