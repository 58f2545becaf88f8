"""Inverse rendering: fit a model's template to one normal map. The library entry point of
``statfit render``.

The fit runs in the model's unit frame (:class:`statfit.structures.frame.Frame`); the camera is moved into
that frame, and a pose found by the initial alignment is folded into the camera, so the filters
act on the model in its own orientation. Target normals are compared in camera space.

Alignment (rigid / similarity), on the map reduced to about 256 px: Adam on the model's
coefficients (weak prior), once jointly with a pose and once alone; the pose is kept where it
lowers the objective by 10%, or where the silhouettes overlapped so poorly that the search had to
start from a rough move matching their centroids. The translation along the viewing axis stays
fixed: from one view it trades off against the shape's size (left free, it drifted by most of a
head radius on test cases); use similarity to estimate a scale. docs/method.md has the numbers.
"""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import torch

from statfit.geometry.align import Similarity, compose
from statfit.geometry.metrics import of_part_of_a_subject
from statfit.errors import StatfitError, StatfitWarning
from statfit.core.fit import StageTimer
from statfit.structures.frame import Frame, surface_vertices
from statfit.structures.normal_map import NormalMap
from statfit.core.methods import resolve
from statfit.core.settings import FitSpace, Settings
from statfit.model.cut import OFF_ITS_PLACE, PlaceRule, fitting_model_and_rule, rigid_motion_distance
from statfit.model.statmodel import StatModel, region_triangles
from statfit.objectives.normals import NormalMapObjective
from statfit.objectives.weights import SILHOUETTE_WEIGHT
from statfit.core.runaway import check_not_runaway
from statfit.render.framing import camera_space_normals, check_framing, check_normals_face_camera, checked_init
from statfit.render.visibility import alignment_visibility, visibility_options
from statfit.core.pose import camera_in_frame, fit_pose
from statfit.core.device import resolve_device
from statfit.renderer import Camera, MeshAdjacency, rasterize
from statfit.core.stages import Fit, PipelineResult, run_stages
from statfit.core.threads import choose_threads, intra_op_threads

ALIGNMENTS = ("none", "rigid", "similarity")
SILHOUETTES = ("auto", "two-sided", "one-sided", "covering")
POSE_ITERATIONS = 200
POSE_LR = 0.01
# The alignment stops once its best value fell by less than this share over 25 iterations (it settles
# by 100-175 of its 200 on the rendering study's cases: docs/studies.md §22).
POSE_SETTLE = 1e-3
# The rigid alignment's step on the model's coefficients (standard deviations), 5x the pose's: at
# the pose's step they move at most ~2 in its 200 steps, short of what bodies far from the mean need
# (a 1.21 m body: -1.8 on the size mode alone). On the body study every method ends closer from this
# start (the old default 16.2 -> 12.2 mm); faces are equal (docs/studies.md §13, session 9).
SHAPE_LR = 0.05
GOOD_OVERLAP = 0.7
MIN_COVERED_PIXELS = 16     # the model's covered pixels to centre it, at least
POSE_GAIN = 0.1
# Floats the rasteriser and objective touch per pixel and iteration (for the thread choice).
RENDER_FLOATS_PER_PIXEL = 16
ALIGN_SIZE = 256  # the alignment runs on the map reduced by an integer factor to about this size


def render_stages(method: str = "default", preset: str = "tuned", region: str | None = None,
                  **overrides: Any) -> tuple[Settings, ...]:
    """The stages of ``method`` for inverse rendering. With a ``region``, ``default`` is the
    3,000-iteration hybrid filter (``--method hybrid``): the fast default schedule drifts when the
    data term sees only part of the map (a face under a 2 cm cap: face error 18.3 mm after 450
    iterations vs 6.9 mm for the hybrid; docs/studies.md §11)."""
    if region is not None and method == "default":
        method = "hybrid"
    return resolve(method, preset, job="render", **overrides)


def _centring_guess(template: torch.Tensor, faces: torch.Tensor, camera: Camera, mask: np.ndarray,
                    with_scale: bool) -> Similarity | None:
    """The starting point of the pose search: None (no move) where the template's silhouette
    overlaps the target's well (IoU ≥ ``GOOD_OVERLAP``), else a move parallel to the image plane
    (and, ``with_scale``, a scale about the centroid) that puts the template's silhouette
    centroid on the target's (and matches their areas). A template that covers almost no pixel
    (e.g. in metres before a camera in millimetres) is measured by its projected bounding box."""
    with torch.no_grad():
        covered = (rasterize(template, faces, camera).triangle >= 0).cpu().numpy()
        pixels, depths = camera.project(template.detach().double())
    rows, cols = np.nonzero(mask)
    target_centre = np.array([cols.mean() + 0.5, rows.mean() + 0.5])
    if covered.sum() >= MIN_COVERED_PIXELS:
        if (covered & mask).sum() >= GOOD_OVERLAP * (covered | mask).sum():
            return None
        model_rows, model_cols = np.nonzero(covered)
        model_centre = np.array([model_cols.mean() + 0.5, model_rows.mean() + 0.5])
        area_ratio = mask.sum() / covered.sum()
    elif with_scale and bool((depths > 0).all()):
        low, high = pixels.min(dim=0).values.cpu().numpy(), pixels.max(dim=0).values.cpu().numpy()
        model_centre = (low + high) / 2
        area_ratio = (np.ptp(cols) + 1) * (np.ptp(rows) + 1) / max(float(np.prod(high - low)), 1e-300)
        rough = _similarity_move(_drawn(template, faces), camera, model_centre, target_centre, area_ratio,
                                 float(depths.mean()))
        moved = torch.as_tensor(rough.apply(template.detach().double().cpu().numpy()), dtype=template.dtype,
                                device=template.device)
        refined = _centring_guess(moved, faces, camera, mask, with_scale)  # now measured on its silhouette
        return rough if refined is None else compose(refined, rough)
    else:
        raise StatfitError("the model is not in the camera's view: are the model and the camera in the same frame "
                           "and units? (--align similarity estimates a scale)")
    return _similarity_move(_drawn(template, faces), camera, model_centre, target_centre,
                            area_ratio if with_scale else 1.0, float(depths.mean()))


def _drawn(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """The vertices (M, 3) of ``vertices`` (N, 3) that triangles use, detached (:func:`surface_vertices`):
    the pose turns and scales about their centroid, wherever a vertex no face uses lies."""
    return surface_vertices(vertices.detach(), faces.cpu().numpy())


def _similarity_move(drawn: torch.Tensor, camera: Camera, model_centre: np.ndarray, target_centre: np.ndarray,
                     area_ratio: float, depth: float) -> Similarity:
    """Scale about the centroid of ``drawn`` (M, 3) by sqrt(area_ratio), then move parallel to the image plane at
    ``depth`` so that the pixel ``model_centre`` lands on ``target_centre``."""
    scale = float(np.sqrt(area_ratio))
    K_inv = np.linalg.inv(camera.K.numpy())
    shift = (K_inv @ [*target_centre, 1.0] - K_inv @ [*model_centre, 1.0]) * depth
    shift[2] = 0.0
    centre = drawn.double().mean(dim=0).cpu().numpy()
    return Similarity(scale, np.eye(3), (1 - scale) * centre + camera.rotation.numpy().T @ shift)


def reconstruct(model: StatModel, normal_map: NormalMap, camera: Camera, method: str = "default", *,
                preset: str = "tuned", normal_space: str = "world", normal_convention: str = "opencv",
                align: str = "rigid", init: np.ndarray | None = None, device: str | None = None,
                dtype: torch.dtype = torch.float32, silhouette_weight: float = SILHOUETTE_WEIGHT, seed: int = 0,
                on_record: Callable[[int, dict[str, float]], None] | None = None,
                timer: StageTimer | None = None, stages: tuple[Settings, ...] | None = None,
                region: str | None = None, on_snapshot: Callable[[int, np.ndarray], None] | None = None,
                threads: int | None = None, silhouette: str = "auto", rigid_modes: str = "auto",
                **overrides: Any) -> Fit:
    """Fit ``model`` to ``normal_map`` seen by ``camera`` with ``method``.

    ``init`` (N, 3): start from these vertices (world frame) instead of the template.
    ``region``: a stored vertex subset; after the alignment (which uses the whole map), the normal
    term counts only pixels showing the region's triangles and the silhouette is not used (the
    outline belongs to the whole mesh); the filter and prior still move every vertex.
    ``on_snapshot(iteration, vertices)`` receives the current vertices (N, 3, world frame) every 10
    iterations of the fit (e.g. to trace the error against a ground truth). ``threads``: torch
    intra-op threads (default: chosen from the model's and the map's sizes, :mod:`statfit.core.threads`).
    ``overrides`` replace the method's settings (see :func:`statfit.core.methods.resolve`); ``stages``
    replaces the method by an explicit pipeline. ``silhouette``: ``two-sided`` (the coverage matches
    the map's mask), ``one-sided`` (only coverage outside the mask counts: for a model of part of the
    subject), ``covering`` (only mask left uncovered counts: for a map of part of the subject, a face
    cut out by a skin mask fitted with a head) or ``auto``: one-sided for a model whose surface faces
    one way (:func:`one_sided_silhouette`), else two-sided (a map cannot tell a cut outline from the
    subject's: docs/studies.md §24). ``rigid_modes``: fit the model's modes as given or without their
    rigid motion (:func:`statfit.model.cut.fitting_model`; ``auto``: without it where it is most of
    what they do and ``align`` finds the pose, or where the alignment moved the model off the place
    its modes give its people, :func:`posed_view`).
    """
    model, place_rule = fitting_model_and_rule(model, rigid_modes, finds_pose=align != "none")
    stages = checked_stages(model, align, silhouette, silhouette_weight, stages, method, preset, region, overrides)
    torch_device = resolve_device(device, "render")
    threads = choose_threads(model.basis.size + RENDER_FLOATS_PER_PIXEL * normal_map.mask.size, threads)
    with intra_op_threads(threads):
        torch.manual_seed(seed)
        started = time.perf_counter()
        timer = timer or StageTimer.for_device(torch_device)
        view = posed_view(model, place_rule, normal_map, camera, torch_device, dtype, normal_space=normal_space,
                          normal_convention=normal_convention, align=align, init=init,
                          silhouette_weight=silhouette_weight, silhouette=silhouette, region=region, timer=timer,
                          **visibility_options(preset, torch_device))
        snapshot = None if on_snapshot is None else lambda it, x: on_snapshot(it, view.to_world(x))
        result = run_stages(stages, view.space, view.objective, view.start, on_record=on_record,
                            on_snapshot=snapshot, timer=timer)
        return view.fitted(result, stages, time.perf_counter() - started, timer, threads)


def checked_stages(model: StatModel, align: str, silhouette: str, silhouette_weight: float,
                   stages: tuple[Settings, ...] | None, method: str, preset: str, region: str | None,
                   overrides: dict[str, Any]) -> tuple[Settings, ...]:
    """The stages of a render fit (``stages``, or ``method``'s), its options that every map's fit
    shares checked first (StatfitError)."""
    silhouette_sides(silhouette, model)
    if align not in ALIGNMENTS:
        raise StatfitError(f"unknown alignment {align!r}; choose one of {', '.join(ALIGNMENTS)}")
    if not (np.isfinite(silhouette_weight) and silhouette_weight >= 0):
        raise StatfitError(f"silhouette_weight must be a finite number ≥ 0, got {silhouette_weight}")
    return stages or render_stages(method, preset, region, **overrides)


@dataclass
class PosedView:
    """A normal map's fit set up in the model's unit frame (after the alignment): the fit space,
    the data term and the start (N, 3); the map's target normals (H, W, 3) and mask (H, W) on the
    device, the camera with the pose folded in, and what the term was made with (``options``), so
    that views of one model can be fitted together (:mod:`statfit.render.many`)."""

    space: FitSpace
    objective: NormalMapObjective
    start: torch.Tensor
    frame: Frame
    pose: Similarity
    target: torch.Tensor
    mask: torch.Tensor
    camera: Camera
    options: dict[str, Any]
    rigid_free: bool = False    # fitted without the modes' rigid motion by :func:`posed_view`'s rule

    @classmethod
    def of(cls, model: StatModel, normal_map: NormalMap, camera: Camera, device: torch.device, dtype: torch.dtype, *,
           normal_space: str = "world", normal_convention: str = "opencv", align: str = "rigid",
           init: np.ndarray | None = None, silhouette_weight: float = SILHOUETTE_WEIGHT, silhouette: str = "auto",
           region: str | None = None, timer: StageTimer | None = None, visibility_every: int = 1,
           visibility_moved: float | None = None, pose_from: Similarity | None = None) -> PosedView:
        """Check the map and the framing, find the pose (``align``; from ``pose_from``, a pose an
        earlier alignment found, instead of the silhouettes' centring) and set up the data terms."""
        sides = silhouette_sides(silhouette, model)
        one_sided, covering = sides == "one-sided", sides == "covering"
        timer = timer or StageTimer.for_device(device)
        start_shape = model.template if init is None else checked_init(init, model)
        check_framing(surface_vertices(start_shape, model.faces), camera, normal_map.mask, align)
        frame = model.frame
        space = FitSpace.of(model, frame, device, dtype)
        in_camera = camera_space_normals(normal_map, camera, normal_space, normal_convention)
        check_normals_face_camera(in_camera, normal_map, camera, normal_space, normal_convention)
        target = torch.as_tensor(in_camera, dtype=dtype, device=device)
        mask = torch.as_tensor(normal_map.mask, device=device)
        faces = torch.as_tensor(model.faces, dtype=torch.long, device=device)
        x0 = torch.as_tensor(frame.to_unit(start_shape), dtype=dtype, device=device)
        region_faces = None if region is None else torch.as_tensor(region_triangles(model, region), device=device)
        adjacency = MeshAdjacency.from_faces(faces)
        pose = Similarity()
        if align != "none":
            with timer("alignment"):
                unit_camera = camera_in_frame(camera, frame)
                guess = pose_from or _centring_guess(x0, faces, unit_camera, normal_map.mask, align == "similarity")
                coarse = NormalMapObjective(*downsampled(target, mask, unit_camera, ALIGN_SIZE), faces,
                                            silhouette_weight, adjacency, one_sided=one_sided, covering=covering,
                                            **alignment_visibility(visibility_every, visibility_moved))
                pose, x0 = _align(x0, coarse, space, guess, align == "similarity", unit_camera.rotation[2].to(dtype),
                                  _drawn(x0, faces).mean(dim=0))
        posed_camera = camera_in_frame(camera, frame, pose)
        options = dict(faces=faces, silhouette_weight=silhouette_weight if region is None else 0.0,
                       adjacency=adjacency, region_faces=region_faces, one_sided=one_sided, covering=covering,
                       visibility_every=visibility_every, visibility_moved=visibility_moved)
        objective = NormalMapObjective(target, mask, posed_camera, **options)
        return cls(space, objective, x0, frame, pose, target, mask, posed_camera, options)

    def moved_by(self, model: StatModel) -> float:
        """How far the alignment moved ``model`` (the model this view was made with) off its place, in
        standard deviations of its modes' rigid motion (:func:`statfit.model.cut.rigid_motion_distance`)."""
        centroid = self.frame.to_unit(model.template).mean(axis=0)
        shift = (self.pose.scale * self.pose.rotation @ centroid + self.pose.translation - centroid) * self.frame.scale
        return rigid_motion_distance(model, self.pose.rotation, shift)

    def to_world(self, x: torch.Tensor) -> np.ndarray:
        """Unit-frame vertices (N, 3) in the world frame (float64)."""
        return self.frame.from_unit(self.pose.apply(x.detach().cpu().double().numpy()))

    def fitted(self, result: PipelineResult, stages: tuple[Settings, ...], seconds: float, timer: StageTimer,
               threads: int) -> Fit:
        """The fit that ``result`` (from ``start``) is, in the world frame; DivergenceError where it ran away
        (:func:`statfit.core.runaway.check_not_runaway`)."""
        check_not_runaway(self.start, result.vertices, self.camera, self.mask.cpu().numpy())
        to_unit = Similarity(1.0 / self.frame.scale, np.eye(3), -self.frame.center / self.frame.scale)
        from_unit = Similarity(self.frame.scale, np.eye(3), self.frame.center)
        return Fit(self.to_world(result.vertices), compose(from_unit, compose(self.pose, to_unit)), stages,
                   result.loss, seconds, dict(timer.seconds), result.iterations, threads=threads)


def posed_view(model: StatModel, place_rule: PlaceRule | None, normal_map: NormalMap, camera: Camera,
               device: torch.device, dtype: torch.dtype, **options: Any) -> PosedView:
    """:meth:`PosedView.of`; where there is a ``place_rule`` (:func:`statfit.model.cut.fitting_model_and_rule`)
    and the alignment moved the model more than OFF_ITS_PLACE standard deviations of its modes' rigid
    motion, made again with the rule's model without that motion, its alignment starting from the
    pose found (a StatfitWarning says so): the person is not where the model places its people, so
    that motion would only trade with the pose (docs/studies.md §46)."""
    view = PosedView.of(model, normal_map, camera, device, dtype, **options)
    if place_rule is not None and (distance := view.moved_by(model)) > OFF_ITS_PLACE:
        warnings.warn(f"the alignment moved the model {distance:.1f} standard deviations of its modes' rigid motion "
                      "off where they place its people: the fit uses its modes without their rigid motion "
                      "(--rigid-modes keep: as built)", StatfitWarning, stacklevel=3)
        view = PosedView.of(place_rule.rigid_free, normal_map, camera, device, dtype, pose_from=view.pose, **options)
        view.rigid_free = True
    return view


def silhouette_sides(silhouette: str, model: StatModel) -> str:
    """``silhouette`` (auto, two-sided, one-sided, covering) as the term ``model`` gets: auto resolved."""
    if silhouette not in SILHOUETTES:
        raise StatfitError(f"unknown silhouette {silhouette!r}; choose one of {', '.join(SILHOUETTES)}")
    if silhouette == "auto":
        return "one-sided" if one_sided_silhouette(model) else "two-sided"
    return silhouette


def one_sided_silhouette(model: StatModel) -> bool:
    """Whether ``auto`` gives ``model`` the one-sided silhouette: its mean shape is of part of a subject
    (:func:`statfit.geometry.metrics.of_part_of_a_subject`)."""
    return of_part_of_a_subject(model.template, model.faces)


def downsampled(normals: torch.Tensor, mask: torch.Tensor, camera: Camera, size: int
                ) -> tuple[torch.Tensor, torch.Tensor, Camera]:
    """The map reduced by the integer factor f = min(H, W) // ``size`` (≥ 1): f×f blocks, a block
    is foreground where at least half its pixels are, with their mean normal renormalised; the
    camera's K scaled by 1/f (the last rows/columns that do not fill a block are dropped)."""
    factor = max(1, min(mask.shape) // size)
    if factor == 1:
        return normals, mask, camera
    height, width = mask.shape[0] // factor, mask.shape[1] // factor
    blocks = lambda image: image[: height * factor, : width * factor].reshape(  # noqa: E731
        height, factor, width, factor, -1).sum(dim=(1, 3))
    covered = blocks(mask[..., None].to(normals.dtype))[..., 0]
    summed = blocks(normals * mask[..., None])
    coarse_mask = covered >= factor * factor / 2
    length = summed.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(normals.dtype).tiny)
    coarse = torch.where(coarse_mask[..., None], summed / length, 0.0)
    K = camera.K.clone()
    K[:2] /= factor
    return coarse, coarse_mask, Camera(width, height, K, camera.world_to_camera)


def _align(start: torch.Tensor, objective: NormalMapObjective, space: FitSpace, guess: Similarity | None,
           with_scale: bool, view_axis: torch.Tensor, centre: torch.Tensor) -> tuple[Similarity, torch.Tensor]:
    """The model → unit-frame pose, turning and scaling about ``centre`` (3,), and the start shape for
    the fit.

    The model's coefficients are fitted jointly with the pose (so that the pose does not absorb
    differences of shape; under a rigid pose at the step SHAPE_LR), and, as a reference, alone
    with the pose held at ``guess``; the pose is kept only where it lowers the objective by
    ``POSE_GAIN`` or more (from one view, small rotations trade off against expressions and
    identity), or where the search had to start from a rough ``guess`` (None: the silhouettes
    overlapped, no move was needed)."""
    basis = (space.basis_t * space.std[:, None]).view(len(space.std), -1, 3)
    # with a scale, the size mode trades against it: the coefficients keep the pose's step
    common = dict(iterations=POSE_ITERATIONS, lr=POSE_LR, settle=POSE_SETTLE, start=guess, fixed_axis=view_axis,
                  shape_basis=basis, shape_lr=POSE_LR if with_scale else SHAPE_LR, centre=centre)
    moved = fit_pose(start, objective, with_scale=with_scale, **common)
    if guess is not None:
        return moved.pose, moved.shape  # the silhouettes disagreed: the rough guess needs refining
    objective.reset()       # a reused visibility would be where the first search ended, not at ``start``
    still = fit_pose(start, objective, move=False, **common)
    chosen = moved if moved.loss < (1.0 - POSE_GAIN) * still.loss else still
    return chosen.pose, chosen.shape
